"""PHYRE-style planning with a task-success classifier on SlotFormer rollouts.

Protocol (SlotFormer Section 4.4; embedded tasks of data/convert/phyre_like.py):

1. SAVi and SlotFormer are trained on videos of candidate actions on the
   training tasks (data split 'train').
2. For a (task, action) pair the red ball is drawn into the first frame,
   SAVi encodes that frame, and SlotFormer rolls the slots out. The success
   classifier (modules/readouts.PhyreReadout) sees ``[first-frame slots,
   rolled-out slots]`` at ``readout.selected_steps`` ('rollout'), or the
   first-frame slots alone ('first_frame', the paper's SAVi baseline). The
   official test-time code feeds zero-padded frames here by mistake; we feed
   the rollout, as the paper describes.
3. ``train_readout``: classifiers are fitted on the training tasks' candidates
   (all solving ones plus ``negatives_per_task`` failing ones per task) and the
   epoch is chosen by AUCCESS on held-out *dev* training tasks (PHYRE's
   create_dev_set), never on test tasks.
4. ``plan``: every candidate of every test task is ranked by the classifier;
   AUCCESS (tasks/planning.py) next to random ranking and the oracle
   (simulated labels).

SlotFormer's rollout starts from the first frame alone
(``slotformer.burn_in`` = 1); with ``slotformer.max_context`` > 1 its context
then grows with its own predictions (the official PHYRE model, 6 frames).

The real PHYRE layout (``config.data.name == 'phyre'``) has rendered
rollouts instead of a simulator: tasks/phyre_rendered.py, dispatched from
``train_readout`` and ``plan`` here.

Workdir: ``planning/<condition>/seed_<s>/{params.msgpack, selection.json}``,
``planning/results.json``, ``planning/results.md``.
"""

from __future__ import annotations

import functools
import json
import logging
import os
from typing import Any

from flax import serialization
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
from PIL import Image
from PIL import ImageDraw

from slotformer_jax import models
from slotformer_jax import inference
from slotformer_jax.data.convert import phyre_like
from slotformer_jax.data.sources import resolve_data_dir
from slotformer_jax.modules import readouts
from slotformer_jax.tasks import phyre_rendered
from slotformer_jax.tasks import planning
from slotformer_jax.tasks import readout as readout_lib

logger = logging.getLogger(__name__)

FIRST_FRAME, ROLLOUT = 'first_frame', 'rollout'
CONDITIONS = (FIRST_FRAME, ROLLOUT)


def planning_dir(workdir: str) -> str:
  return os.path.join(workdir, 'planning')


def build_classifier(config: ml_collections.ConfigDict, condition: str
                     ) -> readouts.PhyreReadout:
  r = config.readout
  selected = (0,) if condition == FIRST_FRAME else tuple(r.selected_steps)
  return readouts.PhyreReadout(
      selected_steps=selected, embed_dim=r.embed_dim,
      num_layers=r.num_layers, num_heads=r.num_heads,
      mlp_size=r.mlp_ratio * r.embed_dim,
      dropout_rate=r.get('dropout_rate', 0.0),
      layer_norm_epsilon=r.get('layer_norm_epsilon', 1e-6))


def task_splits(config: ml_collections.ConfigDict
                ) -> dict[str, list[phyre_like.Task]]:
  """'train', 'dev' (from the training tasks) and 'test' tasks."""
  generation = phyre_like.config_from_data_config(config.data)
  splits = phyre_like.split_tasks(generation)
  rng = np.random.default_rng([generation.seed, 19, generation.fold])
  train = list(splits['train'])
  order = rng.permutation(len(train))
  num_dev = int(round(config.readout.dev_share * len(train)))
  return {'train': [train[i] for i in sorted(order[num_dev:])],
          'dev': [train[i] for i in sorted(order[:num_dev])],
          'test': list(splits['test'])}


def first_frames(task: phyre_like.Task, actions: np.ndarray,
                 resolution: tuple[int, int]) -> np.ndarray:
  """uint8 [A, H, W, 3]: the first frame with each action's red ball."""
  frames = []
  for action in actions:
    bodies = list(task.bodies) + [phyre_like.action_ball(action)]
    poses = [(b.position, b.angle) for b in bodies]
    frames.append(phyre_like.render_state(bodies, poses, resolution)[0])
  return np.stack(frames)


class SlotFeatures:
  """[first-frame slots, SlotFormer rollout] of (task, action) pairs."""

  def __init__(self, config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh):
    self._resolution = tuple(config.data.resolution)
    savi_params, _ = inference.load_savi_params(config, workdir, mesh)
    dynamics_params, step = inference.load_dynamics_params(config, workdir,
                                                          mesh)
    logger.info('planning with SlotFormer step %d', step)
    if config.slotformer.burn_in != 1:
      raise ValueError('planning observes the first frame only: set '
                       'slotformer.burn_in = 1')
    savi = models.build_savi(config)
    slotformer = models.build_slotformer(config)
    num_steps = config.readout.rollout_steps
    self._batch = config.readout.encode_batch_size

    @jax.jit
    def features(frames):
      slots, _ = inference.savi_encode(savi_params, frames[:, None],
                                   jax.random.key(0), None, model=savi)
      rollout = inference.rollout_slots(dynamics_params, slots, model=slotformer,
                                    num_steps=num_steps)
      return jnp.concatenate([slots, rollout], axis=1)

    self._features = features

  def __call__(self, task: phyre_like.Task, actions: np.ndarray
               ) -> np.ndarray:
    """float32 [A, 1 + rollout_steps, N, D]."""
    out = []
    for i in range(0, len(actions), self._batch):
      frames = first_frames(task, actions[i:i + self._batch],
                            self._resolution)
      pad = self._batch - len(frames)  # one compiled batch shape
      frames = np.concatenate([frames, np.repeat(frames[-1:], pad, 0)])
      out.append(np.asarray(self._features(jnp.asarray(frames)))[
          :self._batch - pad])
    return np.concatenate(out)


def _task_features(features: SlotFeatures, tasks, labels, actions):
  """Per task: (valid candidate indices, their features)."""
  out = []
  for task in tasks:
    valid = np.flatnonzero(labels[(task.template, task.index)]
                           != planning.INVALID)
    out.append((valid, features(task, actions[valid])))
  return out


def _scores(model, params, task_features, num_candidates):
  """Per task: float [num_candidates]; invalid candidates score -inf
  (they are never counted as attempts, so their rank does not matter)."""
  scores = []
  for valid, feats in task_features:
    task_scores = np.full(num_candidates, -np.inf)
    task_scores[valid] = readout_lib.predict(model, params, feats)
    scores.append(task_scores)
  return scores


def _setup(config, workdir, mesh, split_names):
  generation = phyre_like.config_from_data_config(config.data)
  labels = phyre_like.task_labels(
      generation, resolve_data_dir(config.data.get('data_dir', None)))
  actions = phyre_like.candidate_actions(generation)
  splits = task_splits(config)
  features = SlotFeatures(config, workdir, mesh)
  by_split = {name: _task_features(features, splits[name], labels, actions)
              for name in split_names}
  outcomes = {name: [labels[(t.template, t.index)] for t in splits[name]]
              for name in split_names}
  return by_split, outcomes, generation


def _run_dir(workdir: str, condition: str, seed: int) -> str:
  return os.path.join(planning_dir(workdir), condition, f'seed_{seed}')


def train_readout(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh) -> None:
  """Fits the success classifiers; the epoch is chosen by dev AUCCESS."""
  if config.data.name == 'phyre':  # the real, pre-rendered layout
    return phyre_rendered.train_readout(config, workdir, mesh)
  by_split, outcomes, generation = _setup(config, workdir, mesh,
                                          ('train', 'dev'))
  rng = np.random.default_rng(config.seed)
  rows, labels = [], []
  for (valid, feats), task_outcomes in zip(by_split['train'],
                                           outcomes['train']):
    solved = task_outcomes[valid] == planning.SOLVED
    negatives = np.flatnonzero(~solved)
    keep = np.concatenate([
        np.flatnonzero(solved),
        rng.permutation(negatives)[:config.readout.negatives_per_task]])
    rows.append(feats[keep])
    labels.append(solved[keep].astype(np.float32))
  train = (np.concatenate(rows), np.concatenate(labels))
  logger.info('classifier training set: %d (task, action) pairs, %.1f%% '
              'solving', len(train[1]), 100 * train[1].mean())
  fit_config = readout_lib.FitConfig(
      epochs=config.readout.epochs, batch_size=config.readout.batch_size,
      learning_rate=config.readout.learning_rate,
      warmup_fraction=config.readout.warmup_fraction)
  for condition in config.readout.conditions:
    model = build_classifier(config, condition)
    for seed in config.readout.seeds:
      directory = _run_dir(workdir, condition, seed)
      if os.path.exists(os.path.join(directory, 'selection.json')):
        continue

      def dev_auccess(params, model=model):
        return planning.plan_auccess(
            _scores(model, params, by_split['dev'],
                    generation.num_candidates), outcomes['dev'])

      params, log = readout_lib.fit(model, train, dev_auccess, fit_config,
                                    seed=seed)
      os.makedirs(directory, exist_ok=True)
      with open(os.path.join(directory, 'params.msgpack'), 'wb') as f:
        f.write(serialization.msgpack_serialize(params))
      with open(os.path.join(directory, 'selection.json'), 'w') as f:
        json.dump({'dev_auccess': log['best_score'],
                   'best_epoch': log['best_epoch'],
                   'dev_scores': log['scores'],
                   'train_losses': log['losses']}, f, indent=1)
      logger.info('classifier %s seed %d: dev AUCCESS %.3f (epoch %d)',
                  condition, seed, log['best_score'], log['best_epoch'])


def plan(config: ml_collections.ConfigDict, workdir: str,
         mesh: Mesh) -> dict[str, Any]:
  """Ranks every candidate of every test task; AUCCESS per method."""
  if config.data.name == 'phyre':  # the real, pre-rendered layout
    return phyre_rendered.plan(config, workdir, mesh)
  by_split, outcomes, generation = _setup(config, workdir, mesh, ('test',))
  test, test_outcomes = by_split['test'], outcomes['test']
  seeds = tuple(config.readout.seeds)
  results: dict[str, Any] = {}
  results['random'] = [planning.plan_auccess(
      planning.random_scores(test_outcomes, seed), test_outcomes)
                       for seed in seeds]
  first_seed_scores = {}
  for condition in config.readout.conditions:
    model = build_classifier(config, condition)
    values = []
    for seed in seeds:
      directory = _run_dir(workdir, condition, seed)
      path = os.path.join(directory, 'params.msgpack')
      if not os.path.exists(path):
        raise FileNotFoundError(
            f'no trained classifier in {directory}; run --mode=train_readout')
      with open(path, 'rb') as f:
        params = serialization.msgpack_restore(f.read())
      scores = _scores(model, params, test, generation.num_candidates)
      first_seed_scores.setdefault(condition, scores)
      values.append(planning.plan_auccess(scores, test_outcomes))
    results[condition] = values
  results['oracle'] = [planning.plan_auccess(
      planning.oracle_scores(test_outcomes), test_outcomes)]
  summary = {name: {'auccess': values, 'mean': float(np.mean(values)),
                    'std': float(np.std(values))}
             for name, values in results.items()}
  summary['num_test_tasks'] = len(test_outcomes)
  summary['fold'] = generation.fold
  summary['solvable_test_tasks'] = int(sum(
      (o == planning.SOLVED).any() for o in test_outcomes))
  os.makedirs(planning_dir(workdir), exist_ok=True)
  with open(os.path.join(planning_dir(workdir), 'results.json'), 'w') as f:
    json.dump(summary, f, indent=1)
  table = format_table(summary, generation.fold)
  with open(os.path.join(planning_dir(workdir), 'results.md'), 'w') as f:
    f.write(table + '\n')
  logger.info('planning, AUCCESS x 100 on %d test tasks:\n%s',
              len(test_outcomes), table)
  condition = ROLLOUT if ROLLOUT in first_seed_scores else FIRST_FRAME
  for k in range(min(config.readout.get('num_pictures', 0),
                     len(test_outcomes))):
    write_ranking_picture(
        os.path.join(planning_dir(workdir), f'test_task_{k}.png'),
        task_splits(config)['test'][k], first_seed_scores[condition][k],
        test_outcomes[k], generation)
  return summary


def write_ranking_picture(path: str, task: phyre_like.Task,
                          scores: np.ndarray, outcomes: np.ndarray,
                          generation: phyre_like.PhyreLikeConfig,
                          top: int = 5) -> None:
  """The ``top`` best-scored valid candidates of a task, one row each: the
  simulated rollout (every other frame) with its score and outcome."""
  actions = phyre_like.candidate_actions(generation)
  order = [i for i in planning.rank_actions(scores)
           if outcomes[i] != planning.INVALID][:top]
  scale, label_h = 2, 12
  rows = []
  for rank, index in enumerate(order, start=1):
    video = phyre_like.render_video(task, actions[index], generation)['video']
    strip = np.concatenate([np.pad(
        np.repeat(np.repeat(frame, scale, 0), scale, 1),
        ((1, 1), (1, 1), (0, 0))) for frame in video[::2]], axis=1)
    canvas = Image.new('RGB', (strip.shape[1], strip.shape[0] + label_h),
                       (255, 255, 255))
    canvas.paste(Image.fromarray(strip), (0, label_h))
    outcome = 'SOLVED' if outcomes[index] == planning.SOLVED else 'not solved'
    ImageDraw.Draw(canvas).text(
        (2, 0), f'{task.template}:{task.index} rank {rank}: candidate '
        f'{index}, p(success) = {scores[index]:.2f}, {outcome}',
        fill=(0, 0, 0))
    rows.append(np.asarray(canvas))
  Image.fromarray(np.concatenate(rows, axis=0)).save(path)


_ROW_NAMES = {
    'random': 'random ranking',
    FIRST_FRAME: 'classifier on first-frame slots',
    ROLLOUT: 'classifier on first frame + SlotFormer rollout',
    'oracle': 'oracle (simulated labels)',
}


def format_table(summary: dict[str, Any], fold: int) -> str:
  lines = [f'| ranking | AUCCESS x 100 (fold {fold}) |', '|---|---|']
  for name in ('random', FIRST_FRAME, ROLLOUT, 'oracle'):
    if name in summary:
      row = summary[name]
      lines.append(f'| {_ROW_NAMES[name]} | {100 * row["mean"]:.1f} +- '
                   f'{100 * row["std"]:.1f} |')
  return '\n'.join(lines)
