"""The planning task (`task='planning'`): a success classifier on the slot
model's slots and SlotFormer's rollout ranks every candidate action of a
task; AUCCESS over the test tasks. One task, two data variants:

* embedded.py: the embedded PHYRE-like tasks (a generated dataset), whose
  simulator (tasks/phyre_world.py) labels every candidate;
* rendered.py: the real PHYRE's rendered rollouts (a converted dataset):
  the candidates are the rendered ones, split by `readout.splits`.
"""

from __future__ import annotations

from typing import Any

import ml_collections

from slotformer_jax import datasets
from slotformer_jax.config import defaults
from slotformer_jax.run import Run
from slotformer_jax.stages.planning import embedded
from slotformer_jax.stages.planning import rendered
from slotformer_jax.stages.task import Task
from slotformer_jax.stages.task import register


def is_rendered(config: ml_collections.ConfigDict) -> bool:
  """Whether the run plans on rendered rollouts (converted data) rather
  than on the embedded simulator's tasks (generated data)."""
  return isinstance(datasets.get(config.data.name), datasets.Converted)


def train_readout(run: Run) -> None:
  """Fits the success classifiers per chain and seed (the epoch chosen on
  the dev tasks)."""
  (rendered if is_rendered(run.config) else embedded).train_readout(run)


def plan(run: Run) -> dict[str, Any]:
  """AUCCESS of each classifier over the test tasks (results.json)."""
  return (rendered if is_rendered(run.config) else embedded).plan(run)


def _reads(config: ml_collections.ConfigDict) -> tuple[tuple[str, str], ...]:
  # The embedded tasks are split by task, from the simulator's labels.
  if not is_rendered(config):
    return ()
  return tuple((f'readout.splits.{k}', v)
               for k, v in sorted(config.readout.splits.items()))


TASK = register(Task(
    name='planning', config='configs/synthetic_phyre.py',
    stages={'train_readout': train_readout, 'plan': plan},
    seeded=('train_readout', 'plan'),
    section='readout', defaults=defaults.planning_readout_config,
    reads=_reads))
