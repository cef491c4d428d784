"""PHYRE planning on the real, pre-rendered layout (datasets/phyre.py): the
pure parts (the stages are in stages/planning/rendered.py).

The layout holds rollouts of a subset of PHYRE's cached actions, not the
10,000 actions per test task the official protocol ranks (those need the
``phyre`` package, which has no wheel for this Python). So
(``readout.candidates='rendered'``, the only one implemented)
``train_readout`` picks its epoch by AUCCESS on a dev share of the training
tasks, never on test tasks, and ``plan`` ranks only the rendered candidates
of every test task: that AUCCESS is not comparable with the paper's, and
every output says so.

Features: SAVi's slots of a rollout's first frame and SlotFormer's rollout
from them. The classifier sees the frames ``readout.selected_steps``,
gathered before it, so it is built with ``selected_steps =
range(len(selected_steps))`` (its temporal code depends on their number
only). The official protocol and what differs: docs/downstream.md, "Real
datasets".
"""

from __future__ import annotations

import dataclasses
from typing import Any

import ml_collections
import numpy as np

from slotformer_jax.errors import ConfigError
from slotformer_jax.modules import readouts
from slotformer_jax.tasks import planning

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


def check_candidates(readout: ml_collections.ConfigDict) -> None:
  """Only the rendered candidates can be ranked without `phyre`.

  Raises:
    ConfigError: another candidate set, in one line.
  """
  candidates = readout.candidates
  if candidates != RENDERED:
    raise ConfigError(
        f'readout.candidates={candidates!r}: ranking PHYRE\'s cached actions '
        '(the official 10,000 per test task) needs the `phyre` package to '
        'simulate their first frames, which has no wheel for this Python and '
        "is not implemented here; use readout.candidates='rendered' (ranks "
        'the rendered rollouts of each test task; not the official protocol)')


def text(value: Any) -> str:
  value = value.item() if isinstance(value, np.ndarray) else value
  return value.decode('utf-8') if isinstance(value, bytes) else str(value)


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


def selected_steps(readout: ml_collections.ConfigDict) -> tuple[int, ...]:
  steps = tuple(int(s) for s in readout.selected_steps)
  if not steps or steps[0] != 0 or list(steps) != sorted(set(steps)):
    raise ConfigError(f'readout.selected_steps={steps}: must start with 0 '
                      '(the observed first frame) and increase')
  return steps


def build_classifier(r: ml_collections.ConfigDict, condition: str,
                     num_selected: int) -> readouts.PhyreReadout:
  """The official classifier on pre-gathered frames (readout section `r`)."""
  frames = 1 if condition == FIRST_FRAME else num_selected
  return readouts.PhyreReadout(
      selected_steps=tuple(range(frames)), embed_dim=r.embed_dim,
      num_layers=r.num_layers, num_heads=r.num_heads,
      mlp_size=r.mlp_ratio * r.embed_dim,
      dropout_rate=r.dropout_rate, layer_norm_epsilon=r.layer_norm_epsilon)


def condition_features(features: np.ndarray, condition: str) -> np.ndarray:
  if condition == FIRST_FRAME:
    return features[:, :1]
  if condition == ROLLOUT:
    return features
  raise ConfigError(f'unknown planning condition {condition!r}; '
                    f'{FIRST_FRAME!r} or {ROLLOUT!r}')


def splits(readout: ml_collections.ConfigDict) -> tuple[str, str]:
  """(train, test) splits of the rendered layout."""
  return readout.splits.train, readout.splits.test
