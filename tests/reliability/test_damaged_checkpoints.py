"""A checkpoint whose bytes differ from what was saved is never restored
(issue 53): each step's files are recorded in `<step>/sha256.json` once
orbax has finished it; a restore checks them first. Training sets a damaged
step aside (`<step>.damaged-<time>`) and resumes from the newest intact one,
and the rerun finishes; a damaged step that is the only one is one line
whose advice works; read-only restores (evaluation, extraction) skip it
without renaming anything; steps saved before digests still restore.

The one-parameter linear stage (tests/linear_stage.py) runs the trainer's
own loop in seconds; two processes agreeing on the step: the slow test in
test_multiprocess.py.
"""

import dataclasses
import glob
import itertools
import json
import logging
import os
import threading
import time

import jax
from jax.sharding import Mesh
import numpy as np
import pytest

from slotformer_jax.errors import UserError
from slotformer_jax.runtime import checkpoint as checkpoint_lib
from slotformer_jax.runtime import checkpoint_digest as digest_lib
from slotformer_jax.runtime import processes
from slotformer_jax.runtime import sharding
from slotformer_jax.train.trainer import fit

from linear_stage import linear_stage


def _mesh():
  return Mesh(np.asarray(jax.devices()[:1]), ('data',))


def _train(directory, steps=4, every=2):
  return fit(linear_stage(directory, num_train_steps=steps,
                          checkpoint_every=every), mesh=_mesh(), seed=0)


def _largest_file(step_directory):
  files = [f for f in glob.glob(os.path.join(step_directory, '**'),
                                recursive=True)
           if os.path.isfile(f) and not f.endswith(checkpoint_lib.DIGEST_FILE)]
  return max(files, key=os.path.getsize)


def _overwrite(step_directory, count=1024):
  """`count` bytes in the middle of the step's largest file replaced."""
  path = _largest_file(step_directory)
  size = os.path.getsize(path)
  with open(path, 'r+b') as f:
    f.seek(max(0, size // 2 - count // 2))
    old = f.read(min(count, size))
    f.seek(max(0, size // 2 - count // 2))
    f.write(bytes(b ^ 0x5A for b in old))


def _truncate(step_directory):
  path = _largest_file(step_directory)
  os.truncate(path, os.path.getsize(path) // 2)


def _warnings(caplog):
  """This project's warning lines (orbax's own are left out)."""
  return [r.getMessage() for r in caplog.records
          if r.levelno == logging.WARNING
          and r.name.startswith('slotformer_jax')]


def _listing(directory):
  """The steps and set-aside steps of a checkpoints folder."""
  return sorted(n for n in os.listdir(directory)
                if n != digest_lib.SINCE_FILE)


def _snapshot(directory):
  out = {}
  for root, _, names in os.walk(directory):
    for name in names:
      path = os.path.join(root, name)
      with open(path, 'rb') as f:
        out[os.path.relpath(path, directory)] = f.read()
  return out


@pytest.fixture(scope='module')
def trained(tmp_path_factory):
  """A linear stage trained 4 steps (checkpoints 2 and 4) and its params."""
  directory = tmp_path_factory.mktemp('damaged') / 'linear'
  state = _train(directory)
  return directory, np.asarray(state.params['w'])


@pytest.fixture
def copied(trained, tmp_path):
  import shutil  # pylint: disable=g-import-not-at-top
  directory, params = trained
  copy = tmp_path / 'linear'
  shutil.copytree(directory, copy)
  return copy, params


def test_every_saved_step_records_its_files(trained):
  directory, _ = trained
  checkpoints = directory / 'checkpoints'
  assert _listing(checkpoints) == ['2', '4']
  assert digest_lib.digests_since(str(checkpoints)) == 2
  for step in ('2', '4'):
    with open(checkpoints / step / checkpoint_lib.DIGEST_FILE) as f:
      digest = json.load(f)
    files = {os.path.relpath(p, checkpoints / step)
             for p in glob.glob(str(checkpoints / step / '**'), recursive=True)
             if os.path.isfile(p)}
    assert set(digest['files']) == files - {checkpoint_lib.DIGEST_FILE}
    assert checkpoint_lib.damage_of(str(checkpoints / step)) is None


@pytest.mark.parametrize('damage', [_overwrite, _truncate])
def test_a_damaged_newest_step_is_set_aside_and_the_rerun_finishes(
    copied, damage, caplog):
  directory, params = copied
  checkpoints = directory / 'checkpoints'
  damage(str(checkpoints / '4'))
  with caplog.at_level(logging.WARNING):
    state = _train(directory)
  # One warning line names the step, why, where it went, and the step used.
  lines = _warnings(caplog)
  assert len(lines) == 1, lines
  assert 'step 4 is damaged' in lines[0]
  assert ('holds other bytes than were saved' if damage is _overwrite
          else 'bytes, ') in lines[0]
  assert 'set aside as 4.damaged-' in lines[0]
  assert 'newest intact checkpoint, step 2' in lines[0]
  # Resumed from 2 and saved step 4 again (no StepAlreadyExistsError):
  # the same parameters as the uninterrupted run.
  assert int(state.step) == 4
  np.testing.assert_array_equal(np.asarray(state.params['w']), params)
  names = _listing(checkpoints)
  assert names[:2] == ['2', '4'] and len(names) == 3
  assert names[2].startswith('4.damaged-')
  assert checkpoint_lib.damage_of(str(checkpoints / '4')) is None
  # The next run finds everything intact.
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    _train(directory)
  assert not _warnings(caplog)


def test_a_damaged_only_step_is_one_line_whose_advice_works(tmp_path):
  directory = tmp_path / 'linear'
  _train(directory, steps=4, every=4)
  checkpoints = directory / 'checkpoints'
  _overwrite(str(checkpoints / '4'))
  with pytest.raises(checkpoint_lib.DamagedCheckpointError) as raised:
    _train(directory, steps=4, every=4)
  message = str(raised.value)
  assert '\n' not in message
  assert 'step 4 is damaged' in message and 'set aside as 4.damaged-' in message
  assert 'Re-run the same command: it trains from step 0' in message
  # Following it: the rerun trains from step 0 and saves step 4 again.
  state = _train(directory, steps=4, every=4)
  assert int(state.step) == 4
  assert _listing(checkpoints)[0] == '4'
  assert checkpoint_lib.damage_of(str(checkpoints / '4')) is None


def test_steps_saved_before_digests_still_restore(copied, caplog):
  directory, params = copied
  checkpoints = directory / 'checkpoints'
  for step in ('2', '4'):
    os.remove(checkpoints / step / checkpoint_lib.DIGEST_FILE)
  os.remove(checkpoints / digest_lib.SINCE_FILE)  # a folder before digests
  checkpointer = checkpoint_lib.Checkpointer(str(checkpoints),
                                             read_only=True)
  with caplog.at_level(logging.WARNING):
    fields, step = checkpointer.restore_fields(
        {'params': {'w': jax.ShapeDtypeStruct((3,), np.float32)}})
  checkpointer.close()
  assert step == 4 and not _warnings(caplog)
  np.testing.assert_array_equal(np.asarray(fields['params']['w']), params)
  # Nothing is recorded retroactively (a read-only restore writes nothing).
  assert not os.path.exists(checkpoints / '4' / checkpoint_lib.DIGEST_FILE)
  # Such a step cut short is still skipped by orbax's own read error, and
  # training sets it aside so that the step can be saved again.
  _truncate(str(checkpoints / '4'))
  with caplog.at_level(logging.WARNING):
    state = _train(directory)
  assert 'could not be read' in caplog.text and '4.damaged-' in caplog.text
  assert int(state.step) == 4


def _restore_read_only(directory):
  return checkpoint_lib.restore_params(
      str(directory), {'w': jax.ShapeDtypeStruct((3,), np.float32)},
      sharding.replicated_sharding(_mesh()), what='linear',
      train_command='python -m train_linear')


def test_read_only_restores_skip_a_damaged_step_and_rename_nothing(
    copied, caplog):
  directory, _ = copied
  checkpoints = directory / 'checkpoints'
  _overwrite(str(checkpoints / '4'))
  before = _snapshot(directory)
  with caplog.at_level(logging.WARNING):
    params, step = _restore_read_only(directory)
  assert step == 2
  assert 'step 4 is damaged' in caplog.text and 'set aside' not in caplog.text
  assert np.asarray(params['w']).shape == (3,)
  # Every step damaged: one line naming the training command; nothing moved.
  _truncate(str(checkpoints / '2'))
  before = _snapshot(directory)
  with pytest.raises(UserError) as raised:
    _restore_read_only(directory)
  message = str(raised.value)
  assert '\n' not in message
  assert 'no intact checkpoint' in message
  assert 'step 4 is damaged' in message and 'step 2 is damaged' in message
  assert 'python -m train_linear' in message
  assert _snapshot(directory) == before


def test_a_damaged_digest_file_counts_as_damage(copied):
  directory, _ = copied
  step = directory / 'checkpoints' / '4'
  for text in ('{', '{"format": 3}', json.dumps(
      {'format': 'slotformer_jax checkpoint digest', 'version': 1,
       'files': {'../2/default/_METADATA': {'bytes': 1, 'sha256': 'x'}}})):
    (step / checkpoint_lib.DIGEST_FILE).write_text(text)
    assert 'sha256.json is unreadable' in checkpoint_lib.damage_of(str(step))
  os.remove(step / checkpoint_lib.DIGEST_FILE)
  assert checkpoint_lib.damage_of(str(step)) is None


def test_processes_go_by_process_0s_verdict(copied, monkeypatch):
  """Process 1 (simulated) reads no digest: it skips the steps process 0
  found damaged and uses the step every process could read."""
  directory, _ = copied
  checkpoints = directory / 'checkpoints'
  calls = []

  def gathered(values):
    calls.append(list(values))
    if len(calls) == 1:  # the verdicts: process 0 found step 4 damaged
      return np.asarray([[1, 0], [0, 0]])
    return np.asarray([values, values])
  class SecondProcess:  # jax as checkpoint.py sees it (orbax keeps its own)
    process_index = staticmethod(lambda: 1)
    process_count = staticmethod(lambda: 2)

    def __getattr__(self, name):
      return getattr(jax, name)
  monkeypatch.setattr(checkpoint_lib, 'jax', SecondProcess())
  monkeypatch.setattr(processes, 'gathered', gathered)
  checkpointer = checkpoint_lib.Checkpointer(str(checkpoints),
                                             read_only=True)
  _, step = checkpointer.restore_fields(
      {'params': {'w': jax.ShapeDtypeStruct((3,), np.float32)}})
  checkpointer.close()
  assert step == 2
  assert calls[0] == [0, 0]  # process 1 checked nothing itself


class _Hang(Exception):
  pass


@pytest.fixture
def no_hang():
  """A test body that blocks for 20 s fails instead of hanging the suite."""
  import signal  # pylint: disable=g-import-not-at-top

  def fire(signum, frame):
    del signum, frame
    raise _Hang('blocked for 20 s: a FIFO or a device was opened')
  previous = signal.signal(signal.SIGALRM, fire)
  signal.alarm(20)
  yield
  signal.alarm(0)
  signal.signal(signal.SIGALRM, previous)


def _digest_of(step):
  with open(step / checkpoint_lib.DIGEST_FILE) as f:
    return json.load(f)


def _write(path, value):
  path.write_text(value if isinstance(value, str) else json.dumps(value))


def _with_number(step, number_text):
  """sha256.json with its first file's size written as `number_text`."""
  digest = _digest_of(step)
  name = sorted(digest['files'])[0]
  digest['files'][name]['bytes'] = 12345
  return json.dumps(digest).replace('12345', number_text)


def _hostile_digests(step, tmp_path):
  """(what, how to make it) for each digest the issue and the review
  found to crash or hang a run, and the neighbours of each."""
  digest_path = step / checkpoint_lib.DIGEST_FILE
  name = sorted(_digest_of(step)['files'])[0]

  def replace_by(make):
    def apply():
      os.remove(digest_path)
      make(digest_path)
    return apply

  def listed_file(make):
    def apply():
      digest = _digest_of(step)
      os.remove(step / name)
      make(step / name)
      digest['files'][name]['bytes'] = 0
      _write(digest_path, digest)
    return apply

  def text(value):
    return lambda: _write(digest_path, value)
  outside = tmp_path / 'outside.json'
  outside.write_text(digest_path.read_text())
  return {
      'bytes 1e400': text(_with_number(step, '1e400')),
      'bytes 2**64': text(_with_number(step, str(2**64))),
      'bytes -1': text(_with_number(step, '-1')),
      'bytes true': text(_with_number(step, 'true')),
      'bytes 12345.0': text(_with_number(step, '12345.0')),
      'bytes of 5000 digits': text(_with_number(step, '9' * 5000)),
      'nested 100,000 deep': text('[' * 100_000 + ']' * 100_000),
      'nested in an entry': text(_with_number(step, '[[[[1]]]]')),
      'sha256 a number': text(json.dumps(_digest_of(step)).replace(
          '"sha256": "', '"sha256": 1, "x": "', 1)),
      'files a list': text({'format': 'slotformer_jax checkpoint digest',
                            'version': 1, 'files': []}),
      'a FIFO': replace_by(os.mkfifo),
      'a link to /dev/zero': replace_by(lambda p: os.symlink('/dev/zero', p)),
      'a link out of the step': replace_by(lambda p: os.symlink(outside, p)),
      'a folder': replace_by(os.mkdir),
      '17 MiB': replace_by(lambda p: os.truncate(
          open(p, 'wb').name, 17 << 20)),  # sparse: nothing is read
      'a listed file that is a FIFO': listed_file(os.mkfifo),
      'a listed file linked to /dev/zero': listed_file(
          lambda p: os.symlink('/dev/zero', p)),
  }


HOSTILE = ['bytes 1e400', 'bytes 2**64', 'bytes -1', 'bytes true',
           'bytes 12345.0', 'bytes of 5000 digits', 'nested 100,000 deep',
           'nested in an entry', 'sha256 a number', 'files a list', 'a FIFO',
           'a link to /dev/zero', 'a link out of the step', 'a folder',
           '17 MiB', 'a listed file that is a FIFO',
           'a listed file linked to /dev/zero']


@pytest.mark.parametrize('kind', HOSTILE)
def test_a_hostile_digest_is_damage_not_a_crash_or_a_hang(
    copied, kind, tmp_path, no_hang):
  """Issue 61, case 1: `"bytes": 1e400` was an OverflowError traceback, a
  digest nested 100,000 deep a RecursionError, a FIFO hung the run."""
  directory, _ = copied
  step = directory / 'checkpoints' / '4'
  _hostile_digests(step, tmp_path)[kind]()
  reason = checkpoint_lib.damage_of(str(step))
  assert reason is not None and '\n' not in reason, reason
  assert checkpoint_lib.damage_of(str(directory / 'checkpoints' / '2')) is None


@pytest.mark.parametrize('kind', ['a FIFO', 'bytes 1e400',
                                  'nested 100,000 deep'])
def test_training_sets_a_step_with_a_hostile_digest_aside(
    copied, kind, tmp_path, caplog, no_hang):
  directory, params = copied
  checkpoints = directory / 'checkpoints'
  _hostile_digests(checkpoints / '4', tmp_path)[kind]()
  # A read-only restore (evaluation, extraction) skips it, moves nothing.
  with caplog.at_level(logging.WARNING):
    _, step = _restore_read_only(directory)
  assert step == 2 and 'step 4 is damaged' in caplog.text
  assert _listing(checkpoints) == ['2', '4']
  caplog.clear()
  with caplog.at_level(logging.WARNING):
    state = _train(directory)
  lines = _warnings(caplog)
  assert len(lines) == 1 and 'sha256.json is unreadable' in lines[0], lines
  assert 'set aside as 4.damaged-' in lines[0]
  np.testing.assert_array_equal(np.asarray(state.params['w']), params)


def test_a_step_whose_digest_was_never_written_is_not_taken_as_intact(
    copied, caplog):
  """Issue 61, case 4: killed between orbax's commit and the digest, then
  1 kB damaged: it was restored, and training stopped on NaN advice."""
  directory, params = copied
  checkpoints = directory / 'checkpoints'
  os.remove(checkpoints / '4' / checkpoint_lib.DIGEST_FILE)
  _overwrite(str(checkpoints / '4'))
  with caplog.at_level(logging.WARNING):
    state = _train(directory)
  lines = _warnings(caplog)
  assert len(lines) == 1, lines
  assert 'step 4 is damaged (it has no sha256.json' in lines[0]
  assert 'newest intact checkpoint, step 2' in lines[0]
  np.testing.assert_array_equal(np.asarray(state.params['w']), params)


def test_a_step_that_cannot_be_set_aside_is_named_and_skipped(
    copied, caplog, monkeypatch):
  """Issue 61, case 2: a read-only checkpoints folder made the set-aside
  rename an `OSError: [Errno 30]` traceback."""
  import errno  # pylint: disable=g-import-not-at-top
  directory, _ = copied
  checkpoints = directory / 'checkpoints'

  def read_only(folder, step):
    raise OSError(errno.EROFS, os.strerror(errno.EROFS))
  monkeypatch.setattr(checkpoint_lib, 'set_aside', read_only)
  _overwrite(str(checkpoints / '4'))
  abstract = {'params': {'w': jax.ShapeDtypeStruct((3,), np.float32)}}
  checkpointer = checkpoint_lib.Checkpointer(str(checkpoints))
  with caplog.at_level(logging.WARNING):
    _, step = checkpointer.restore_fields(abstract)
  checkpointer.close()
  lines = _warnings(caplog)
  assert step == 2 and len(lines) == 1, lines
  assert 'step 4 is damaged' in lines[0]
  assert 'not set aside (Read-only file system)' in lines[0]
  assert 'newest intact checkpoint, step 2' in lines[0]
  # Every step damaged: one line that says what to do.
  _truncate(str(checkpoints / '2'))
  checkpointer = checkpoint_lib.Checkpointer(str(checkpoints))
  with pytest.raises(checkpoint_lib.DamagedCheckpointError) as raised:
    checkpointer.restore_fields(abstract)
  checkpointer.close()
  message = str(raised.value)
  assert '\n' not in message and 'Make the folder writable' in message
  assert _listing(checkpoints) == ['2', '4']


def test_slots_of_a_lost_newer_step_name_the_retraining_not_extraction(
    tmp_path):
  """Issue 61, case 3: with SAVi's newest step damaged, evaluation said
  the slots were stale and to re-extract them, which rewrote good slots
  from the older step; retraining the lost steps is what restores it."""
  from slotformer_jax.slot_models import chain as chain_lib  # pylint: disable=g-import-not-at-top
  from slotformer_jax.workdir.paths import Paths  # pylint: disable=g-import-not-at-top
  paths = Paths.of(str(tmp_path / 'run'))
  directory = paths.slots('test')
  os.makedirs(directory)
  fields = {'chunk_length': 8}
  with open(os.path.join(directory, 'meta.json'), 'w') as f:
    json.dump({'complete': True, 'fields': fields,
               'parent': {'savi_run_id': 'r1', 'savi_step': 30}}, f)
  with pytest.raises(UserError) as raised:
    chain_lib.check_slots_current(
        paths, 'test', {'savi_run_id': 'r1', 'savi_step': 20}, fields, 'SAVi')
  message = str(raised.value)
  assert '\n' not in message and 'extract_slots' not in message, message
  assert 'made by SAVi step 30' in message
  assert 'newest intact checkpoint is step 20' in message
  assert f'--workdir={paths.stage1} --mode=train_savi' in message
  # Slots of another SAVi run are stale: re-extracting them is right.
  with pytest.raises(UserError, match='are stale.*--mode=extract_slots'):
    chain_lib.check_slots_current(
        paths, 'test', {'savi_run_id': 'r2', 'savi_step': 30}, fields, 'SAVi')


def _nan_from(stage, step):
  plain = stage.batches

  def batches(start_step):
    for k, batch in zip(itertools.count(start_step), plain(start_step)):
      yield {'x': batch['x'] * np.nan} if k >= step else batch
  return dataclasses.replace(stage, batches=batches)


def test_a_divergence_right_after_a_resume_names_the_restored_step(tmp_path):
  """Issue 61, case 3: the advice blamed the learning rate only, when the
  restored checkpoint was a damaged one."""
  from linear_stage import linear_stage as make  # pylint: disable=g-import-not-at-top
  from slotformer_jax.train.trainer import Diverged  # pylint: disable=g-import-not-at-top
  _train(tmp_path / 'linear', steps=4, every=2)
  stage = _nan_from(make(tmp_path / 'linear', num_train_steps=6,
                         checkpoint_every=2), 4)
  with pytest.raises(Diverged) as raised:
    fit(stage, mesh=_mesh(), seed=0)
  message = str(raised.value)
  assert '\n' not in message
  assert 'right after resuming from step 4' in message
  assert os.path.join(str(tmp_path / 'linear' / 'checkpoints'), '4') in message
  # Diverging later, or without a resume, is the plain line.
  fresh = _nan_from(make(tmp_path / 'fresh', num_train_steps=6,
                         checkpoint_every=2), 3)
  with pytest.raises(Diverged) as raised:
    fit(fresh, mesh=_mesh(), seed=0)
  assert 'resuming' not in str(raised.value)


def test_a_file_the_digest_does_not_list_is_damage(copied):
  """An entry deleted from sha256.json would leave its file unchecked."""
  directory, _ = copied
  step = directory / 'checkpoints' / '4'
  digest = _digest_of(step)
  name = sorted(digest['files'])[0]
  del digest['files'][name]
  _write(step / checkpoint_lib.DIGEST_FILE, digest)
  reason = checkpoint_lib.damage_of(str(step))
  assert reason == f'{name} is not in its sha256.json', reason


def test_extraction_keeps_slots_of_a_lost_newer_step(tmp_path):
  """--mode=extract_slots with SAVi's newest step damaged re-extracted the
  good slots from the older step; it now stops with the retraining line
  (followed as written: train_savi reproduces step 20, after which the
  slots are 'already extracted'; by hand on configs/synthetic.py:tiny)."""
  import types  # pylint: disable=g-import-not-at-top
  from slotformer_jax.stages import extract  # pylint: disable=g-import-not-at-top
  from slotformer_jax.workdir.paths import Paths  # pylint: disable=g-import-not-at-top
  run = types.SimpleNamespace(paths=Paths.of(str(tmp_path / 'run')))
  with pytest.raises(UserError) as raised:
    extract._refuse_lost_steps(  # pylint: disable=protected-access
        run, 'slots/train', {'savi_run_id': 'r', 'savi_step': 20},
        {'savi_run_id': 'r', 'savi_step': 10}, 'SAVi')
  message = str(raised.value)
  assert '--mode=train_savi' in message and 'extract_slots' not in message
  # Another SAVi run: re-extracting is right, nothing is refused.
  extract._refuse_lost_steps(  # pylint: disable=protected-access
      run, 'slots/train', {'savi_run_id': 'old', 'savi_step': 20},
      {'savi_run_id': 'r', 'savi_step': 10}, 'SAVi')


# --------------------------------------------------------------------------
# A peer killed right after a save: the survivor's watchdog exit keeps the
# committed step's digest (issue 61; two real processes: the slow
# test_multiprocess.py::test_sigkill_of_one_process_stops_the_other_...).
# --------------------------------------------------------------------------


def _digested(step_directory, seconds):
  deadline = time.monotonic() + seconds
  path = os.path.join(step_directory, checkpoint_lib.DIGEST_FILE)
  while not os.path.exists(path) and time.monotonic() < deadline:
    time.sleep(0.02)
  return os.path.exists(path)


def test_a_committed_step_is_digested_while_orbax_still_waits(tmp_path,
                                                              monkeypatch):
  """After its commit orbax waits for every process at a barrier, which a
  killed one never reaches; the digest is written without waiting for it
  (before: the digest thread waited in `wait_until_finished` forever)."""
  checkpointer = checkpoint_lib.Checkpointer(str(tmp_path / 'checkpoints'))
  barrier = threading.Event()
  real_wait = checkpointer._manager.wait_until_finished  # pylint: disable=protected-access

  def stuck_at_the_barrier():
    # Only the digest thread is held: orbax's own save calls this too.
    if threading.current_thread().name.startswith('checkpoint digest'):
      barrier.wait(60)
    real_wait()
  monkeypatch.setattr(checkpointer._manager, 'wait_until_finished',  # pylint: disable=protected-access
                      stuck_at_the_barrier)
  monkeypatch.setattr(checkpointer._manager, 'is_saving_in_progress',  # pylint: disable=protected-access
                      lambda: not barrier.is_set())
  try:
    checkpointer.save(1, {'x': np.arange(4.0)})
    assert _digested(str(tmp_path / 'checkpoints' / '1'), 20)
  finally:
    barrier.set()
    checkpointer.close()
  assert checkpoint_lib.damage_of(str(tmp_path / 'checkpoints' / '1'),
                                  required=True) is None


def test_the_watchdog_exit_waits_for_the_digest_in_flight(tmp_path,
                                                          monkeypatch):
  """A slow digest (a loaded host, a large step) is written before the
  watchdog's `os._exit` (before: the exit came first, and the rerun found
  the committed step undigested, damaged: 'it trains from step 0')."""
  real_write = checkpoint_lib.write_digest

  def slow_write(step_directory):
    time.sleep(1.0)
    real_write(step_directory)
  monkeypatch.setattr(checkpoint_lib, 'write_digest', slow_write)
  exits = []
  monkeypatch.setattr(processes.os, '_exit', exits.append)
  checkpointer = checkpoint_lib.Checkpointer(str(tmp_path / 'checkpoints'))
  step = str(tmp_path / 'checkpoints' / '1')
  try:
    checkpointer.save(1, {'x': np.arange(4.0)})
    os.makedirs(tmp_path / 'processes')
    watchdog = processes.PeerWatchdog(str(tmp_path / 'processes'), 1, 2,
                                      timeout=1.0)
    watchdog.leave(1, 'a peer is lost')  # os._exit recorded, not done
    assert exits == [1]
    assert os.path.exists(os.path.join(step, checkpoint_lib.DIGEST_FILE))
  finally:
    checkpointer.close()
  assert processes._before_exit == []  # pylint: disable=protected-access


def test_the_exit_hooks_are_bounded(monkeypatch):
  """A hook that never returns delays the exit by `EXIT_GRACE_SECONDS` at
  most (a save cut short by the lost peer is never committed)."""
  monkeypatch.setattr(processes, 'EXIT_GRACE_SECONDS', 0.3)
  forever = threading.Event()
  calls = []

  def stuck(seconds):
    calls.append(seconds)
    forever.wait(seconds)
  processes.before_exit(stuck)
  processes.before_exit(stuck)
  try:
    started = time.monotonic()
    processes._run_before_exit(processes.EXIT_GRACE_SECONDS)  # pylint: disable=protected-access
    took = time.monotonic() - started
  finally:
    processes.not_before_exit(stuck)
    processes.not_before_exit(stuck)
  assert took < 1.0, took
  assert len(calls) == 1 and calls[0] <= 0.3  # the second: no time left


def test_the_replica_slice_threshold_is_set_and_both_sizes_restore(
    tmp_path):
  """The array handler the checkpoint module registers keeps orbax's
  replica-parallel saving for slices of MIN_REPLICA_SLICE_BYTES or more and
  writes smaller arrays whole; a replicated array on each side of the
  threshold comes back as saved. (Which arrays orbax splits is orbax's
  rule, not checked here.)"""
  import orbax.checkpoint as ocp  # pylint: disable=g-import-not-at-top
  handler = ocp.type_handlers.get_type_handler(jax.Array)
  assert (handler._min_slice_bytes_for_replica_parallel  # pylint: disable=protected-access
          == checkpoint_lib.MIN_REPLICA_SLICE_BYTES)
  mesh = Mesh(np.asarray(jax.devices()[:4]), ('data',))
  replicated = sharding.replicated_sharding(mesh)
  rng = np.random.default_rng(0)
  # 4 MiB split over 4 devices: 1 MiB slices, split; 4 KiB: written whole.
  state = {'large': rng.normal(size=(1024, 1024)).astype(np.float32),
           'small': rng.normal(size=(32, 32)).astype(np.float32)}
  placed = jax.device_put(state, replicated)
  checkpointer = checkpoint_lib.Checkpointer(str(tmp_path / 'ckpt'))
  checkpointer.save(1, placed)
  checkpointer.wait_until_finished()
  abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(
      x.shape, x.dtype, sharding=replicated), placed)
  restored = checkpointer.restore(abstract, step=1)
  for name, value in state.items():
    np.testing.assert_array_equal(np.asarray(restored[name]), value)
  checkpointer.close()
