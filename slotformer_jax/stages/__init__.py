"""The stage table: which stages a run executes, in which order.

A run is the data stage (`prepare_data`: every `--mode` runs it first, so
the stages after it find their data made and checked), stage 1 (the slot
model's own parts, `stages/stage1.py`), slot extraction, stage 2
(SlotFormer; the Slot-LSTM baseline when the config trains it), then either
the video-prediction evaluation and pictures, or a downstream task: contact
prediction, planning, or VQA. `--mode=all` runs them in table order;
`--mode=<stage>` runs the data stage, then that one.

Every stage function is `(run: Run) -> None | results` (run.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from slotformer_jax.errors import CommandLineError
from slotformer_jax.errors import UserError
from slotformer_jax.run import Run
from slotformer_jax.stages import contact
from slotformer_jax.stages import data
from slotformer_jax.stages import dynamics
from slotformer_jax.stages import extract
from slotformer_jax.stages import planning
from slotformer_jax.stages import planning_rendered
from slotformer_jax.stages import stage1
from slotformer_jax.stages import video_prediction
from slotformer_jax.stages import vqa

StageFn = Callable[[Run], Any]

# Reading never writes: the data are made here, before every other stage.
DATA: dict[str, StageFn] = {'prepare_data': data.prepare_data}
STAGE2: dict[str, StageFn] = {
    'extract_slots': extract.extract_slots,
    'train_slotformer': dynamics.train_slotformer,
    'train_slot_lstm': dynamics.train_slot_lstm,
}
VIDEO_PREDICTION: dict[str, StageFn] = {
    'evaluate': video_prediction.evaluate,
    'render': video_prediction.render,
    'explore': video_prediction.explore,
}
# Downstream tasks, by `config.task`.
TASKS: dict[str, dict[str, StageFn]] = {
    'contact': {'train_readout': contact.train_readout,
                'evaluate_readout': contact.evaluate_readout},
    'planning': {'train_readout': planning.train_readout,
                 'plan': planning.plan},
    'vqa': {'vqa_slots': vqa.vqa_slots, 'train_vqa': vqa.train_vqa,
            'evaluate_vqa': vqa.evaluate_vqa},
}
# The real PHYRE layout holds rendered rollouts, not a simulator.
PLANNING_RENDERED: dict[str, StageFn] = {
    'train_readout': planning_rendered.train_readout,
    'plan': planning_rendered.plan,
}
# Where each task's stages come from, for messages.
TASK_CONFIGS = {'contact': 'configs/synthetic_contact.py',
                'planning': 'configs/synthetic_phyre.py',
                'vqa': 'configs/synthetic_vqa.py',
                None: 'configs/synthetic.py'}


def stage_table(run: Run) -> dict[str, StageFn]:
  """The stages `run` can execute, in the order `--mode=all` runs them."""
  table = dict(DATA)
  table.update(stage1.stage_functions(run))
  table.update(STAGE2)
  task = run.task
  if task is None:
    table.update(VIDEO_PREDICTION)
  elif task == 'planning' and run.config.data.name == 'phyre':
    table.update(PLANNING_RENDERED)
  elif task in TASKS:
    table.update(TASKS[task])
  else:
    raise UserError(f'unknown task {task!r}; one of {sorted(TASKS)} (or '
                    'none, for video prediction)')
  return table


def selected_stages(run: Run, mode: str) -> tuple[str, ...]:
  """The stages `--mode=<mode>` runs for `run`, in order; the data stage
  first, whatever the mode."""
  table = stage_table(run)
  if mode == 'all':
    # The Slot-LSTM baseline only when the config asks for it.
    return tuple(m for m in table
                 if m != 'train_slot_lstm' or run.config.slot_lstm.train)
  if mode not in table:
    raise CommandLineError(_not_a_stage(run, mode, table))
  return tuple(dict.fromkeys([*DATA, mode]))


def _not_a_stage(run: Run, mode: str, table: dict[str, StageFn]) -> str:
  """One line: what `--mode=<mode>` is not, and where it belongs."""
  line = (f'--mode={mode} does not apply to this config (slot_model='
          f'{run.config.slot_model!r}, task={run.task!r}); it runs '
          f'{", ".join(table)}')
  owners = [task for task, stages in TASKS.items() if mode in stages]
  if mode in VIDEO_PREDICTION:
    owners = [None]
  if owners:
    line += (f'. --mode={mode} belongs to ' + ' or '.join(
        TASK_CONFIGS[task] for task in owners))
  return line + '.'
