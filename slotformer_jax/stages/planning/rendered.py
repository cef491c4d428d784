"""Planning on the real, pre-rendered PHYRE layout (the task: __init__.py;
a converted dataset): `train_readout` and `plan` over
the rendered candidates of each task. What the layout holds, and why this is
not the official protocol: tasks/phyre_rendered.py.

Features: the slot model's slots of a rollout's first frame (the extracted
slots' frame 0) and SlotFormer's rollout from them.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from typing import Any

import jax
import numpy as np

from slotformer_jax import inference
from slotformer_jax.config.sections import primary_dynamics
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.errors import ConfigError
from slotformer_jax.files import write_atomic
from slotformer_jax.files import write_json_atomic
from slotformer_jax.run import Run
from slotformer_jax.stages import readout_fit
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
  if run.dynamics_section(primary_dynamics(run.config)).burn_in != 1:
    raise ConfigError('planning observes the first frame only: set '
                      'slotformer.burn_in = 1')
  num_steps = max(steps)
  if num_steps == 0:
    return first_slots[:, None]
  trained = run.dynamics(primary_dynamics(run.config))
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


@dataclasses.dataclass(frozen=True)
class TrainingSet:
  """What a chain's classifiers are fitted on and selected by.

  Attributes:
    features: float32 [V, S, N, D], `rollout_features` of every training
      rollout.
    outcomes: int64 [V], each rollout's (planning.SOLVED / NOT_SOLVED).
    fit_rows: the rows of the training tasks the classifiers fit on.
    labels: float32 [len(fit_rows)], 1 where that rollout solves its task.
    is_dev: bool [V], rows of the dev tasks (selection by AUCCESS).
    dev_groups: dev task -> its rows.
    tasks: [V], each rollout's task.
  """
  features: np.ndarray
  outcomes: np.ndarray
  fit_rows: np.ndarray
  labels: np.ndarray
  is_dev: np.ndarray
  dev_groups: dict[str, list[int]]
  tasks: list[str]


def training_set(run: Run) -> TrainingSet:
  """The training rollouts of `run`'s chain (its slots and SlotFormer),
  the dev tasks drawn with `run.seed` (config.seed; seed s on chain s).

  Raises:
    ConfigError: the training tasks cannot be split by readout.dev_share.
  """
  readout = run.config.readout
  train = load_rendered(run, phyre_rendered.splits(readout)[0])
  dev = phyre_rendered.dev_tasks(train.tasks, readout.dev_share, run.seed)
  is_dev = np.array([t in dev for t in train.tasks])
  if is_dev.all() or not is_dev.any():
    raise ConfigError(f'{len(set(train.tasks))} training tasks cannot be '
                      f'split by readout.dev_share={readout.dev_share}')
  fit_rows = np.flatnonzero(~is_dev)
  return TrainingSet(
      features=rollout_features(run, train.first_slots),
      outcomes=train.outcomes, fit_rows=fit_rows,
      labels=(train.outcomes[fit_rows] == planning.SOLVED).astype(np.float32),
      is_dev=is_dev,
      dev_groups={task: rows for task, rows
                  in phyre_rendered.group_by_task(train.tasks).items()
                  if task in dev},
      tasks=list(train.tasks))


def fit_classifier(readout: Any, condition: str, data: TrainingSet,
                   seed: int, directory: str
                   ) -> tuple[Any, Any, dict[str, Any]]:
  """(module, params, fit log) of the classifier of `condition` fitted
  with `seed` on `data` in `directory` (`readout_fit.fit_readout`), its
  epoch chosen by dev AUCCESS."""
  model = phyre_rendered.build_classifier(readout, condition,
                                          data.features.shape[1])
  inputs = phyre_rendered.condition_features(data.features, condition)
  rows = np.flatnonzero(data.is_dev)

  def dev_auccess(params):
    scores = np.full(len(inputs), -np.inf)
    scores[rows] = readout_lib.predict(model, params, inputs[rows])
    return phyre_rendered.task_auccess(scores, data.outcomes,
                                       data.dev_groups)

  fit_config = readout_lib.FitConfig(
      epochs=readout.epochs, batch_size=readout.batch_size,
      learning_rate=readout.learning_rate,
      warmup_fraction=readout.warmup_fraction)
  params, log = readout_fit.fit_readout(
      directory, f'classifier {condition} seed {seed}', model,
      (inputs[data.fit_rows], data.labels), dev_auccess, fit_config, seed)
  return model, params, log


def train_readout(run: Run) -> None:
  """Fits the classifiers on the training tasks' rollouts, per chain and
  seed (`Run.readout_chains`: a one-seed run readout.seeds on its chain,
  a several-seed run seed s on chain s); the epoch is chosen by AUCCESS
  over the dev tasks' rendered candidates."""
  readout = run.config.readout
  phyre_rendered.check_candidates(readout)
  if run.seeds is not None:
    logger.info('seeds %s: one classifier per chain, seed s on chain s '
                '(readout.seeds is not used)', run.seeds)
  for chain, seeds in run.readout_chains(readout.seeds):
    todo = [(condition, seed) for condition in readout.conditions
            for seed in seeds if not _trained(chain, condition, seed)]
    if not todo:
      logger.info('classifiers of seeds %s already trained', seeds)
      continue
    data = training_set(chain)
    logger.info('classifier training set: %d rollouts of %d tasks (%.1f%% '
                'solving); dev: %d tasks', len(data.fit_rows),
                len(set(data.tasks)) - len(data.dev_groups),
                100 * data.labels.mean(),
                len(data.dev_groups))
    for condition, seed in todo:
      directory = chain.paths.planner(condition, seed)
      _, _, log = fit_classifier(readout, condition, data, seed, directory)
      # params.msgpack holds the chosen epoch's parameters (`fit_readout`);
      # a seed counts as trained once selection.json exists.
      write_json_atomic(os.path.join(directory, 'selection.json'), {
          'dev_auccess_rendered': log['best_score'],
          'best_epoch': log['best_epoch'],
          'dev_tasks': sorted(data.dev_groups),
          'dev_scores': log['scores'], 'train_losses': log['losses']},
                        sort_keys=False)
      logger.info('classifier %s seed %d: dev AUCCESS (rendered candidates) '
                  '%.3f (epoch %d)', condition, seed, log['best_score'],
                  log['best_epoch'])


def load_classifier(run: Run, condition: str, seed: int,
                    num_selected: int) -> tuple[Any, Any]:
  """(module, params) of the classifier of `condition` and `seed` on
  `run`'s chain, over `num_selected` rollout steps.

  Raises:
    MissingInputError: not trained (the message names the stage).
  """
  params = readout_fit.load_params(run.paths.planner(condition, seed),
                                   'classifier')
  return (phyre_rendered.build_classifier(run.config.readout, condition,
                                          num_selected), params)


def _trained(run: Run, condition: str, seed: int) -> bool:
  return os.path.exists(os.path.join(run.paths.planner(condition, seed),
                                     'selection.json'))


def plan(run: Run) -> dict[str, Any]:
  """Ranks the rendered candidates of every test task; AUCCESS per method
  (random ranking, each classifier, oracle) and seed (per chain with
  several seeds), with the protocol stated."""
  readout = run.config.readout
  phyre_rendered.check_candidates(readout)
  results: dict[str, list[float]] = {'random': []}
  seeds_evaluated = []
  for chain, seeds in run.readout_chains(readout.seeds):
    test = load_rendered(chain, phyre_rendered.splits(readout)[1])
    groups = phyre_rendered.group_by_task(test.tasks)
    features = rollout_features(chain, test.first_slots)
    for seed in seeds:
      seeds_evaluated.append(seed)
      results['random'].append(phyre_rendered.task_auccess(
          np.random.default_rng(seed).random(len(test.outcomes)),
          test.outcomes, groups))
      for condition in readout.conditions:
        model, params = load_classifier(chain, condition, seed,
                                        features.shape[1])
        scores = readout_lib.predict(
            model, params,
            phyre_rendered.condition_features(features, condition))
        results.setdefault(condition, []).append(
            phyre_rendered.task_auccess(scores, test.outcomes, groups))
  results['oracle'] = [phyre_rendered.task_auccess(
      (test.outcomes == planning.SOLVED).astype(np.float64), test.outcomes,
      groups)]
  summary: dict[str, Any] = {
      name: {'auccess': values, 'mean': float(np.mean(values)),
             'std': float(np.std(values))}
      for name, values in results.items()}
  # Which seed each AUCCESS entry is; 'per_seed': each on its own chain.
  summary['seeds'] = seeds_evaluated
  summary['chains'] = 'one' if run.seeds is None else 'per_seed'
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
  table = phyre_planning.format_table(summary, readout.fold)
  header = (f'{phyre_rendered.PROTOCOL_NOTE}. {len(groups)} test tasks, '
            f'{min(sizes)}-{max(sizes)} candidates each, '
            f'{100 * summary["solving_share"]:.1f}% solving.')
  write_atomic(os.path.join(directory, 'results.md'),
               header + '\n\n' + table + '\n')
  logger.warning('%s', header)
  logger.info('planning on PHYRE (rendered candidates), AUCCESS x 100:\n%s',
              table)
  return summary
