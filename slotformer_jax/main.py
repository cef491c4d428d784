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
from slotformer_jax import xla_flags
from slotformer_jax.data.sources import default_data_dir
from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import visualize
from slotformer_jax.train import sharding

MODES = ('all', 'train_savi', 'extract_slots', 'train_slotformer',
         'train_slot_lstm', 'evaluate', 'render')

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


def main(argv):
  del argv
  # Before anything starts jax's backends ($SLOTFORMER_XLA_CPU_FLAGS=0: off).
  added_flags = xla_flags.apply_fast_cpu_flags()
  if _DISTRIBUTED.value:
    jax.distributed.initialize()
  _configure_logging()
  _enable_compilation_cache()
  if added_flags:
    logger.info('XLA_FLAGS += %s', ' '.join(added_flags))
  config, workdir, mode = _CONFIG.value, _WORKDIR.value, _MODE.value
  if config is None:
    raise app.UsageError('--config is required, e.g. configs/synthetic.py')
  if config.slot_model != 'savi':
    raise NotImplementedError(
        f'slot_model={config.slot_model!r} is not implemented yet; only '
        "'savi' (incl. stochastic SAVi) is. Override it with "
        '--config.slot_model=savi to use SAVi on this dataset.')
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
  wall_times = {}
  if mode == 'all':
    # The Slot-LSTM baseline only when the config asks for it.
    selected = tuple(m for m in MODES[1:]
                     if m != 'train_slot_lstm' or config.slot_lstm.train)
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
