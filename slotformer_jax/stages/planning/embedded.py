"""Planning on the embedded PHYRE-like tasks (the task: __init__.py):
`train_readout` (the success classifier, epoch chosen by dev AUCCESS) and
`plan` (AUCCESS over every test task's candidates). The protocol and the pure
parts are in tasks/phyre_planning.py.

Features of a (task, action) pair: the slot model encodes the first frame
with the action's red ball drawn in, SlotFormer rolls the slots out.

Seeds (`Run.readout_chains`): a one-seed run fits `readout.seeds`
classifiers on its one chain; a several-seed run (config.seeds) one per
chain, chain s's with seed s on its own slot model and SlotFormer (and
its negatives drawn with s). results.json gives each seed's AUCCESS, the
mean and std.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax import inference
from slotformer_jax.config.sections import primary_dynamics
from slotformer_jax.data.sources import resolve_data_dir
from slotformer_jax.datasets import synthetic_phyre as phyre_like_data
from slotformer_jax.errors import ConfigError
from slotformer_jax.files import write_atomic
from slotformer_jax.files import write_json_atomic
from slotformer_jax.run import Run
from slotformer_jax.stages import readout_fit
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.tasks import planning
from slotformer_jax.tasks import readout as readout_lib
from slotformer_jax.tasks import phyre_world

logger = logging.getLogger(__name__)

FIRST_FRAME, ROLLOUT = phyre_planning.FIRST_FRAME, phyre_planning.ROLLOUT


class SlotFeatures:
  """[first-frame slots, SlotFormer rollout] of (task, action) pairs."""

  def __init__(self, run: Run):
    self._resolution = tuple(run.config.data.resolution)
    if run.dynamics_section(primary_dynamics(run.config)).burn_in != 1:
      raise ConfigError('planning observes the first frame only: set '
                        'slotformer.burn_in = 1')
    slot_model = run.slot_model
    if slot_model.conditioning_fields:
      raise ConfigError(
          'planning observes rendered first frames without boxes: it needs '
          'an unconditional slot model (savi.initial_slots=learned)')
    slot_params = run.stage1.params
    trained = run.dynamics(primary_dynamics(run.config))
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

  def __call__(self, task: phyre_world.Task, actions: np.ndarray
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
  actions = phyre_world.candidate_actions(generation)
  splits = phyre_planning.task_splits(config.data, config.readout)
  features = SlotFeatures(run)
  by_split = {name: _task_features(features, splits[name], labels, actions)
              for name in split_names}
  outcomes = {name: [labels[(t.template, t.index)] for t in splits[name]]
              for name in split_names}
  return by_split, outcomes, generation


def train_readout(run: Run) -> None:
  """Fits the success classifiers per chain and seed; the epoch is chosen
  by dev AUCCESS."""
  conditions = tuple(run.config.readout.conditions)
  if run.seeds is not None:
    logger.info('seeds %s: one classifier per chain, seed s on chain s '
                '(readout.seeds is not used)', run.seeds)
  for chain, seeds in run.readout_chains(run.config.readout.seeds):
    if all(_trained(chain, c, seed) for c in conditions for seed in seeds):
      logger.info('classifiers of seeds %s already trained', seeds)
      continue
    _train_chain(chain, seeds)


def training_set(candidates, task_outcomes, negatives_per_task: int,
                 seed: int) -> tuple[np.ndarray, np.ndarray]:
  """(features [P, ...], labels float32 [P]) of the classifiers: every
  solving candidate of each training task and `negatives_per_task` others
  drawn with `seed`. `candidates`: `task_candidates`'s per-task (valid
  indices, features); `task_outcomes`: per task, every candidate's."""
  rng = np.random.default_rng(seed)
  rows, labels = [], []
  for (valid, feats), outcomes in zip(candidates, task_outcomes):
    solved = outcomes[valid] == planning.SOLVED
    negatives = np.flatnonzero(~solved)
    keep = np.concatenate([
        np.flatnonzero(solved),
        rng.permutation(negatives)[:negatives_per_task]])
    rows.append(feats[keep])
    labels.append(solved[keep].astype(np.float32))
  return np.concatenate(rows), np.concatenate(labels)


def fit_config_of(readout: Any) -> readout_lib.FitConfig:
  """The classifiers' training settings from `config.readout`."""
  return readout_lib.FitConfig(
      epochs=readout.epochs, batch_size=readout.batch_size,
      learning_rate=readout.learning_rate,
      warmup_fraction=readout.warmup_fraction)


def _trained(run: Run, condition: str, seed: int) -> bool:
  return os.path.exists(os.path.join(run.paths.planner(condition, seed),
                                     'selection.json'))


def _train_chain(run: Run, seeds: tuple[int, ...]) -> None:
  """The classifiers of `seeds` on `run`'s chain (its slot model and
  SlotFormer); negatives drawn with `run.seed`."""
  config = run.config
  by_split, outcomes, generation = task_candidates(run, ('train', 'dev'))
  train = training_set(by_split['train'], outcomes['train'],
                       config.readout.negatives_per_task, run.seed)
  logger.info('classifier training set: %d (task, action) pairs, %.1f%% '
              'solving', len(train[1]), 100 * train[1].mean())
  fit_config = fit_config_of(config.readout)
  for condition in config.readout.conditions:
    model = phyre_planning.build_classifier(config.readout, condition)
    for seed in seeds:
      directory = run.paths.planner(condition, seed)
      if _trained(run, condition, seed):
        continue

      def dev_auccess(params, model=model):
        return planning.plan_auccess(
            phyre_planning.candidate_scores(model, params, by_split['dev'],
                    generation.num_candidates), outcomes['dev'])

      _, log = readout_fit.fit_readout(
          directory, f'classifier {condition} seed {seed}', model, train,
          dev_auccess, fit_config, seed)
      # params.msgpack holds the chosen epoch's parameters (`fit_readout`);
      # a seed counts as trained once selection.json exists.
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
  params = readout_fit.load_params(run.paths.planner(condition, seed),
                                   'classifier')
  return phyre_planning.build_classifier(run.config.readout, condition), params


def plan(run: Run) -> dict[str, Any]:
  """Ranks every candidate of every test task; AUCCESS per method and
  seed (per chain with several seeds)."""
  config = run.config
  results: dict[str, Any] = {'random': []}
  first_seed_scores = {}
  seeds_evaluated = []
  for chain, seeds in run.readout_chains(config.readout.seeds):
    by_split, outcomes, generation = task_candidates(chain, ('test',))
    test, test_outcomes = by_split['test'], outcomes['test']
    for seed in seeds:
      seeds_evaluated.append(seed)
      results['random'].append(planning.plan_auccess(
          planning.random_scores(test_outcomes, seed), test_outcomes))
      for condition in config.readout.conditions:
        model, params = load_classifier(chain, condition, seed)
        scores = phyre_planning.candidate_scores(model, params, test,
                                                 generation.num_candidates)
        first_seed_scores.setdefault(condition, scores)
        results.setdefault(condition, []).append(
            planning.plan_auccess(scores, test_outcomes))
  results['oracle'] = [planning.plan_auccess(
      planning.oracle_scores(test_outcomes), test_outcomes)]
  summary = {name: {'auccess': values, 'mean': float(np.mean(values)),
                    'std': float(np.std(values))}
             for name, values in results.items()}
  # Which seed each AUCCESS entry is; 'per_seed': each on its own chain.
  summary['seeds'] = seeds_evaluated
  summary['chains'] = 'one' if run.seeds is None else 'per_seed'
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


