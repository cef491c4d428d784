"""The planning stages (`task='planning'`) on the embedded PHYRE-like tasks:
`train_readout` (the success classifier, epoch chosen by dev AUCCESS) and
`plan` (AUCCESS over every test task's candidates). The protocol and the pure
parts are in tasks/phyre_planning.py; the real, pre-rendered PHYRE layout has
its own stages in planning_rendered.py (the stage table picks by
`data.name`).

Features of a (task, action) pair: the slot model encodes the first frame
with the action's red ball drawn in, SlotFormer rolls the slots out.
"""

from __future__ import annotations

import logging
import os
from typing import Any

from flax import serialization
import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax import inference
from slotformer_jax.config.sections import SLOTFORMER
from slotformer_jax.data.data_dir import resolve_data_dir
from slotformer_jax.data.embedded import phyre_like as phyre_like_data
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.files import write_atomic
from slotformer_jax.files import write_json_atomic
from slotformer_jax.run import Run
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.tasks import planning
from slotformer_jax.tasks import readout as readout_lib
from slotformer_jax.worlds import phyre_like

logger = logging.getLogger(__name__)

FIRST_FRAME, ROLLOUT = phyre_planning.FIRST_FRAME, phyre_planning.ROLLOUT


class SlotFeatures:
  """[first-frame slots, SlotFormer rollout] of (task, action) pairs."""

  def __init__(self, run: Run):
    self._resolution = tuple(run.config.data.resolution)
    if run.dynamics_section(SLOTFORMER).burn_in != 1:
      raise ConfigError('planning observes the first frame only: set '
                        'slotformer.burn_in = 1')
    slot_model = run.slot_model
    if slot_model.conditioning_fields:
      raise ConfigError(
          'planning observes rendered first frames without boxes: it needs '
          'an unconditional slot model (savi.initial_slots=learned)')
    slot_params = run.stage1.params
    trained = run.dynamics(SLOTFORMER)
    dynamics_params, slotformer = trained.params, trained.module
    logger.info('planning with SlotFormer step %d', trained.step)
    num_steps = run.config.readout.rollout_steps
    self._batch = run.config.readout.encode_batch_size

    @jax.jit
    def features(frames):
      slots, _ = slot_model.encode(slot_params, frames[:, None],
                                   jax.random.key(0), None)
      rollout = inference.rollout_slots(dynamics_params, slots, model=slotformer,
                                    num_steps=num_steps)
      return jnp.concatenate([slots, rollout], axis=1)

    self._features = features

  def __call__(self, task: phyre_like.Task, actions: np.ndarray
               ) -> np.ndarray:
    """float32 [A, 1 + rollout_steps, N, D]."""
    out = []
    for i in range(0, len(actions), self._batch):
      frames = phyre_planning.first_frames(task, actions[i:i + self._batch],
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


def task_candidates(run: Run, split_names: tuple[str, ...]):
  """The candidates of the embedded tasks of `split_names` ('train',
  'dev', 'test'), as the classifiers read them.

  Returns:
    by_split: {split: per task, (valid candidate indices, their features)}.
    outcomes: {split: per task, every candidate's outcome
      (`tasks/planning.py`: SOLVED, ..., INVALID)}.
    generation: the tasks' generation parameters (PhyreLikeConfig).
  """
  config = run.config
  generation = phyre_like_data.config_from_data_config(config.data)
  labels = phyre_like_data.load_task_labels(
      generation, resolve_data_dir(config.data.data_dir))
  actions = phyre_like.candidate_actions(generation)
  splits = phyre_planning.task_splits(config.data, config.readout)
  features = SlotFeatures(run)
  by_split = {name: _task_features(features, splits[name], labels, actions)
              for name in split_names}
  outcomes = {name: [labels[(t.template, t.index)] for t in splits[name]]
              for name in split_names}
  return by_split, outcomes, generation


def train_readout(run: Run) -> None:
  """Fits the success classifiers; the epoch is chosen by dev AUCCESS."""
  config = run.config
  by_split, outcomes, generation = task_candidates(run, ('train', 'dev'))
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
    model = phyre_planning.build_classifier(config.readout, condition)
    for seed in config.readout.seeds:
      directory = run.paths.planner(condition, seed)
      if os.path.exists(os.path.join(directory, 'selection.json')):
        continue

      def dev_auccess(params, model=model):
        return planning.plan_auccess(
            phyre_planning.candidate_scores(model, params, by_split['dev'],
                    generation.num_candidates), outcomes['dev'])

      params, log = readout_lib.fit(model, train, dev_auccess, fit_config,
                                    seed=seed)
      # params first: a seed counts as trained once selection.json exists.
      write_atomic(os.path.join(directory, 'params.msgpack'),
                   serialization.msgpack_serialize(params))
      write_json_atomic(os.path.join(directory, 'selection.json'), {
          'dev_auccess': log['best_score'], 'best_epoch': log['best_epoch'],
          'dev_scores': log['scores'], 'train_losses': log['losses']},
                        sort_keys=False)
      logger.info('classifier %s seed %d: dev AUCCESS %.3f (epoch %d)',
                  condition, seed, log['best_score'], log['best_epoch'])


def load_classifier(run: Run, condition: str, seed: int) -> Any:
  """(module, params) of the success classifier of `condition` and `seed`.

  Raises:
    MissingInputError: not trained (the message names the stage).
  """
  directory = run.paths.planner(condition, seed)
  path = os.path.join(directory, 'params.msgpack')
  if not os.path.exists(path):
    raise MissingInputError(
        f'no trained classifier in {directory}; run --mode=train_readout')
  with open(path, 'rb') as f:
    params = serialization.msgpack_restore(f.read())
  return phyre_planning.build_classifier(run.config.readout, condition), params


def plan(run: Run) -> dict[str, Any]:
  """Ranks every candidate of every test task; AUCCESS per method."""
  config = run.config
  by_split, outcomes, generation = task_candidates(run, ('test',))
  test, test_outcomes = by_split['test'], outcomes['test']
  seeds = tuple(config.readout.seeds)
  results: dict[str, Any] = {}
  results['random'] = [planning.plan_auccess(
      planning.random_scores(test_outcomes, seed), test_outcomes)
                       for seed in seeds]
  first_seed_scores = {}
  for condition in config.readout.conditions:
    values = []
    for seed in seeds:
      model, params = load_classifier(run, condition, seed)
      scores = phyre_planning.candidate_scores(model, params, test,
                                               generation.num_candidates)
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
  directory = run.paths.planning
  write_json_atomic(os.path.join(directory, 'results.json'), summary,
                    sort_keys=False)
  table = phyre_planning.format_table(summary, generation.fold)
  write_atomic(os.path.join(directory, 'results.md'), table + '\n')
  logger.info('planning, AUCCESS x 100 on %d test tasks:\n%s',
              len(test_outcomes), table)
  condition = ROLLOUT if ROLLOUT in first_seed_scores else FIRST_FRAME
  for k in range(min(config.readout.num_pictures, len(test_outcomes))):
    phyre_planning.write_ranking_picture(
        os.path.join(directory, f'test_task_{k}.png'),
        phyre_planning.task_splits(config.data, config.readout)['test'][k],
        first_seed_scores[condition][k],
        test_outcomes[k], generation)
  return summary


