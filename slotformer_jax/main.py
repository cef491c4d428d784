r"""Runs the SlotFormer pipeline: SAVi -> slots -> SlotFormer -> eval -> render.

  python -m slotformer_jax.main --config=configs/synthetic.py --workdir=runs/demo
  python -m slotformer_jax.main --config=configs/synthetic.py:tiny \
      --workdir=runs/tiny --mode=train_savi --config.savi.num_train_steps=50

Re-running the same command resumes: finished stages are skipped, training
continues from the newest checkpoint.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time

from absl import app
from absl import flags
from absl import logging as absl_logging
import jax
from ml_collections import config_flags
import tqdm

from slotformer_jax import stages
from slotformer_jax.data.sources import default_data_dir
from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import visualize
from slotformer_jax.train import sharding

MODES = ('all', 'train_savi', 'train_dvae', 'tokenize_frames', 'train_steve',
         'extract_slots', 'train_slotformer', 'train_slot_lstm', 'evaluate',
         'render')
# Stage 1 of each slot model, in order (what `--mode=all` runs first).
STAGE1_MODES = {'savi': ('train_savi',),
                'steve': ('train_dvae', 'tokenize_frames', 'train_steve')}

_CONFIG = config_flags.DEFINE_config_file(
    'config', None, 'Config file, e.g. configs/obj3d.py or '
    'configs/synthetic.py:tiny.', lock_config=True)
_WORKDIR = flags.DEFINE_string(
    'workdir', None, 'Folder for checkpoints, slots, metrics and pictures.',
    required=True)
_MODE = flags.DEFINE_enum('mode', 'all', MODES, 'Which stage(s) to run.')
_DISTRIBUTED = flags.DEFINE_bool(
    'distributed', False, 'Call jax.distributed.initialize() first (one '
    'process per host on a TPU pod or multi-node GPU cluster).')


logger = logging.getLogger('slotformer_jax')


class _TqdmHandler(logging.Handler):
  """Writes log lines above the progress bars instead of through them."""

  def emit(self, record: logging.LogRecord) -> None:
    tqdm.tqdm.write(self.format(record), file=sys.stderr)


def _configure_logging() -> None:
  """INFO lines of this package on stderr; chatty libraries (orbax, tfds log
  through absl) only report errors."""
  absl_logging.set_verbosity(absl_logging.ERROR)
  handler = _TqdmHandler()
  handler.setFormatter(logging.Formatter(
      '%(asctime)s %(levelname).1s %(name)s] %(message)s', '%H:%M:%S'))
  logger.handlers[:] = [handler]
  logger.setLevel(logging.INFO)
  logger.propagate = False


def _enable_compilation_cache() -> None:
  """Re-runs (and resumed runs) reuse compiled steps instead of recompiling;
  $JAX_COMPILATION_CACHE_DIR, when set, wins."""
  if not os.environ.get('JAX_COMPILATION_CACHE_DIR'):
    jax.config.update('jax_compilation_cache_dir',
                      str(default_data_dir() / 'xla_cache'))
  jax.config.update('jax_persistent_cache_min_compile_time_secs', 1.0)


def _save_config(config, workdir: str) -> None:
  if jax.process_index() == 0:
    os.makedirs(workdir, exist_ok=True)
    with open(os.path.join(workdir, 'config.json'), 'w') as f:
      f.write(config.to_json_best_effort(indent=1))


def steve_stages_by_mode():
  """The stages with STEVE as the slot model (slotformer_jax/steve_*)."""
  # pylint: disable=g-import-not-at-top
  from slotformer_jax import steve_stages
  from slotformer_jax.evaluation import steve_evaluate
  return {
      'train_dvae': steve_stages.train_dvae,
      'tokenize_frames': steve_stages.tokenize_frames,
      'train_steve': steve_stages.train_steve,
      'extract_slots': steve_stages.extract_slots,
      'train_slotformer': steve_stages.train_slotformer,
      'train_slot_lstm': steve_stages.train_slot_lstm,
      'evaluate': steve_evaluate.evaluate,
      'render': steve_evaluate.render,
  }


def main(argv):
  del argv
  if _DISTRIBUTED.value:
    jax.distributed.initialize()
  _configure_logging()
  _enable_compilation_cache()
  config, workdir, mode = _CONFIG.value, _WORKDIR.value, _MODE.value
  if config is None:
    raise app.UsageError('--config is required, e.g. configs/synthetic.py')
  if config.slot_model not in STAGE1_MODES:
    raise ValueError(f'slot_model must be one of {tuple(STAGE1_MODES)}, got '
                     f'{config.slot_model!r}')
  _save_config(config, workdir)
  mesh = sharding.make_mesh()
  logger.info('%d processes, %d devices (%s)', jax.process_count(),
               jax.device_count(), jax.devices()[0].platform)

  run = {
      'train_savi': stages.train_savi,
      'extract_slots': stages.extract_slots,
      'train_slotformer': stages.train_slotformer,
      'train_slot_lstm': stages.train_slot_lstm,
      'evaluate': evaluate.evaluate,
      'render': visualize.render,
  }
  if config.slot_model == 'steve':
    run = steve_stages_by_mode()
  other_stage1 = {m for model, modes in STAGE1_MODES.items()
                  if model != config.slot_model for m in modes}
  if mode in other_stage1:
    raise app.UsageError(f'--mode={mode} does not belong to '
                         f'slot_model={config.slot_model!r}')
  wall_times = {}
  if mode == 'all':
    # The Slot-LSTM baseline only when the config asks for it.
    selected = tuple(m for m in MODES[1:] if m not in other_stage1 and (
        m != 'train_slot_lstm' or config.slot_lstm.train))
  else:
    selected = (mode,)
  for stage in selected:
    started = time.time()
    logger.info('=== %s ===', stage)
    run[stage](config, workdir, mesh)
    wall_times[stage] = round(time.time() - started, 1)
    logger.info('%s took %.1f s', stage, wall_times[stage])
  if jax.process_index() == 0:
    with open(os.path.join(workdir, 'wall_times.json'), 'a') as f:
      f.write(json.dumps(wall_times) + '\n')


if __name__ == '__main__':
  app.run(main)
