"""The stage table: which stages a run executes, in which order, and every
check before the first of them.

A run is the data stage (`prepare_data`: every `--mode` runs it first, so
the stages after it find their data made and checked), stage 1 (the slot
model's own parts, `stages/stage1.py`), slot extraction, stage 2
(every dynamics model the config trains: SlotFormer, the Slot-LSTM
baseline when asked, ...: dynamics/), then the
stages of its task (`config.task`, `stages/task.py`): video prediction's
evaluation and pictures, or a downstream task's. `--mode=all` runs them in
table order; `--mode=<stage>` runs the data stage, then that one.

Every stage function is `(run: Run) -> None | results` (run.py).
"""

from __future__ import annotations

import importlib
import os
import pkgutil
from collections.abc import Callable, Sequence
from typing import Any

import jax

from slotformer_jax import datasets
from slotformer_jax.config import checks as config_checks
from slotformer_jax.config.sections import dynamics_stages
from slotformer_jax.config.sections import trained_dynamics
from slotformer_jax.errors import CommandLineError
from slotformer_jax.errors import ConfigError
from slotformer_jax.run import Run
from slotformer_jax.stages import data
from slotformer_jax.stages import dynamics
from slotformer_jax.stages import extract
from slotformer_jax.stages import stage1
from slotformer_jax.stages import task as task_lib

StageFn = Callable[[Run], Any]

# Every module of the package is imported: each task module registers its
# task (tests/test_layout.py counts these imports as edges).
for _module in pkgutil.iter_modules(__path__):
  importlib.import_module(f'{__name__}.{_module.name}')

# Reading never writes: the data are made here, before every other stage.
DATA: dict[str, StageFn] = {'prepare_data': data.prepare_data}


def stage2(run: Run) -> dict[str, StageFn]:
  """Slot extraction, then every dynamics model's training."""
  return {'extract_slots': extract.extract_slots,
          **dynamics.stage_functions(run.config)}


def stage_table(run: Run) -> dict[str, StageFn]:
  """The stages `run` can execute, in the order `--mode=all` runs them."""
  table = dict(DATA)
  table.update(stage1.stage_functions(run))
  table.update(stage2(run))
  table.update(task_lib.get(run.task).stages)
  return table


def selected_stages(run: Run, mode: str) -> tuple[str, ...]:
  """The stages `--mode=<mode>` runs for `run`, in order; the data stage
  first, whatever the mode."""
  table = stage_table(run)
  if mode == 'all':
    # The dynamics models the config trains (a baseline only when asked).
    untrained = set(dynamics_stages(run.config)) - {
        f'train_{name}' for name in trained_dynamics(run.config)}
    return tuple(m for m in table if m not in untrained)
  if mode not in table:
    raise CommandLineError(_not_a_stage(run, mode, table))
  return tuple(dict.fromkeys([*DATA, mode]))


def check(run: Run, stages: Sequence[str], *, num_devices: int | None = None,
          num_processes: int | None = None) -> None:
  """Every problem of the config for `stages` (of the slot model's own
  settings, the dataset's and the task's too) as one ConfigError, before
  any work: nothing is made, trained or written. Video lengths are read
  from data already there."""
  config, stages = run.config, tuple(stages)
  task = task_lib.get(run.task)
  dataset = datasets.DATASETS.get(config.data.name)  # unknown: a problem

  def video_length(split: str) -> int | None:
    # A generated dataset's from its parameters, else from its data.
    known = dataset.num_frames(config.data) if dataset is not None else None
    if known is not None:
      return known
    try:
      source = run.videos(split)
      return len(source[0]['video']) if len(source) else None
    except Exception:  # pylint: disable=broad-except
      return None  # missing data: the stage that reads it says how to fix

  config_checks.validate(
      config, stages,
      num_devices=(jax.device_count() if num_devices is None
                   else num_devices),
      num_processes=(jax.process_count() if num_processes is None
                     else num_processes),
      slot_model_problems=lambda: run.slot_model.check_config(
          frozenset(stages)),
      data_problems=(datasets.config_problems(config)
                     + task.problems(config)),
      dataset_splits=dataset.splits if dataset is not None else (),
      task_seeded=task.seeded,
      # The task's splits, where its stages run (they read them).
      task_splits=(task.reads(config) if set(stages) & set(task.stages)
                   and not task.problems(config) else ()),
      video_length=video_length)
  if set(stages) & set(task.stages) and not task.problems(config):
    problems = task.input_problems(run, stages)
    if problems:
      raise ConfigError('; '.join(problems))


# The shipped configs (a source checkout; absent from an installed wheel).
_CONFIGS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))), 'configs')


def _is_video_prediction(path: str) -> bool:
  """Whether the config file `path` exists and sets no task."""
  if not os.path.isfile(path):
    return False
  try:
    return config_checks.load_config_file(path).get('task') is None
  except Exception:  # pylint: disable=broad-except
    return False  # a hint only: never an error of its own


def _not_a_stage(run: Run, mode: str, table: dict[str, StageFn]) -> str:
  """One line: what `--mode=<mode>` is not, and where it belongs."""
  line = (f'--mode={mode} does not apply to this config (slot_model='
          f'{run.config.slot_model!r}, task={run.task!r}); it runs '
          f'{", ".join(table)}')
  owners = task_lib.owners(mode)
  if owners:
    line += (f'. --mode={mode} belongs to ' + ' or '.join(
        task.config for task in owners))
  if any(task.name is None for task in owners):
    # Video prediction on this run's dataset and stage 1, not the
    # synthetic config's.
    own = os.path.join(_CONFIGS, f'{run.config.data.name}.py')
    if run.task is not None and _is_video_prediction(own):
      line += (f'; on this run\'s data and stage 1: a new --workdir with '
               f'--config=configs/{run.config.data.name}.py '
               f'--config.stage1_workdir={run.paths.root}')
  return line + '.'
