"""Mistakes and faults that still ended badly (issue 39), each now one line
before any work, or a fault that ends in one line with nothing lost:

* an empty `--workdir=` (an unset variable) trained in the current folder;
* `--config.evaluation.split=valid` trained three stages, then asked
  forever for slots no stage makes;
* a full disk with TensorBoard on: the summary writer's OSError traceback
  hid the trainer's line, followed by ~40 lines of asyncio noise;
* a dataset lock left on a shared data dir by a run on another host: every
  later run waited forever;
* Ctrl-C during `python -m slotformer_jax.data.prepare`: a traceback per
  process.

(A full disk while writing the explorer page: tests/evaluation/
test_explore.py; a signal ignored before training: test_reliability.py.)
"""

import errno
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import jax
from jax.sharding import Mesh
import numpy as np
import pytest

import dataset_fixtures as fx
import pipeline_helpers
from slotformer_jax.workdir import lock as lock_lib
from slotformer_jax import main as main_lib
from slotformer_jax.datasets import obj3d
from slotformer_jax.errors import UserError
from slotformer_jax.workdir.lock import FileLock
from slotformer_jax.runtime import checkpoint as checkpoint_lib
from linear_stage import linear_stage
from slotformer_jax.train.trainer import fit

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), '..', '..'))
SYNTHETIC = os.path.join(ROOT, 'configs', 'synthetic.py')


def _env(tmp_path):
  env = dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS='cpu',
             SLOTFORMER_DATA_DIR=str(tmp_path / 'data'))
  env.pop('XLA_FLAGS', None)
  return env


def test_an_empty_workdir_is_one_line(tmp_path):
  """`--workdir=$RUN` with RUN unset: before, the run wrote its lock,
  config.json, data and checkpoints into the current folder."""
  for value in ('',):
    result = subprocess.run(
        [sys.executable, '-m', 'slotformer_jax.main',
         f'--config={SYNTHETIC}:tiny', f'--workdir={value}',
         '--mode=train_savi', '--config.savi.num_train_steps=1'],
        cwd=tmp_path, env=_env(tmp_path), capture_output=True, text=True,
        timeout=300)
    assert result.returncode == 2, result.stderr[-3000:]
    errors = [line for line in result.stderr.splitlines()
              if line.startswith('error:')]
    assert len(errors) == 1 and '--workdir is empty' in errors[0], (
        result.stderr[-3000:])
    assert 'Traceback' not in result.stderr
  assert os.listdir(tmp_path) == []


@pytest.mark.parametrize('field, value, stages', [
    ('evaluation.split', 'valid', ('train_savi', 'extract_slots', 'evaluate')),
    ('evaluation.split', 'valid', ('explore',)),
])
def test_a_split_no_stage_extracts_fails_before_work(tmp_path, field, value,
                                                      stages):
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  config.data.data_dir = str(tmp_path / 'data')
  section, name = field.split('.')
  config[section][name] = value
  with pytest.raises(UserError) as caught:
    pipeline_helpers.check(config, stages, num_devices=1)
  message = str(caught.value)
  assert f"{field}='valid' is not one of the splits whose slots are " \
      'extracted (extraction.splits: train, val, test)' in message, message
  assert not os.path.exists(tmp_path / 'data')


def test_a_readout_split_no_stage_extracts_fails_before_work(tmp_path):
  config = pipeline_helpers.load_config('synthetic_contact')
  config.data.data_dir = str(tmp_path / 'data')
  config.readout.splits.test = 'readout_tset'
  with pytest.raises(UserError, match="readout.splits.test='readout_tset' "
                     'is not one of the splits whose slots are extracted'):
    pipeline_helpers.check(config, ('train_readout',), num_devices=1)


# --------------------------------------------------------------------------
# A full disk with TensorBoard on
# --------------------------------------------------------------------------


def _linear_stage(directory, **config_changes):
  """The linear stage, TensorBoard on."""
  return linear_stage(directory, tensorboard=True, **config_changes)


def _full_disk(*args, **kwargs):
  raise OSError(errno.ENOSPC, 'No space left on device')


@pytest.fixture
def tensorboard_disk_full(monkeypatch):
  """tensorboardX's event file fills the disk after its first event: every
  later write fails (in its writer thread, and in close())."""
  from tensorboardX import record_writer  # pylint: disable=g-import-not-at-top
  calls = {'write': 0, 'flush': 0}

  def failing(name):
    original = getattr(record_writer.RecordWriter, name)

    def method(self, *args):
      calls[name] += 1
      if calls[name] > 1:
        _full_disk()
      return original(self, *args)
    return method
  for name in calls:
    monkeypatch.setattr(record_writer.RecordWriter, name, failing(name))
  return calls


@pytest.mark.parametrize('saves_fail', [False, True])
def test_a_full_disk_under_tensorboard_leaves_the_trainer_s_line(
    tmp_path, tensorboard_disk_full, monkeypatch, capfd, caplog, saves_fail):
  """Only the summaries fail: training ends, with a warning that they
  stopped. The checkpoint fails too: the trainer's one-line error is what
  comes out. Before, the writer's OSError ended the run in both cases, in
  a traceback that replaced the trainer's line."""
  if saves_fail:
    def failing_save(self, step, state, force=False):
      raise checkpoint_lib.CheckpointSaveError(
          f'saving the checkpoint of step {step} failed (OSError: [Errno 28] '
          'No space left on device); training stopped.')
    monkeypatch.setattr(checkpoint_lib.Checkpointer, 'save', failing_save)
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  stage = _linear_stage(tmp_path / 'linear')
  with caplog.at_level(logging.WARNING):
    if saves_fail:
      with pytest.raises(checkpoint_lib.CheckpointSaveError):
        fit(stage, mesh=mesh, seed=0)
    else:
      fit(stage, mesh=mesh, seed=0)
  time.sleep(0.5)  # the writer thread has met the full disk by now
  captured = capfd.readouterr()
  assert 'Traceback' not in captured.err + captured.out, captured.err
  warnings = [r.getMessage() for r in caplog.records
              if 'TensorBoard' in r.getMessage()]
  assert warnings and 'No space left on device' in warnings[-1], warnings


@pytest.fixture
def main_logging():
  """main's logging set up for one test, then undone: it stops the
  package's records at its own handler (propagate False), which left every
  later caplog test of the session (in test_host_memory, test_reliability,
  test_seeds) seeing no record."""
  package = logging.getLogger('slotformer_jax')
  saved = (list(package.handlers), package.level, package.propagate)
  main_lib._configure_logging()  # pylint: disable=protected-access
  yield
  package.handlers[:] = saved[0]
  package.setLevel(saved[1])
  package.propagate = saved[2]


def test_asyncio_s_unretrieved_futures_are_not_printed(caplog, main_logging):
  """orbax's failed writes on a full disk each left an asyncio 'Task
  exception was never retrieved' line (about 40 after the trainer's)."""
  del main_logging
  asyncio_logger = logging.getLogger('asyncio')
  with caplog.at_level(logging.ERROR):
    for text in ('Task exception was never retrieved',
                 'Future exception was never retrieved'):
      try:
        raise OSError(errno.ENOSPC, 'No space left on device')
      except OSError:
        asyncio_logger.error(text, exc_info=True)
    asyncio_logger.error('some other asyncio error\nwith detail')
  shown = [(r.getMessage(), r.exc_info) for r in caplog.records
           if r.name == 'asyncio']
  # Other errors stay, one line each.
  assert shown == [('some other asyncio error', None)], shown


def _mount_tmpfs(path, size):
  """A tmpfs of `size` at `path`, or None where mounting is not allowed."""
  path.mkdir()
  if shutil.which('mount') is None or os.geteuid() != 0:
    return None
  done = subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size}',
                         'tmpfs', str(path)], capture_output=True, check=False)
  return path if done.returncode == 0 else None


@pytest.mark.slow
def test_a_really_full_disk_under_tensorboard_is_one_line(tmp_path):
  """The whole command on a 600 KB tmpfs filled to 52 KB free, TensorBoard
  on (needs root to mount; skipped elsewhere): one `error:` line, no
  traceback, no asyncio lines, nothing after it but orbax's one-line E
  logs."""
  workdir = _mount_tmpfs(tmp_path / 'small', '600k')
  if workdir is None:
    pytest.skip('cannot mount a tmpfs here (needs root)')
  try:
    (workdir / 'fill').write_bytes(bytes(560_000))
    micro = [a for a in pipeline_helpers_micro_overrides()]
    result = subprocess.run(
        [sys.executable, '-m', 'slotformer_jax.main',
         f'--config={SYNTHETIC}:tiny', f'--workdir={workdir / "run"}',
         '--mode=train_savi', *micro, '--config.savi.num_train_steps=30',
         '--config.savi.checkpoint_every=1000',
         '--config.logging.tensorboard=True'],
        cwd=tmp_path, env=_env(tmp_path), capture_output=True, text=True,
        timeout=1200)
  finally:
    subprocess.run(['umount', str(workdir)], check=False)
  assert result.returncode == 1, result.stderr[-3000:]
  errors = [line for line in result.stderr.splitlines()
            if line.startswith('error:')]
  assert len(errors) == 1 and 'No space left on device' in errors[0], (
      result.stderr[-3000:])
  for noise in ('Traceback', 'never retrieved', 'Exception ignored'):
    assert noise not in result.stderr, result.stderr[-3000:]


def pipeline_helpers_micro_overrides():
  """pipeline_helpers' SAVi micro config, as command-line overrides."""
  return ['--config.data.resolution=(16,16)', '--config.data.num_frames=8',
          '--config.data.num_train=8', '--config.data.num_val=4',
          '--config.data.num_test=4', '--config.savi.decoder.features=(8,8)',
          '--config.savi.encoder.features=(8,8)',
          '--config.savi.encoder.strides=(1,1)', '--config.savi.log_every=1']


# --------------------------------------------------------------------------
# A lock left on a shared data dir by a run on another host
# --------------------------------------------------------------------------


def test_a_stale_lock_of_another_host_is_named_after_a_bounded_wait(
    tmp_path, monkeypatch):
  """A holder on another host cannot be asked whether it lives: a waiting
  lock is a heartbeat its holder touches; untouched for STALE_AFTER
  seconds, the waiter stops with one line naming the file, the owner and
  how to clear it. Before, it waited forever."""
  monkeypatch.setattr(lock_lib, 'STALE_AFTER', 2.0, raising=False)
  path = tmp_path / '.dataset.lock'
  path.write_text(json.dumps({'pid': 4242, 'host': 'gpu-node-7',
                              'started': '2026-01-02T03:04:05Z'}))
  outcome = {}

  def wait_for_it():
    try:
      FileLock(str(path), what='the synthetic dataset X', wait=True).acquire()
      outcome['acquired'] = True
    except UserError as error:
      outcome['error'] = str(error)
  started = time.monotonic()
  waiter = threading.Thread(target=wait_for_it, daemon=True)
  waiter.start()
  waiter.join(20)
  assert not waiter.is_alive(), 'still waiting for a stale lock'
  message = outcome.get('error', '')
  assert time.monotonic() - started < 2.0 + 6.0
  for needle in ('process 4242 on gpu-node-7', str(path),
                 f'delete {path} and re-run', 'has not been touched'):
    assert needle in message, message
  assert path.exists()  # never taken over: its holder may yet live


def test_a_live_holder_on_another_host_keeps_its_lock(tmp_path, monkeypatch):
  """The holder's heartbeat: a waiter on another host keeps waiting while
  the holder lives, and gets the lock when it is released."""
  monkeypatch.setattr(lock_lib, 'STALE_AFTER', 1.0)
  monkeypatch.setattr(lock_lib, 'REFRESH_EVERY', 0.2)
  path = str(tmp_path / '.dataset.lock')
  holder = FileLock(path, what='the dataset', wait=True)
  holder.acquire()
  # The waiter believes the holder is on another host.
  real_hostname = socket.gethostname
  monkeypatch.setattr(lock_lib.socket, 'gethostname',
                      lambda: real_hostname() + '-other')
  outcome = {}

  def wait_for_it():
    waiter = FileLock(path, what='the dataset', wait=True)
    try:
      waiter.acquire()
      outcome['acquired'] = time.monotonic()
      waiter.release()
    except UserError as error:
      outcome['error'] = str(error)
  thread = threading.Thread(target=wait_for_it, daemon=True)
  thread.start()
  time.sleep(3.0)  # three times STALE_AFTER: the heartbeat keeps it alive
  assert 'error' not in outcome and 'acquired' not in outcome, outcome
  holder.release()
  thread.join(10)
  assert 'acquired' in outcome, outcome


# --------------------------------------------------------------------------
# Ctrl-C during data.prepare
# --------------------------------------------------------------------------


def _obj3d_source(root, videos, frames):
  for number in range(videos):
    for t in range(1, frames + 1):
      fx.write_png(root / 'train' / str(number) /
                   obj3d.FRAME_TEMPLATE.format(t),
                   np.full((24, 24, 3), (7 * number + t) % 256, np.uint8))
  return root


def test_ctrl_c_during_prepare_is_one_line_and_the_rerun_finishes(tmp_path):
  """Ctrl-C in a terminal reaches every process of the group (the
  converter and its workers): one `interrupted:` line, exit status 130, no
  traceback; the rerun converts what is left. Before: a KeyboardInterrupt
  traceback from the converter and one from each worker."""
  # 384 videos in 192 shards: enough converting that the signal arrives
  # before the run ends (96 were too few; docs/reliability.md, "Mistakes").
  source = _obj3d_source(tmp_path / 'OBJ3D', videos=384, frames=8)
  command = [sys.executable, '-u', '-m', 'slotformer_jax.data.prepare',
             '--dataset=obj3d', f'--source={source}',
             f'--data_dir={tmp_path / "data"}', '--splits=train',
             '--resolution=16', '--num_frames=8', '--num_workers=2',
             '--videos_per_shard=2', '--no_progress']
  log = tmp_path / 'prepare.log'
  with open(log, 'w') as out:
    process = subprocess.Popen(command, env=_env(tmp_path), stdout=out,
                               stderr=subprocess.STDOUT,
                               start_new_session=True)
  deadline = time.monotonic() + 240
  # Signalled once the first shard is done (its progress record), while the
  # 191 others are still to write: a fixed sleep raced a fast machine.
  while not list((tmp_path / 'data').glob('**/_progress/train-[0-9]*.json')):
    assert process.poll() is None and time.monotonic() < deadline, (
        log.read_text()[-3000:])
    time.sleep(0.02)
  os.killpg(process.pid, signal.SIGINT)  # as a terminal's Ctrl-C
  status = process.wait(timeout=120)
  text = log.read_text()
  assert status == 130, text[-3000:]
  assert 'Traceback' not in text and 'KeyboardInterrupt' not in text, text
  lines = [line for line in text.splitlines()
           if line.startswith(('interrupted:', 'error:'))]
  assert lines == ['interrupted: Ctrl-C; re-run the same command to convert '
                   'the remaining shards'], text[-3000:]
  rerun = subprocess.run(command, env=_env(tmp_path), capture_output=True,
                         text=True, timeout=600)
  assert rerun.returncode == 0, rerun.stderr[-3000:]
  assert 'train: 384' in rerun.stdout + rerun.stderr


_WAIT_PROGRAM = r'''
import concurrent.futures, signal, threading, traceback
from slotformer_jax.data.write import pool
future = concurrent.futures.Future()
# Ctrl-C 0.3 s into the wait; the future would finish only after 30 s.
threading.Timer(0.3, signal.raise_signal, (signal.SIGINT,)).start()
finisher = threading.Timer(30, future.set_result, (1,))
finisher.daemon = True
finisher.start()
try:
  pool.wait_done([future])
  print('not interrupted')
except KeyboardInterrupt as error:
  frames = traceback.extract_tb(error.__traceback__)
  print('raised in', frames[-1].filename.rsplit('/', 1)[-1], frames[-1].name)
  print('handler restored',
        signal.getsignal(signal.SIGINT) is signal.default_int_handler)
'''


def test_ctrl_c_while_waiting_on_workers_is_raised_outside_any_lock():
  """The converter's Ctrl-C once ended in "RuntimeError: release unlocked
  lock" with a traceback: the KeyboardInterrupt landed inside threading's
  Condition.wait under `as_completed`. `wait_done` notes Ctrl-C and raises
  it from its own frame, at once, with the default handler put back."""
  started = time.monotonic()
  result = subprocess.run([sys.executable, '-c', _WAIT_PROGRAM],
                          env=dict(os.environ, PYTHONPATH=ROOT),
                          capture_output=True, text=True, timeout=60)
  assert result.returncode == 0, result.stderr[-3000:]
  assert result.stdout.splitlines() == [
      'raised in pool.py __exit__', 'handler restored True'], result.stdout
  assert time.monotonic() - started < 20  # not after the future's 30 s
