"""What a run does after stage 2, behind one interface: a `Task`.

`config.task` names it: None is video prediction (evaluate, render,
explore); 'contact', 'planning' and 'vqa' are the downstream tasks. Each
task module of this package declares its `Task` and registers it at import;
the stage table (stages/__init__.py) imports every module of the package,
and a task defined elsewhere (a research file, a test) registers itself
from its own file with `register` (docs/developing.md, "A new task").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import ml_collections

from slotformer_jax.config import checks as config_checks
from slotformer_jax.errors import UserError

# (run) -> results; `Run` is not imported here (the task modules take it).
StageFn = Callable[[Any], Any]


def _no_splits(config: ml_collections.ConfigDict) -> tuple[()]:
  del config
  return ()


@dataclasses.dataclass(frozen=True)
class Task:
  """A downstream task (or video prediction) as the stage table runs it.

  Attributes:
    name: its `config.task` value (None: video prediction).
    config: the shipped config that runs it, named in messages.
    stages: {stage name: (run) -> results}, in the order `--mode=all` runs
      them after stage 2.
    seeded: those of its stages that take several seeds (config.seeds):
      one task model per chain, seed s on chain s (`Run.readout_chains`).
    section: the config section holding its settings ('readout', 'vqa';
      None: it has none of its own).
    defaults: () -> that section's defaults (config/defaults.py), named
      when a config sets the task without the section.
    reads: config -> ((field, split), ...): the data splits its stages
      open besides the extracted ones; the data stage makes and checks
      them, and each must be a split of the dataset whose slots are
      extracted (config/checks.py).
    input_problems: (run, stages) -> one line per problem of its inputs
      that is known before any work when the data is there already (VQA:
      questions about videos the converted split lacks); run by
      `stages.check`, so that nothing is trained first.
  """

  name: str | None
  config: str
  stages: Mapping[str, StageFn]
  seeded: tuple[str, ...] = ()
  section: str | None = None
  defaults: Callable[[], ml_collections.ConfigDict] | None = None
  reads: Callable[[ml_collections.ConfigDict],
                  tuple[tuple[str, str], ...]] = _no_splits
  input_problems: Callable[[Any, Sequence[str]], list[str]] = (
      lambda run, stages: [])

  def problems(self, config: ml_collections.ConfigDict) -> list[str]:
    """One line if the config lacks the task's section."""
    if self.section is None or isinstance(config.get(self.section),
                                          ml_collections.ConfigDict):
      return []
    how = (f' = {self.defaults.__module__.rsplit(".", 1)[-1]}.'
           f'{self.defaults.__name__}()' if self.defaults else '')
    return [f'task={self.name!r} reads config.{self.section}, which this '
            f'config has not got: set config.{self.section}{how}, as '
            f'{self.config} does']


TASKS: dict[str | None, Task] = {}


def register(task: Task) -> Task:
  """Makes `task` selectable as `config.task = task.name`, at the import of
  its module (the same task again is a no-op). Returns it."""
  taken = TASKS.get(task.name)
  if taken is not None and taken.config != task.config:
    raise ValueError(f'task name {task.name!r} is taken by {taken.config}')
  TASKS[task.name] = task
  return task


def get(name: str | None) -> Task:
  """The task `config.task = name` selects.

  Raises:
    UserError: no task is registered under `name` (one line).
  """
  if name not in TASKS:
    known = sorted(repr(n) for n in TASKS if n is not None)
    raise UserError(f'unknown task {name!r}; one of {", ".join(known)} (or '
                    'none, for video prediction; a task of your own '
                    'registers with slotformer_jax.stages.task.register)')
  return TASKS[name]


def owners(stage: str) -> list[Task]:
  """The tasks that have a stage named `stage`."""
  return [task for task in TASKS.values() if stage in task.stages]


def seeds_problems(config: ml_collections.ConfigDict,
                   stages: Sequence[str]) -> list[str]:
  """config/checks.py's `seeds_problems` for `stages` of `config`, whose
  task's seeded stages (`Task.seeded`) take several seeds too."""
  return config_checks.seeds_problems(config, stages, get(config.task).seeded)
