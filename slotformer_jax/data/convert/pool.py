"""The one process pool of the offline writers (converters, synthetic
generator): 'spawn' workers that die with their parent.

'spawn' because the parent may hold threads (JAX, tfds) that make fork
unsafe. A killed parent (kill -9, OOM) must not leave workers rendering
forever: on Linux the kernel kills them (PR_SET_PDEATHSIG), and everywhere a
watchdog thread exits the worker once its parent is gone.
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

_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent_pid: int) -> None:
  """Worker initializer."""
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


def process_pool(num_workers: int) -> concurrent.futures.ProcessPoolExecutor:
  """A 'spawn' pool whose workers exit when this process dies. Unlike
  multiprocessing.Pool (which respawns dying workers forever), the executor
  fails fast if workers cannot start."""
  return concurrent.futures.ProcessPoolExecutor(
      num_workers, mp_context=multiprocessing.get_context('spawn'),
      initializer=_die_with_parent, initargs=(os.getpid(),))
