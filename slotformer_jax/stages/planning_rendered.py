"""The planning stages on the real, pre-rendered PHYRE layout
(`task='planning'`, `data.name='phyre'`): `train_readout` and `plan` over
the rendered candidates of each task. What the layout holds, and why this is
not the official protocol: tasks/phyre_rendered.py.

Features: the slot model's slots of a rollout's first frame (the extracted
slots' frame 0) and SlotFormer's rollout from them.
"""

from __future__ import annotations

import logging
import os
from typing import Any

from flax import serialization
import jax
import numpy as np

from slotformer_jax import inference
from slotformer_jax.config.sections import SLOTFORMER
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.files import write_atomic
from slotformer_jax.files import write_json_atomic
from slotformer_jax.run import Run
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.tasks import phyre_rendered
from slotformer_jax.tasks import planning
from slotformer_jax.tasks import readout as readout_lib
from slotformer_jax.tasks.phyre_rendered import Rendered

logger = logging.getLogger(__name__)


def load_rendered(run: Run, split: str) -> Rendered:
  """First-frame slots, outcomes and task ids of a split's rollouts.

  Raises:
    MissingInputError: the split's slots were not extracted (names
      --mode=extract_slots) or the dataset is not converted.
  """
  directory = run.paths.slots(split)
  slots = SlotSource(directory)
  videos = run.videos(split)
  if len(videos) != len(slots):
    raise ValueError(f'{directory} holds slots of {len(slots)} rollouts but '
                     f'the {split} split has {len(videos)}; re-run '
                     '--mode=extract_slots')
  first, outcomes, tasks = [], [], []
  for i in range(len(videos)):
    item = videos[i]
    first.append(slots[i]['slots'][0])
    outcomes.append(planning.SOLVED if int(item['label']) == 1
                    else planning.NOT_SOLVED)
    tasks.append(phyre_rendered.text(item['task']))
  return Rendered(np.stack(first).astype(np.float32),
                  np.asarray(outcomes, np.int64), tasks)


def rollout_features(run: Run, first_slots: np.ndarray) -> np.ndarray:
  """float32 [V, S, N, D]: [first-frame slots, SlotFormer's rollout] at
  ``readout.selected_steps`` (S of them)."""
  steps = phyre_rendered.selected_steps(run.config.readout)
  if run.dynamics_section(SLOTFORMER).burn_in != 1:
    raise ConfigError('planning observes the first frame only: set '
                      'slotformer.burn_in = 1')
  num_steps = max(steps)
  if num_steps == 0:
    return first_slots[:, None]
  trained = run.dynamics(SLOTFORMER)
  logger.info('PHYRE rollouts from SlotFormer step %d', trained.step)
  params = trained.params
  roll = jax.jit(lambda p, s: inference.rollout_slots(
      p, s, model=trained.module, num_steps=num_steps))
  batch = run.config.readout.encode_batch_size
  gather = np.asarray(steps[1:]) - 1
  out = []
  for i in range(0, len(first_slots), batch):
    chunk = first_slots[i:i + batch]
    pad = batch - len(chunk)  # one compiled batch shape
    padded = np.concatenate([chunk, np.repeat(chunk[-1:], pad, 0)])
    rollout = np.asarray(roll(params, padded[:, None]))[:len(chunk)]
    out.append(np.concatenate([chunk[:, None], rollout[:, gather]], axis=1))
  return np.concatenate(out).astype(np.float32)


def train_readout(run: Run) -> None:
  """Fits the classifiers on the training tasks' rollouts; the epoch is
  chosen by AUCCESS over the dev tasks' rendered candidates."""
  config = run.config
  phyre_rendered.check_candidates(config.readout)
  train = load_rendered(run, phyre_rendered.splits(config.readout)[0])
  dev = phyre_rendered.dev_tasks(train.tasks, config.readout.dev_share,
                                 config.seed)
  is_dev = np.array([t in dev for t in train.tasks])
  if is_dev.all() or not is_dev.any():
    raise ConfigError(f'{len(set(train.tasks))} training tasks cannot be '
                      f'split by readout.dev_share={config.readout.dev_share}')
  features = rollout_features(run, train.first_slots)
  dev_groups = {task: rows for task, rows
                in phyre_rendered.group_by_task(train.tasks).items()
                if task in dev}
  fit_rows = np.flatnonzero(~is_dev)
  labels = (train.outcomes[fit_rows] == planning.SOLVED).astype(np.float32)
  logger.info('classifier training set: %d rollouts of %d tasks (%.1f%% '
              'solving); dev: %d tasks', len(fit_rows),
              len(set(train.tasks)) - len(dev), 100 * labels.mean(), len(dev))
  fit_config = readout_lib.FitConfig(
      epochs=config.readout.epochs, batch_size=config.readout.batch_size,
      learning_rate=config.readout.learning_rate,
      warmup_fraction=config.readout.warmup_fraction)
  num_selected = features.shape[1]
  for condition in config.readout.conditions:
    model = phyre_rendered.build_classifier(config.readout, condition,
                                            num_selected)
    inputs = phyre_rendered.condition_features(features, condition)
    for seed in config.readout.seeds:
      directory = run.paths.planner(condition, seed)
      if os.path.exists(os.path.join(directory, 'selection.json')):
        continue

      def dev_auccess(params, model=model, inputs=inputs):
        scores = np.full(len(inputs), -np.inf)
        rows = np.flatnonzero(is_dev)
        scores[rows] = readout_lib.predict(model, params, inputs[rows])
        return phyre_rendered.task_auccess(scores, train.outcomes, dev_groups)

      params, log = readout_lib.fit(model, (inputs[fit_rows], labels),
                                    dev_auccess, fit_config, seed=seed)
      # params first: a seed counts as trained once selection.json exists.
      write_atomic(os.path.join(directory, 'params.msgpack'),
                   serialization.msgpack_serialize(params))
      write_json_atomic(os.path.join(directory, 'selection.json'), {
          'dev_auccess_rendered': log['best_score'],
          'best_epoch': log['best_epoch'], 'dev_tasks': sorted(dev),
          'dev_scores': log['scores'], 'train_losses': log['losses']},
                        sort_keys=False)
      logger.info('classifier %s seed %d: dev AUCCESS (rendered candidates) '
                  '%.3f (epoch %d)', condition, seed, log['best_score'],
                  log['best_epoch'])


def plan(run: Run) -> dict[str, Any]:
  """Ranks the rendered candidates of every test task; AUCCESS per method
  (random ranking, each classifier, oracle), with the protocol stated."""
  config = run.config
  phyre_rendered.check_candidates(config.readout)
  test = load_rendered(run, phyre_rendered.splits(config.readout)[1])
  groups = phyre_rendered.group_by_task(test.tasks)
  features = rollout_features(run, test.first_slots)
  seeds = tuple(config.readout.seeds)
  results: dict[str, list[float]] = {}
  rng_scores = [np.random.default_rng(seed).random(len(test.outcomes))
                for seed in seeds]
  results['random'] = [phyre_rendered.task_auccess(s, test.outcomes, groups)
                       for s in rng_scores]
  for condition in config.readout.conditions:
    model = phyre_rendered.build_classifier(config.readout, condition,
                                            features.shape[1])
    inputs = phyre_rendered.condition_features(features, condition)
    values = []
    for seed in seeds:
      path = os.path.join(run.paths.planner(condition, seed),
                          'params.msgpack')
      if not os.path.exists(path):
        raise MissingInputError(
            f'no trained classifier at {path}; run --mode=train_readout')
      with open(path, 'rb') as f:
        params = serialization.msgpack_restore(f.read())
      scores = readout_lib.predict(model, params, inputs)
      values.append(phyre_rendered.task_auccess(scores, test.outcomes, groups))
    results[condition] = values
  results['oracle'] = [phyre_rendered.task_auccess(
      (test.outcomes == planning.SOLVED).astype(np.float64), test.outcomes,
      groups)]
  summary: dict[str, Any] = {
      name: {'auccess': values, 'mean': float(np.mean(values)),
             'std': float(np.std(values))}
      for name, values in results.items()}
  sizes = [len(i) for i in groups.values()]
  summary.update(
      protocol=phyre_rendered.PROTOCOL_NOTE, candidates=phyre_rendered.RENDERED,
      num_test_tasks=len(groups),
      candidates_per_task=[int(min(sizes)), int(max(sizes))],
      solving_share=float((test.outcomes == planning.SOLVED).mean()),
      solvable_test_tasks=int(sum((test.outcomes[i] == planning.SOLVED).any()
                                  for i in groups.values())))
  directory = run.paths.planning
  write_json_atomic(os.path.join(directory, 'results.json'), summary,
                    sort_keys=False)
  table = phyre_planning.format_table(summary, config.readout.fold)
  header = (f'{phyre_rendered.PROTOCOL_NOTE}. {len(groups)} test tasks, '
            f'{min(sizes)}-{max(sizes)} candidates each, '
            f'{100 * summary["solving_share"]:.1f}% solving.')
  write_atomic(os.path.join(directory, 'results.md'),
               header + '\n\n' + table + '\n')
  logger.warning('%s', header)
  logger.info('planning on PHYRE (rendered candidates), AUCCESS x 100:\n%s',
              table)
  return summary
