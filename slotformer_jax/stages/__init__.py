"""The stage table: which stages a config runs, in which order.

A run is the data stage (`prepare_data`: every `--mode` runs it first, so
the stages after it find their data made and checked), stage 1 (the slot
model's own stages, `slot_models/`), slot extraction, stage 2 (SlotFormer;
the Slot-LSTM baseline when the config trains it), then either the
video-prediction evaluation and pictures, or a downstream task: contact
prediction, planning, or VQA. `--mode=all` runs them in table order;
`--mode=<stage>` runs the data stage, then that one. The `--mode` values
are the union of every table, derived from the registries below.

Every stage function is `(config, workdir, mesh) -> None | results`.
"""

from __future__ import annotations

import ml_collections

from slotformer_jax import slot_models
from slotformer_jax.errors import UserError
from slotformer_jax.slot_models.base import StageFn
from slotformer_jax.stages import contact
from slotformer_jax.stages import data
from slotformer_jax.stages import dynamics
from slotformer_jax.stages import extract
from slotformer_jax.stages import planning
from slotformer_jax.stages import planning_rendered
from slotformer_jax.stages import video_prediction
from slotformer_jax.stages import vqa

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
# Downstream tasks, by `config.task` ('vqa': a config with a `vqa` section).
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


def _modes() -> tuple[str, ...]:
  names = []
  for table in ([DATA] + [m.stage1 for m in slot_models.SLOT_MODELS.values()]
                + [STAGE2, VIDEO_PREDICTION, *TASKS.values()]):
    names += [name for name in table if name not in names]
  return ('all', *names)


# Every value `--mode` accepts.
MODES = _modes()


def task_of(config: ml_collections.ConfigDict) -> str | None:
  """The downstream task of `config` (None: video prediction)."""
  if 'vqa' in config:
    return 'vqa'
  return config.get('task') or None


def stage_table(config: ml_collections.ConfigDict) -> dict[str, StageFn]:
  """The stages `config` can run, in the order `--mode=all` runs them."""
  table = dict(DATA)
  table.update(slot_models.get(config).stage1)
  table.update(STAGE2)
  task = task_of(config)
  if task is None:
    table.update(VIDEO_PREDICTION)
  elif task == 'planning' and config.data.name == 'phyre':
    table.update(PLANNING_RENDERED)
  elif task in TASKS:
    table.update(TASKS[task])
  else:
    raise UserError(f'unknown task {task!r}; one of {sorted(TASKS)} (or '
                    'none, for video prediction)')
  return table


def selected_stages(config: ml_collections.ConfigDict,
                    mode: str) -> tuple[str, ...]:
  """The stages `--mode=<mode>` runs for `config`, in order; the data stage
  first, whatever the mode."""
  table = stage_table(config)
  if mode == 'all':
    # The Slot-LSTM baseline only when the config asks for it.
    return tuple(m for m in table
                 if m != 'train_slot_lstm' or config.slot_lstm.train)
  if mode not in table:
    raise UserError(
        f'--mode={mode} does not apply to this config (slot_model='
        f'{config.slot_model!r}, task={task_of(config)!r}); it runs '
        f'{", ".join(table)}. Task stages need a task config, e.g. '
        'configs/synthetic_contact.py, configs/synthetic_phyre.py or '
        'configs/synthetic_vqa.py.')
  return tuple(dict.fromkeys([*DATA, mode]))
