"""The one process pool of the offline writers (converters, synthetic
generator): 'spawn' workers that die with their parent.

'spawn' because the parent may hold threads (JAX, tfds) that make fork
unsafe. A killed parent (kill -9, OOM) must not leave workers rendering
forever: on Linux the kernel kills them (PR_SET_PDEATHSIG), and everywhere a
watchdog thread exits the worker once its parent is gone.

The parent waits on the workers' futures through `wait_done`, never through
a bare `Future.result()` / `as_completed`: Python raises Ctrl-C's
KeyboardInterrupt wherever the main thread is, and inside threading's
`Condition.wait` (how futures are waited on) it can leave the condition's
lock released, so the process ended with "RuntimeError: release unlocked
lock" and a traceback instead of its one `interrupted:` line (seen once in
tests/reliability/test_faults.py).
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import TypeVar

_PR_SET_PDEATHSIG = 1
T = TypeVar('T')
# How often a wait on the workers wakes up to see whether Ctrl-C came.
_POLL_SECONDS = 0.2


def _die_with_parent(parent_pid: int) -> None:
  """Worker initializer. Ctrl-C in a terminal reaches every process of the
  group: the workers ignore it and the parent, which stops the pool,
  reports it (one line instead of one traceback per worker)."""
  signal.signal(signal.SIGINT, signal.SIG_IGN)
  if sys.platform.startswith('linux'):
    try:
      libc = ctypes.CDLL(None, use_errno=True)
      libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):
      pass
  if os.getppid() != parent_pid:  # the parent died before prctl
    os._exit(1)

  def watch() -> None:
    while True:
      time.sleep(1.0)
      if os.getppid() != parent_pid:
        os._exit(1)

  threading.Thread(target=watch, daemon=True, name='die-with-parent').start()


class _Pool(concurrent.futures.ProcessPoolExecutor):
  """Workers are started with SIGINT ignored: Ctrl-C in a terminal reaches
  every process of the group, and a worker still importing (a 'spawn'
  worker imports for seconds) would print a KeyboardInterrupt traceback.
  The parent reports the Ctrl-C and stops the pool."""

  def _adjust_process_count(self):  # where the executor starts workers
    if threading.current_thread() is not threading.main_thread():
      super()._adjust_process_count()
      return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
      super()._adjust_process_count()
    finally:
      signal.signal(signal.SIGINT, previous)


class _CtrlCDeferred:
  """Within the block, Ctrl-C is noted (`received`) instead of raised; the
  block's end raises the KeyboardInterrupt, outside any lock. Main thread
  only, and only where Ctrl-C would raise KeyboardInterrupt (Python's
  default handler): a handler the program set (training's, main's with
  several processes) or an ignored SIGINT is left as it is."""

  def __init__(self):
    self.received = False
    self._previous = None

  def __enter__(self) -> _CtrlCDeferred:
    if (threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
      self._previous = signal.signal(signal.SIGINT, self._note)
    return self

  def _note(self, signum, frame) -> None:
    del signum, frame
    self.received = True

  def __exit__(self, exc_type, *exc) -> bool:
    if self._previous is not None:
      signal.signal(signal.SIGINT, self._previous)
    if self.received and exc_type is None:
      raise KeyboardInterrupt
    return False


def wait_done(futures) -> set[concurrent.futures.Future]:
  """Blocks until one of `futures` is done and returns those done; Ctrl-C
  meanwhile raises KeyboardInterrupt here (module docstring)."""
  done = set()
  with _CtrlCDeferred() as ctrl_c:  # raises on leaving if Ctrl-C came
    while not done and not ctrl_c.received:
      done, _ = concurrent.futures.wait(
          futures, timeout=_POLL_SECONDS,
          return_when=concurrent.futures.FIRST_COMPLETED)
  return done


def _make_each(make: Callable[[int], T], indices: range) -> list[T]:
  return [make(index) for index in indices]


def process_pool(num_workers: int) -> concurrent.futures.ProcessPoolExecutor:
  """A 'spawn' pool whose workers exit when this process dies and ignore
  Ctrl-C (the parent handles it). Unlike multiprocessing.Pool (which
  respawns dying workers forever), the executor fails fast if workers
  cannot start."""
  return _Pool(
      num_workers, mp_context=multiprocessing.get_context('spawn'),
      initializer=_die_with_parent, initargs=(os.getpid(),))


def ordered_map(make: Callable[[int], T], count: int,
                num_workers: int | None = None) -> Iterator[T]:
  """``make(0), ..., make(count - 1)`` in index order, computed by
  ``num_workers`` processes (default: the available cores; 1: in this
  process). ``make`` must be picklable and depend on its index alone, so
  the output is the serial one whatever the worker count."""
  workers = min(num_workers or len(os.sched_getaffinity(0)), count)
  if workers <= 1:
    for index in range(count):
      yield make(index)
    return
  pool = process_pool(workers)
  try:
    # Four indices per task, as Executor.map(chunksize=4) would send them.
    futures = [pool.submit(_make_each, make, range(start, min(start + 4, count)))
               for start in range(0, count, 4)]
    for future in futures:
      wait_done([future])
      yield from future.result()
  except concurrent.futures.process.BrokenProcessPool as error:
    raise RuntimeError(
        'Data-generation worker processes died (out of memory?). With the '
        '"spawn" start method they re-import the main script, so a script '
        "that builds a dataset must do so under `if __name__ == '__main__':`;"
        ' or set the data config field num_workers=1.') from error
  finally:
    # On an early exit (error, Ctrl-C) drop the queued items instead of
    # computing them all before returning.
    pool.shutdown(wait=True, cancel_futures=True)
