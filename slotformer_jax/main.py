r"""Runs the SlotFormer pipeline: SAVi -> slots -> SlotFormer -> eval -> render.

  python -m slotformer_jax.main --config=configs/synthetic.py --workdir=runs/demo
  python -m slotformer_jax.main --config=configs/synthetic.py:tiny \
      --workdir=runs/tiny --mode=train_savi --config.savi.num_train_steps=50

Re-running the same command resumes: finished stages are skipped, training
continues from the newest checkpoint. One run writes a workdir at a time (a
lock), changed settings on an existing workdir are refused unless
--allow_config_change, and every config problem is reported before any work.
A problem the user can fix ends the run with one line on stderr and exit
status 1 (2 for a bad command line); SIGTERM during training saves a
checkpoint first (exit status 143), and so does Ctrl-C (SIGINT, 130). With
several processes (--distributed) they stop after the same step, and a lost
process is named by the others, which stop too. See docs/reliability.md.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import time
import traceback

from absl import app
from absl import flags
from absl import logging as absl_logging
import jax
from ml_collections import config_flags
import tqdm

from slotformer_jax import stages
from slotformer_jax.config import checks as config_checks
from slotformer_jax.data.sources import default_data_dir
from slotformer_jax.errors import CommandLineError
from slotformer_jax.errors import UserError
from slotformer_jax.errors import one_line
from slotformer_jax.files import append_line_atomic
from slotformer_jax.run import Run
from slotformer_jax.runtime import host_memory
from slotformer_jax.runtime import processes
from slotformer_jax.runtime import startup
from slotformer_jax.runtime import xla_flags
from slotformer_jax.runtime.preemption import Preempted
from slotformer_jax.slot_models import chain
from slotformer_jax.workdir.lock import workdir_lock
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir.settings import accept_config
from slotformer_jax.workdir.settings import withdraw_unused_config

_CONFIG = config_flags.DEFINE_config_file(
    'config', None, 'Config file, e.g. configs/obj3d.py or '
    'configs/synthetic.py:tiny.', lock_config=True)
_WORKDIR = flags.DEFINE_string(
    'workdir', None, 'Folder for checkpoints, slots, metrics and pictures.',
    required=True)
_MODE = flags.DEFINE_string(
    'mode', 'all', "Which stage to run, or 'all': a stage of the config's "
    'table (its slot model, e.g. train_savi or train_dvae, tokenize_frames, '
    'train_steve; extract_slots, train_slotformer, train_slot_lstm; then '
    'evaluate, render, explore, or the task\'s stages); prepare_data, which '
    'makes and checks the data, runs first in every mode. docs/running.md.')
_DISTRIBUTED = flags.DEFINE_bool(
    'distributed', False, 'Call jax.distributed.initialize() first (one '
    'process per host on a TPU pod or multi-node GPU cluster). It detects '
    'the cluster (SLURM, TPU, ...) unless the next three flags are given.')
_COORDINATOR_ADDRESS = flags.DEFINE_string(
    'coordinator_address', None, 'HOST:PORT of process 0, which every '
    'process connects to (implies --distributed; with --num_processes and '
    '--process_id).')
_NUM_PROCESSES = flags.DEFINE_integer(
    'num_processes', None, 'How many processes the run has (with '
    '--coordinator_address).')
_PROCESS_ID = flags.DEFINE_integer(
    'process_id', None, 'This process: 0 .. num_processes-1 (with '
    '--coordinator_address).')
_PEER_TIMEOUT = flags.DEFINE_float(
    'peer_timeout', 30.0, 'With several processes: seconds without a '
    'heartbeat from another process (in <workdir>/.processes/) after which '
    'it counts as lost and this one stops too.')
_STARTUP_TIMEOUT = flags.DEFINE_float(
    'startup_timeout', 120.0, 'With several processes: seconds for every '
    'process to start, connect and agree on what it runs (config, mode, '
    'code, workdir); a process missing by then is named and every process '
    'stops.')
# An empty --workdir (an unset variable: --workdir=$RUN) would make the run
# write into the current folder.
flags.register_validator(
    'workdir', lambda value: value is None or bool(value.strip()),
    message='--workdir is empty (an unset variable?); give the folder of '
    'the run')
_ALLOW_CONFIG_CHANGE = flags.DEFINE_bool(
    'allow_config_change', False, 'Accept settings that differ from the ones '
    'this workdir was run with: the stages they affect are retrained or '
    're-extracted (old checkpoints are kept as <stage>.stale-<run id>) and '
    'the old settings go to config_history.jsonl.')


logger = logging.getLogger('slotformer_jax')


class _TqdmHandler(logging.Handler):
  """Writes log lines above the progress bars instead of through them."""

  def emit(self, record: logging.LogRecord) -> None:
    tqdm.tqdm.write(self.format(record), file=sys.stderr)


class _OneLineErrors(logging.Filter):
  """Library errors as one line each, no traceback: e.g. a full disk makes
  orbax's background threads log one traceback per file they could not
  write, while the training loop already stops with its own one line."""

  def filter(self, record: logging.LogRecord) -> bool:
    message = record.getMessage().strip().splitlines()
    record.msg = (message[0][:300] if message else '')
    record.args = ()
    record.exc_info = record.exc_text = record.stack_info = None
    return True


class _NoUnretrievedFutures(logging.Filter):
  """asyncio's 'Task exception was never retrieved', once per failed write
  of orbax's save (about 40 on a full disk): the trainer reports the failed
  save itself, in one line."""

  def filter(self, record: logging.LogRecord) -> bool:
    return not str(record.msg).startswith(
        ('Task exception was never retrieved',
         'Future exception was never retrieved'))


def _configure_logging() -> None:
  """INFO lines of this package on stderr; chatty libraries (orbax, tfds log
  through absl) only report errors, one line each."""
  absl_logging.set_verbosity(absl_logging.ERROR)
  for name in ('absl', 'asyncio'):
    library_logger = logging.getLogger(name)
    if not any(isinstance(f, _OneLineErrors) for f in library_logger.filters):
      if name == 'asyncio':
        library_logger.addFilter(_NoUnretrievedFutures())
      library_logger.addFilter(_OneLineErrors())
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


def main(argv):
  del argv
  # Before anything starts jax's backends ($SLOTFORMER_XLA_CPU_FLAGS=0: off).
  added_flags = xla_flags.apply_fast_cpu_flags()
  # Before jax allocates: freed step buffers stay mapped (runtime/host_memory).
  host_memory.keep_freed_memory()
  explicit = processes.check_flags(_COORDINATOR_ADDRESS.value,
                                   _NUM_PROCESSES.value, _PROCESS_ID.value)
  for flag in (_PEER_TIMEOUT, _STARTUP_TIMEOUT):
    if flag.value <= 0:
      raise UserError(f'--{flag.name}={flag.value} must be > 0')
  config, workdir, mode = _CONFIG.value, _WORKDIR.value, _MODE.value
  if config is None:
    raise app.UsageError('--config is required, e.g. configs/synthetic.py')
  _configure_logging()
  if _DISTRIBUTED.value or explicit:
    _start_processes(config, workdir, mode)
  _enable_compilation_cache()
  if added_flags:
    logger.info('XLA_FLAGS += %s', ' '.join(added_flags))
  # The config is checked once and the run built once; every stage gets it.
  run = Run.create(config, workdir)
  selected = stages.selected_stages(run, mode)
  # Every check before any work: a bad value costs seconds, not a stage.
  stages.check(run, selected)
  global _lock
  lock = workdir_lock(run.paths)
  if jax.process_index() == 0:
    lock.acquire()
    _lock = lock
  try:
    _run(run, selected)
  finally:
    lock.release()


_watchdog: processes.PeerWatchdog | None = None
_lock = None  # the workdir's lock, while this process holds it


def _start_processes(config, workdir: str, mode: str) -> None:
  """jax.distributed with a bounded start, then, before any work, every
  process checks that all were started alike (`startup.agree`); from then
  on each one that ends early tells the others (`PeerWatchdog.leave`)."""
  global _watchdog
  directory = Paths.of(workdir).heartbeats
  start = startup.Startup(
      directory, _PROCESS_ID.value, _NUM_PROCESSES.value,
      timeout=_STARTUP_TIMEOUT.value,
      coordinator=_COORDINATOR_ADDRESS.value).begin()
  # jax's own heartbeat and start timeouts (a stack dump when they fire)
  # come after ours.
  processes.initialize(
      _COORDINATOR_ADDRESS.value, _NUM_PROCESSES.value, _PROCESS_ID.value,
      heartbeat_timeout=max(100, int(3 * _PEER_TIMEOUT.value)),
      initialization_timeout=int(_STARTUP_TIMEOUT.value) + 60)
  start.end()
  if jax.process_count() == 1:
    return
  _watchdog = processes.PeerWatchdog(
      directory, jax.process_index(), jax.process_count(),
      timeout=_PEER_TIMEOUT.value).start()
  # Outside training (which saves first) Ctrl-C and SIGTERM end this
  # process through `leave`, so the others learn why at once.
  for signum in (signal.SIGINT, signal.SIGTERM):
    if signal.getsignal(signum) is not signal.SIG_IGN:
      signal.signal(signum, _interrupted)
  startup.agree(config.to_dict(), mode, workdir, directory=directory,
                startup=start, watchdog=_watchdog)


_SIGNAL_LINES = {
    signal.SIGINT: ('interrupted: Ctrl-C', 'interrupted by Ctrl-C'),
    signal.SIGTERM: ('terminated: SIGTERM', 'terminated by SIGTERM'),
}


def _interrupted(signum, frame) -> None:
  """Ctrl-C or SIGTERM outside training, with several processes: this
  process ends from the handler itself. A KeyboardInterrupt raised here can
  be swallowed: Python raises it in whatever runs next, and when that was
  jax's garbage-collection callback it printed 'Exception ignored' and the
  run went on (measured during evaluation)."""
  del frame
  line, reason = _SIGNAL_LINES[signum]
  # os.write: the main thread may be inside a print to stderr right now.
  os.write(2, f'{line} outside training; re-run the same command to resume '
           'from what was saved.\n'.encode())
  if _lock is not None:
    _lock.release()
  _leave(128 + signum, f'{reason} outside training')


def _leave(status: int, reason: str) -> None:
  """With several processes: ends this one now and tells the others why
  (never returns). With one: nothing; the caller exits."""
  if _watchdog is not None:
    _watchdog.leave(status, reason)


def _quiet_teardown() -> None:
  """After the one line of a failed run: objects of orbax's failed saves
  that Python collects while it shuts down raise again ('Exception ignored
  in: <coroutine ...>'); nothing is left to say."""
  sys.unraisablehook = lambda unraisable: None


def _run(run: Run, selected: tuple[str, ...]) -> None:
  if run.paths.foreign_stage1:
    # Before any data is made: the read-only stage 1 must fit (stacked as
    # the run's chains are).
    chain.check_identities(run.slot_model, run.paths,
                           run.chains()[0].stacked)
  # config.json only ever records settings that are used from here on.
  new_workdir = not os.path.exists(run.paths.config_file)
  changes = accept_config(run.config.to_dict(), run.paths,
                          allow_change=_ALLOW_CONFIG_CHANGE.value)
  if changes:
    logger.warning('accepted changed settings (--allow_config_change): %s',
                   '; '.join(changes))
  logger.info('%d processes, %d devices (%s)', jax.process_count(),
               jax.device_count(), jax.devices()[0].platform)

  table = stages.stage_table(run)
  wall_times = {}
  try:
    for stage in selected:
      started = time.time()
      logger.info('=== %s ===', stage)
      table[stage](run)
      run.forget()  # a later stage reads what this one trained
      wall_times[stage] = round(time.time() - started, 1)
      logger.info('%s took %.1f s', stage, wall_times[stage])
  except BaseException:
    # A first run that made nothing leaves no settings to refuse the
    # corrected command with.
    if new_workdir and withdraw_unused_config(run.paths):
      logger.info('%s holds nothing yet: its config.json is not kept',
                  run.paths.root)
    raise
  if jax.process_index() == 0:
    append_line_atomic(run.paths.wall_times, json.dumps(wall_times))


def run_main(argv: list[str] | None = None) -> None:
  """The entry point: anticipated errors become one line and a non-zero
  exit; unexpected ones keep their traceback."""
  argv = sys.argv if argv is None else argv
  # A shipped config by its name from any folder (`pip install .`).
  argv = [f'--config={config_checks.shipped_config(arg[len("--config="):])}'
          if arg.startswith('--config=') else arg for arg in argv]
  try:
    # The config file and the --config.* names, before absl's tracebacks.
    problem = config_checks.check_overrides(argv[1:])
  except config_checks.ConfigFileError as error:
    problem = _one_line(error)
  except UserError as error:  # the file's own mistake, not the command's
    print(f'error: {_one_line(error)}', file=sys.stderr)
    sys.exit(1)
  if not problem and config_checks.config_spec(argv[1:]) is None and not any(
      arg.split('=')[0] in _HELP_AND_FLAGFILE for arg in argv[1:]):
    problem = '--config is required, e.g. --config=configs/synthetic.py:tiny'
  if problem:
    print(f'error: {problem}', file=sys.stderr)
    sys.exit(2)
  status = 1
  try:
    app.run(main, argv=argv, flags_parser=_parse_flags)
  except SystemExit as exit_:
    status = 0 if exit_.code is None else (
        exit_.code if isinstance(exit_.code, int) else 1)
    raise
  except Preempted as error:
    # Every process stops after the same step (agreed): they end together.
    print(f'preempted: {_one_line(error)}', file=sys.stderr)
    status = 128 + error.signal
    sys.exit(status)
  except CommandLineError as error:
    print(f'error: {_one_line(error)}', file=sys.stderr)
    status = 2
    sys.exit(status)
  except UserError as error:
    line = _one_line(error)
    print(f'error: {line}', file=sys.stderr)
    status = 2 if isinstance(error, startup.Disagreement) else 1
    _quiet_teardown()
    _leave(status, f'error: {line}')
    sys.exit(status)
  except KeyboardInterrupt:
    # Ctrl-C outside a training loop (which saves and raises Preempted).
    print('interrupted: Ctrl-C outside training; re-run the same command to '
          'resume from what was saved.', file=sys.stderr)
    status = 128 + 2
    _leave(status, 'interrupted by Ctrl-C outside training')
    sys.exit(status)
  except Exception as error:
    if _watchdog is not None:
      # A failed collective usually means another process was lost: let the
      # watchdog name it (and end this one) instead of a traceback.
      _watchdog.wait_for_verdict()
      traceback.print_exc()
      _leave(1, f'{type(error).__name__}: {_one_line(error)}')
    raise
  finally:
    if _watchdog is not None:
      _watchdog.finish(status)


# absl answers these without a --config (a --flagfile may hold one).
_HELP_AND_FLAGFILE = ('-h', '-?', '--help', '--helpshort', '--helpfull',
                      '--helpxml', '--flagfile', '--only_check_args')


def _parse_flags(argv: list[str]) -> list[str]:
  """absl's flag parsing, with a bad flag (a wrong type, an unknown --mode,
  a missing --workdir) as one `error:` line and exit status 2."""
  try:
    return flags.FLAGS(argv)
  except flags.Error as error:
    print(f'error: {_one_line(error)} (see --helpshort)', file=sys.stderr)
    sys.exit(2)


def _one_line(error: BaseException) -> str:
  # Its own lines joined; nothing a terminal would act on (a name quoted
  # from a file) reaches it raw.
  return one_line(error)


if __name__ == '__main__':
  run_main()
