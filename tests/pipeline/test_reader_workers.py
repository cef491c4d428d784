"""Reader worker processes (`train_batches(num_workers=N)`, data/workers.py):
the same stream as in-process, workers stopped on close, failures reported in
one line without hanging, signals, memory-mapped sources."""

from __future__ import annotations

import gc
import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from slotformer_jax.data import pipeline
from slotformer_jax.data import workers


class CodeSource:
  """Picklable: video i frame t has pixels (100 i + t) % 256, `code` the
  full value; `fail_at`: reading that video raises; `slow`: seconds per read.
  """

  def __init__(self, lengths, fail_at=None, slow=0.0):
    self.lengths = list(lengths)
    self.fail_at = fail_at
    self.slow = slow

  def __len__(self):
    return len(self.lengths)

  def __getitem__(self, index):
    if index == self.fail_at:
      raise ValueError(f'broken record {index}')
    if self.slow:
      time.sleep(self.slow)
    code = (100 * index + np.arange(self.lengths[index])).astype(np.int32)
    # 'video' is 3 x 4 x 12 = 144 bytes a batch: 'code' after it starts on
    # the next 64-byte boundary in the worker's block.
    return {'video': np.broadcast_to(code[:, None, None, None] % 256,
                                     (len(code), 1, 1, 3)).astype(np.uint8),
            'code': code, 'num': np.array(index, np.int32)}


class Unpicklable(CodeSource):

  def __reduce__(self):
    raise TypeError('not today')


def _stream(source, start_step=0, steps=7, **kwargs):
  kwargs = {'batch_size': 3, 'clip_length': 4, 'seed': 5,
            'fields': ('video', 'code', 'num'), **kwargs}
  it = pipeline.train_batches(source, start_step=start_step, **kwargs)
  try:
    return [next(it) for _ in range(steps)]
  finally:
    it.close()


def _assert_same(a, b):
  assert len(a) == len(b)
  for x, y in zip(a, b):
    assert x.keys() == y.keys()
    for key in x:
      assert x[key].dtype == y[key].dtype and x[key].shape == y[key].shape
      np.testing.assert_array_equal(x[key], y[key])


def _with_timeout(seconds):
  """Fails the test (instead of hanging the suite) after `seconds`."""
  def fail(signum, frame):
    raise TimeoutError(f'no answer within {seconds} s')
  previous = signal.signal(signal.SIGALRM, fail)
  signal.alarm(seconds)
  return previous


@pytest.fixture
def timeout():
  previous = _with_timeout(60)
  yield
  signal.alarm(0)
  signal.signal(signal.SIGALRM, previous)
  assert not multiprocessing.active_children()


def test_same_stream_for_any_number_of_workers_and_resume(timeout):
  source = CodeSource([9, 12, 10, 7, 15, 11, 8])
  reference = _stream(source, steps=10)
  _assert_same(_stream(source, steps=10, num_workers=1), reference)
  _assert_same(_stream(source, steps=10, num_workers=3), reference)
  # Resumed at step 4 with 2 workers: the same batches from step 4.
  _assert_same(_stream(source, start_step=4, steps=6, num_workers=2),
               reference[4:])
  # Host 1 of 2 reads its rows of the same global batches.
  host = dict(process_index=1, process_count=2)
  _assert_same(_stream(source, steps=5, num_workers=2, **host),
               _stream(source, steps=5, **host))


def test_workers_stop_when_the_consumer_stops(timeout):
  source = CodeSource([10] * 4)
  it = pipeline.train_batches(source, batch_size=2, clip_length=2, seed=0,
                              num_workers=2)
  next(it)
  children = multiprocessing.active_children()
  assert len(children) == 2
  it.close()
  assert not multiprocessing.active_children()
  assert all(not child.is_alive() and child.exitcode == 0
             for child in children)
  # Dropping the iterator without close() also stops them.
  it = pipeline.train_batches(source, batch_size=2, clip_length=2, seed=0,
                              num_workers=2)
  next(it)
  del it
  gc.collect()
  assert not multiprocessing.active_children()


def test_worker_error_reaches_the_consumer_in_one_line(timeout):
  # Step 0 reads video 2 (3 videos, batch 3): worker 0 fails at step 0.
  source = CodeSource([10] * 3, fail_at=2)
  it = pipeline.train_batches(source, batch_size=3, clip_length=2, seed=0,
                              num_workers=2)
  with pytest.raises(ValueError) as caught:
    next(it)
  message = str(caught.value)
  assert '\n' not in message
  assert message.startswith('training reader worker 0 (pid ')
  assert 'step 0: broken record 2' in message
  assert 'broken record 2' in caught.value.worker_traceback
  it.close()


def _cannot_reopen():
  raise OSError('cannot reopen the dataset folder')


class ReopensBadly(CodeSource):

  def __reduce__(self):
    return _cannot_reopen, ()


def test_a_source_that_fails_to_unpickle_in_the_worker(timeout):
  it = pipeline.train_batches(ReopensBadly([10] * 3), batch_size=2,
                              clip_length=2, seed=0, start_step=4,
                              num_workers=2)
  with pytest.raises(OSError, match=r'^training reader worker 0 \(pid \d+\), '
                     'step 4: cannot reopen the dataset folder$'):
    next(it)
  it.close()


def test_unpicklable_worker_error_is_a_reader_worker_error():
  previous = _with_timeout(60)
  try:
    error = workers._worker_error(1, 99, 7, None, 'Weird', 'it broke', 'tb')
    assert isinstance(error, workers.ReaderWorkerError)
    assert str(error) == ('training reader worker 1 (pid 99), step 7: '
                          'Weird: it broke')
  finally:
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def test_killed_worker_is_reported_not_hung(timeout):
  source = CodeSource([10] * 4, slow=0.05)
  it = pipeline.train_batches(source, batch_size=2, clip_length=2, seed=0,
                              num_workers=2, prefetch=1)
  next(it)
  victim = [c for c in multiprocessing.active_children()
            if c.name == 'slotformer-reader-1'][0]
  os.kill(victim.pid, signal.SIGKILL)
  started = time.time()
  with pytest.raises(workers.ReaderWorkerError) as caught:
    for _ in range(10):
      next(it)
  assert time.time() - started < 10
  message = str(caught.value)
  assert '\n' not in message
  assert f'training reader worker 1 (pid {victim.pid}) was killed by SIGKILL' \
      in message
  assert 'before delivering the batch of step' in message
  it.close()


def test_workers_ignore_sigint_and_sigterm(timeout):
  # Ctrl-C and a scheduler's SIGTERM reach the whole process group: the
  # trainer saves and then closes the stream; the workers must keep going.
  source = CodeSource([9, 12, 10, 7])
  reference = _stream(source, steps=8)
  it = pipeline.train_batches(source, batch_size=3, clip_length=4, seed=5,
                              fields=('video', 'code', 'num'), num_workers=2)
  got = [next(it)]
  for child in multiprocessing.active_children():
    os.kill(child.pid, signal.SIGTERM)
    os.kill(child.pid, signal.SIGINT)
  time.sleep(0.5)
  got += [next(it) for _ in range(7)]
  _assert_same(got, reference)
  it.close()


def test_workers_ignore_sigint_and_sigterm_while_they_start(timeout):
  # The same signals from the first moment: a worker still importing (before
  # it sets its handlers) must not die of them either.
  source = CodeSource([9, 12, 10, 7])
  reference = _stream(source, steps=4)
  it = pipeline.train_batches(source, batch_size=3, clip_length=4, seed=5,
                              fields=('video', 'code', 'num'), num_workers=2)
  done = threading.Event()
  signalled = set()

  def signal_every_worker():
    while not done.is_set():
      for child in multiprocessing.active_children():
        if child.name.startswith('slotformer-reader-'):
          os.kill(child.pid, signal.SIGTERM)
          os.kill(child.pid, signal.SIGINT)
          signalled.add(child.pid)
      time.sleep(0.002)

  sender = threading.Thread(target=signal_every_worker, daemon=True)
  sender.start()
  try:
    got = [next(it) for _ in range(4)]
  finally:
    done.set()
    sender.join()
  assert len(signalled) == 2
  _assert_same(got, reference)
  it.close()


def test_workers_exit_when_the_consumer_process_dies(tmp_path):
  script = textwrap.dedent(f'''
      import multiprocessing, os, signal, sys
      sys.path[:0] = {sys.path!r}
      from slotformer_jax.data import pipeline
      from test_reader_workers import CodeSource
      if __name__ == '__main__':
        it = pipeline.train_batches(CodeSource([10] * 4), batch_size=2,
                                    clip_length=2, seed=0, num_workers=2)
        next(it)
        print(' '.join(str(c.pid) for c in multiprocessing.active_children()),
              flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
  ''')
  path = tmp_path / 'consumer.py'
  path.write_text(script)
  result = subprocess.run([sys.executable, str(path)], capture_output=True,
                          text=True, timeout=120, cwd=os.getcwd())
  assert result.returncode == -signal.SIGKILL, result.stderr
  pids = [int(p) for p in result.stdout.split()]
  assert len(pids) == 2
  deadline = time.time() + 20
  while time.time() < deadline and any(_alive(pid) for pid in pids):
    time.sleep(0.1)
  assert not any(_alive(pid) for pid in pids)


def _alive(pid: int) -> bool:
  try:
    with open(f'/proc/{pid}/stat') as f:
      return f.read().split(') ')[-1][0] != 'Z'
  except FileNotFoundError:
    return False


def test_unpicklable_source_falls_back_to_the_thread(timeout):
  source = Unpicklable([9, 12, 10, 7])
  with pytest.warns(UserWarning, match='does not pickle .*TypeError: not '
                    'today.*thread instead of 2 worker processes'):
    got = _stream(source, steps=4, num_workers=2)
  _assert_same(got, _stream(CodeSource([9, 12, 10, 7]), steps=4))
  assert not [t for t in threading.enumerate()
              if t.name == 'slotformer-data-prefetch']


class MemmapSource:

  def __init__(self, path):
    self.frames = np.load(path, mmap_mode='r')[2:].reshape(4, 15, 1000)

  def __len__(self):
    return 4

  def __getitem__(self, index):
    return {'video': np.asarray(self.frames[index])}


def test_memory_maps_pickle_as_files_not_data(tmp_path, timeout):
  path = tmp_path / 'frames.npy'
  np.save(path, np.arange(62 * 1000, dtype=np.float32).reshape(62, 1000))
  source = MemmapSource(path)
  pickled = workers._dumps(source)
  assert len(pickled) < 2000  # not the 240 kB of data
  copy = pickle.loads(pickled)
  assert isinstance(copy.frames, np.memmap)
  np.testing.assert_array_equal(copy.frames, source.frames)
  _assert_same(_stream(source, steps=4, fields=('video',), clip_length=2,
                       num_workers=2),
               _stream(source, steps=4, fields=('video',), clip_length=2))


def test_bad_num_workers():
  with pytest.raises(ValueError, match='num_workers must be an integer >= 0'):
    pipeline.train_batches(CodeSource([4]), batch_size=1, clip_length=2,
                           seed=0, num_workers=-1)


@pytest.mark.parametrize('value', [-1, -3])
def test_config_rejects_bad_reader_workers(value):
  import slotformer_jax.dynamics  # noqa: F401  registers them, as main does
  from slotformer_jax.config import checks
  from slotformer_jax.config import defaults
  from slotformer_jax.errors import ConfigError
  config = defaults.base_config()
  config.data.reader_workers = value
  with pytest.raises(ConfigError) as caught:
    checks.validate(config, ['train_savi'], num_devices=1)
  assert (f'data.reader_workers must be an integer >= 0, got {value!r}'
          in str(caught.value))
  assert '\n' not in str(caught.value)


def test_reader_workers_is_not_a_setting_of_the_run():
  from slotformer_jax.workdir import identity
  assert 'reader_workers' in identity.NOT_SHAPING
  assert identity.ADDED_FIELDS['data.reader_workers'] == 0
