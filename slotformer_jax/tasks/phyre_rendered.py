"""PHYRE planning on the real, pre-rendered layout (data/convert/phyre.py).

What the layout holds (scripts/render_phyre.py, the official selection):
rollouts of a *subset* of PHYRE's cached actions with their simulated
outcome. Split 'train' has the fold's train + dev tasks (per task
int(int(2000 * pos_ratio) * data_ratio) solving and int(int(2000 * (1 -
pos_ratio)) * data_ratio) failing actions: 40 + 160 at the official 0.2 /
0.1), split 'val' the fold's test tasks (10 + 40 per task). No invalid
action is rendered.

The official protocol (phyre_planning/test_phyre_planning.py) trains the
success classifier on the 'train' rollouts, picks its checkpoint on the
'val' rollouts (the test tasks), and at test time ranks the first 10,000
actions of PHYRE's 100k-action cache on every test task: each action's
first frame is simulated with the ``phyre`` package, SAVi + SlotFormer +
classifier score it, the actions the cache marks invalid are skipped, and
AUCCESS is computed over the ranking. ``phyre`` has no wheel for this
Python and the layout holds neither those actions' first frames nor their
statuses, so here (``readout.candidates = 'rendered'``, the only one
implemented):

* ``train_readout`` fits the classifier on the rollouts of the 'train'
  tasks minus a dev set (``readout.dev_share`` of every template's tasks)
  and picks the epoch by AUCCESS over the dev tasks' rendered candidates
  (never on test tasks);
* ``plan`` ranks only the rendered candidates of every test task ('val'):
  about 50 per task, 20% of them solving, where PHYRE's 10,000 have a few
  per cent. That AUCCESS is NOT comparable with the paper's; every output
  says so.

Features: SAVi's slots of a rollout's first frame (the extracted slots'
frame 0, i.e. the first frame with the red ball, as the official code
encodes it) and SlotFormer's rollout from them (growing context with
``slotformer.max_context``); the classifier sees the frames
``readout.selected_steps`` (official (0, 3) at 1 fps), gathered before it,
so it is built with ``selected_steps = range(len(selected_steps))`` (its
temporal code depends on the number of selected frames only).

Workdir: ``planning/<condition>/seed_<s>/{params.msgpack, selection.json}``,
``planning/results.json``, ``planning/results.md``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from typing import Any

from flax import serialization
import jax
from jax.sharding import Mesh
import ml_collections
import numpy as np

from slotformer_jax import inference
from slotformer_jax import models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.errors import ConfigError
from slotformer_jax.modules import readouts
from slotformer_jax.tasks import planning
from slotformer_jax.tasks import readout as readout_lib

logger = logging.getLogger(__name__)

FIRST_FRAME, ROLLOUT = 'first_frame', 'rollout'
RENDERED = 'rendered'
PROTOCOL_NOTE = (
    'AUCCESS over the rendered candidates of each test task only (the '
    'layout\'s rollouts): NOT the official protocol, which ranks 10,000 '
    'cached actions per test task simulated with the `phyre` package')


@dataclasses.dataclass
class Rendered:
  """The rendered rollouts of one split.

  Attributes:
    first_slots: float32 [V, N, D] slots of each rollout's first frame.
    outcomes: int [V] planning.SOLVED / NOT_SOLVED.
    tasks: V task ids ('TTTTT:VVV').
  """

  first_slots: np.ndarray
  outcomes: np.ndarray
  tasks: list[str]


def check_candidates(config: ml_collections.ConfigDict) -> None:
  """Only the rendered candidates can be ranked without `phyre`.

  Raises:
    ConfigError: another candidate set, in one line.
  """
  candidates = config.readout.get('candidates', RENDERED)
  if candidates != RENDERED:
    raise ConfigError(
        f'readout.candidates={candidates!r}: ranking PHYRE\'s cached actions '
        '(the official 10,000 per test task) needs the `phyre` package to '
        'simulate their first frames, which has no wheel for this Python and '
        "is not implemented here; use readout.candidates='rendered' (ranks "
        'the rendered rollouts of each test task; not the official protocol)')


def _text(value: Any) -> str:
  value = value.item() if isinstance(value, np.ndarray) else value
  return value.decode('utf-8') if isinstance(value, bytes) else str(value)


def load_rendered(config: ml_collections.ConfigDict, workdir: str,
                  split: str) -> Rendered:
  """First-frame slots, outcomes and task ids of a split's rollouts.

  Raises:
    MissingInputError: the split's slots were not extracted (names
      --mode=extract_slots) or the dataset is not converted.
  """
  directory = workdir_lib.slots_dir(
      workdir_lib.stage1_workdir(config, workdir), split)
  slots = SlotSource(directory)
  videos = get_video_source(config.data, split)
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
    tasks.append(_text(item['task']))
  return Rendered(np.stack(first).astype(np.float32),
                  np.asarray(outcomes, np.int64), tasks)


def group_by_task(tasks: list[str]) -> dict[str, np.ndarray]:
  """{task id: indices of its rollouts}, task ids sorted."""
  groups: dict[str, list[int]] = {}
  for i, task in enumerate(tasks):
    groups.setdefault(task, []).append(i)
  return {task: np.asarray(groups[task]) for task in sorted(groups)}


def dev_tasks(task_ids: list[str], dev_share: float, seed: int) -> set[str]:
  """A within-template dev set: ``round(dev_share * n)`` of each template's
  n tasks (at least one task overall when ``dev_share`` > 0), drawn with
  ``seed``; deterministic and independent of the input order."""
  by_template: dict[str, list[str]] = {}
  for task in sorted(set(task_ids)):
    by_template.setdefault(task.split(':')[0], []).append(task)
  rng = np.random.default_rng([seed, 23])
  chosen: set[str] = set()
  for template in sorted(by_template):
    tasks = by_template[template]
    order = rng.permutation(len(tasks))
    chosen.update(tasks[i] for i in order[:int(round(dev_share * len(tasks)))])
  if dev_share > 0 and not chosen and len(set(task_ids)) > 1:
    chosen.add(min(task_ids))
  return chosen


def task_auccess(scores: np.ndarray, outcomes: np.ndarray,
                 groups: dict[str, np.ndarray]) -> float:
  """AUCCESS of ranking each task's rollouts by ``scores`` (float [V])."""
  return planning.plan_auccess([scores[i] for i in groups.values()],
                               [outcomes[i] for i in groups.values()])


def selected_steps(config: ml_collections.ConfigDict) -> tuple[int, ...]:
  steps = tuple(int(s) for s in config.readout.selected_steps)
  if not steps or steps[0] != 0 or list(steps) != sorted(set(steps)):
    raise ConfigError(f'readout.selected_steps={steps}: must start with 0 '
                      '(the observed first frame) and increase')
  return steps


def rollout_features(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh, first_slots: np.ndarray) -> np.ndarray:
  """float32 [V, S, N, D]: [first-frame slots, SlotFormer's rollout] at
  ``readout.selected_steps`` (S of them)."""
  steps = selected_steps(config)
  if config.slotformer.burn_in != 1:
    raise ConfigError('planning observes the first frame only: set '
                      'slotformer.burn_in = 1')
  num_steps = max(steps)
  if num_steps == 0:
    return first_slots[:, None]
  params, step = inference.load_dynamics_params(config, workdir, mesh)
  logger.info('PHYRE rollouts from SlotFormer step %d', step)
  model = models.build_slotformer(config)
  run = jax.jit(lambda p, s: inference.rollout_slots(
      p, s, model=model, num_steps=num_steps))
  batch = config.readout.encode_batch_size
  gather = np.asarray(steps[1:]) - 1
  out = []
  for i in range(0, len(first_slots), batch):
    chunk = first_slots[i:i + batch]
    pad = batch - len(chunk)  # one compiled batch shape
    padded = np.concatenate([chunk, np.repeat(chunk[-1:], pad, 0)])
    rollout = np.asarray(run(params, padded[:, None]))[:len(chunk)]
    out.append(np.concatenate([chunk[:, None], rollout[:, gather]], axis=1))
  return np.concatenate(out).astype(np.float32)


def build_classifier(config: ml_collections.ConfigDict, condition: str,
                     num_selected: int) -> readouts.PhyreReadout:
  """The official classifier on pre-gathered frames."""
  r = config.readout
  frames = 1 if condition == FIRST_FRAME else num_selected
  return readouts.PhyreReadout(
      selected_steps=tuple(range(frames)), embed_dim=r.embed_dim,
      num_layers=r.num_layers, num_heads=r.num_heads,
      mlp_size=r.mlp_ratio * r.embed_dim,
      dropout_rate=r.get('dropout_rate', 0.0),
      layer_norm_epsilon=r.get('layer_norm_epsilon', 1e-6))


def condition_features(features: np.ndarray, condition: str) -> np.ndarray:
  if condition == FIRST_FRAME:
    return features[:, :1]
  if condition == ROLLOUT:
    return features
  raise ConfigError(f'unknown planning condition {condition!r}; '
                    f'{FIRST_FRAME!r} or {ROLLOUT!r}')


def _splits(config: ml_collections.ConfigDict) -> tuple[str, str]:
  splits = config.readout.get('splits') or {}
  return splits.get('train', 'train'), splits.get('test', 'val')


def _run_dir(workdir: str, condition: str, seed: int) -> str:
  return os.path.join(workdir, 'planning', condition, f'seed_{seed}')


def train_readout(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh) -> None:
  """Fits the classifiers on the training tasks' rollouts; the epoch is
  chosen by AUCCESS over the dev tasks' rendered candidates."""
  check_candidates(config)
  train = load_rendered(config, workdir, _splits(config)[0])
  dev = dev_tasks(train.tasks, config.readout.dev_share, config.seed)
  is_dev = np.array([t in dev for t in train.tasks])
  if is_dev.all() or not is_dev.any():
    raise ConfigError(f'{len(set(train.tasks))} training tasks cannot be '
                      f'split by readout.dev_share={config.readout.dev_share}')
  features = rollout_features(config, workdir, mesh, train.first_slots)
  dev_groups = {task: rows for task, rows in group_by_task(train.tasks).items()
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
    model = build_classifier(config, condition, num_selected)
    inputs = condition_features(features, condition)
    for seed in config.readout.seeds:
      directory = _run_dir(workdir, condition, seed)
      if os.path.exists(os.path.join(directory, 'selection.json')):
        continue

      def dev_auccess(params, model=model, inputs=inputs):
        scores = np.full(len(inputs), -np.inf)
        rows = np.flatnonzero(is_dev)
        scores[rows] = readout_lib.predict(model, params, inputs[rows])
        return task_auccess(scores, train.outcomes, dev_groups)

      params, log = readout_lib.fit(model, (inputs[fit_rows], labels),
                                    dev_auccess, fit_config, seed=seed)
      os.makedirs(directory, exist_ok=True)
      with open(os.path.join(directory, 'params.msgpack'), 'wb') as f:
        f.write(serialization.msgpack_serialize(params))
      with open(os.path.join(directory, 'selection.json'), 'w') as f:
        json.dump({'dev_auccess_rendered': log['best_score'],
                   'best_epoch': log['best_epoch'],
                   'dev_tasks': sorted(dev),
                   'dev_scores': log['scores'],
                   'train_losses': log['losses']}, f, indent=1)
      logger.info('classifier %s seed %d: dev AUCCESS (rendered candidates) '
                  '%.3f (epoch %d)', condition, seed, log['best_score'],
                  log['best_epoch'])


def plan(config: ml_collections.ConfigDict, workdir: str,
         mesh: Mesh) -> dict[str, Any]:
  """Ranks the rendered candidates of every test task; AUCCESS per method
  (random ranking, each classifier, oracle), with the protocol stated."""
  check_candidates(config)
  test = load_rendered(config, workdir, _splits(config)[1])
  groups = group_by_task(test.tasks)
  features = rollout_features(config, workdir, mesh, test.first_slots)
  seeds = tuple(config.readout.seeds)
  results: dict[str, list[float]] = {}
  rng_scores = [np.random.default_rng(seed).random(len(test.outcomes))
                for seed in seeds]
  results['random'] = [task_auccess(s, test.outcomes, groups)
                       for s in rng_scores]
  for condition in config.readout.conditions:
    model = build_classifier(config, condition, features.shape[1])
    inputs = condition_features(features, condition)
    values = []
    for seed in seeds:
      path = os.path.join(_run_dir(workdir, condition, seed),
                          'params.msgpack')
      if not os.path.exists(path):
        raise FileNotFoundError(
            f'no trained classifier at {path}; run --mode=train_readout')
      with open(path, 'rb') as f:
        params = serialization.msgpack_restore(f.read())
      scores = readout_lib.predict(model, params, inputs)
      values.append(task_auccess(scores, test.outcomes, groups))
    results[condition] = values
  results['oracle'] = [task_auccess(
      (test.outcomes == planning.SOLVED).astype(np.float64), test.outcomes,
      groups)]
  summary: dict[str, Any] = {
      name: {'auccess': values, 'mean': float(np.mean(values)),
             'std': float(np.std(values))}
      for name, values in results.items()}
  sizes = [len(i) for i in groups.values()]
  summary.update(
      protocol=PROTOCOL_NOTE, candidates=RENDERED,
      num_test_tasks=len(groups),
      candidates_per_task=[int(min(sizes)), int(max(sizes))],
      solving_share=float((test.outcomes == planning.SOLVED).mean()),
      solvable_test_tasks=int(sum((test.outcomes[i] == planning.SOLVED).any()
                                  for i in groups.values())))
  directory = os.path.join(workdir, 'planning')
  os.makedirs(directory, exist_ok=True)
  with open(os.path.join(directory, 'results.json'), 'w') as f:
    json.dump(summary, f, indent=1)
  from slotformer_jax.tasks import phyre_planning  # pylint: disable=g-import-not-at-top
  table = phyre_planning.format_table(summary, config.readout.get('fold', '?'))
  header = (f'{PROTOCOL_NOTE}. {len(groups)} test tasks, '
            f'{min(sizes)}-{max(sizes)} candidates each, '
            f'{100 * summary["solving_share"]:.1f}% solving.')
  with open(os.path.join(directory, 'results.md'), 'w') as f:
    f.write(header + '\n\n' + table + '\n')
  logger.warning('%s', header)
  logger.info('planning on PHYRE (rendered candidates), AUCCESS x 100:\n%s',
              table)
  return summary
