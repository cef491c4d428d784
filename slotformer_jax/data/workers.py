"""Training batches built by worker processes (numpy and the standard
library only; no jax here).

`worker_batches(make, start_step, num_workers)` yields ``make(start_step)``,
``make(start_step + 1)``, ... like `pipeline._prefetched`, but worker ``w``
builds the steps ``s`` with ``(s - start_step) % num_workers == w`` and the
consumer takes them round-robin, so the stream is the same for any number
of workers and after a resume at any step (``make`` is a pure function of
the step). Workers are ``spawn`` processes (the parent has jax's threads)
that never import the parent's main module; memory-mapped arrays pickle as
their file and offset (`_dumps`); batches come back through shared-memory
blocks, not a pipe. Workers ignore SIGINT and SIGTERM (the trainer must get
batches until it has saved) and exit when the consumer closes their control
pipe or dies; an exception in ``make`` or a dead worker ends the stream
with one line naming the worker and the step. Measurements:
docs/experiments/reader.md and docs/performance.md, "Reader worker
processes and device prefetch".
"""

from __future__ import annotations

import io
import mmap
import multiprocessing
from multiprocessing import connection as mp_connection
from multiprocessing import shared_memory
import os
import pickle
import signal
import sys
import traceback
import types
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

_POLL_S = 0.1          # how often a waiting consumer checks the workers
_JOIN_TIMEOUT_S = 30.0  # a worker finishes at most the batch it is building
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # the trainer saves; workers go on


class ReaderWorkerError(RuntimeError):
  """A reader worker failed or died; the message names it and the step."""


# ---- pickling sources -------------------------------------------------------

def _open_memmap(filename: str, dtype: str, mode: str, offset: int,
                 shape: tuple[int, ...]) -> np.memmap:
  return np.memmap(filename, dtype=np.dtype(dtype), mode=mode, offset=offset,
                   shape=shape)


def _memmap_file_offset(array: np.memmap) -> int | None:
  """The byte offset in its file of `array`'s first element, or None when
  it cannot be reopened from the file (no file, not C-contiguous)."""
  backing = getattr(array, '_mmap', None)
  if (backing is None or not getattr(array, 'filename', None)
      or not array.flags.c_contiguous or array.size == 0):
    return None
  base = np.frombuffer(backing, np.uint8).ctypes.data
  start = array.offset - array.offset % mmap.ALLOCATIONGRANULARITY
  return start + array.ctypes.data - base


class _SourcePickler(pickle.Pickler):
  """Pickles read-only memory maps as (file, offset, shape), not data."""

  def reducer_override(self, obj):  # pylint: disable=invalid-name
    if isinstance(obj, np.memmap) and obj.mode in ('r', 'c'):
      offset = _memmap_file_offset(obj)
      if offset is not None:
        return _open_memmap, (os.fspath(obj.filename), obj.dtype.str,
                              obj.mode, offset, obj.shape)
    return NotImplemented


def _dumps(obj: Any) -> bytes:
  buffer = io.BytesIO()
  _SourcePickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
  return buffer.getvalue()


def picklable(make: Callable[[int], Any]) -> tuple[bytes | None, str]:
  """(``make`` pickled for the workers, '') or (None, why it does not)."""
  try:
    return _dumps(make), ''
  except Exception as error:  # pylint: disable=broad-except
    return None, f'{type(error).__name__}: {_first_line(error)}'


def _first_line(error: BaseException) -> str:
  text = str(error).strip()
  return text.splitlines()[0][:300] if text else ''


# ---- the worker -------------------------------------------------------------

def _flatten(batch: dict[str, Any]) -> list[tuple[str, np.ndarray]]:
  if not isinstance(batch, dict):
    raise TypeError(f'a batch must be a dict of arrays, got {type(batch)}')
  return [(key, np.asarray(value)) for key, value in batch.items()]


def _aligned(nbytes: int, to: int = 64) -> int:
  """Each array of a block starts on a cache line (a float32 field after a
  uint8 one stays aligned)."""
  return -(-nbytes // to) * to


def _worker_main(index: int, num_workers: int, start_step: int, depth: int,
                 make_bytes: bytes, control: mp_connection.Connection,
                 results: mp_connection.Connection) -> None:
  """Builds steps start + index, start + index + N, ... until the control
  pipe closes. Messages to the consumer: ('block', slot, name),
  ('batch', step, slot, layout), ('error', step, pickled error or None,
  type name, first line, traceback)."""
  for signum in _STOP_SIGNALS:
    signal.signal(signum, signal.SIG_IGN)
  # Blocked since `_start` (so a signal during start-up could not kill the
  # worker); ignored now, so a pending one is dropped.
  signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
  blocks: list[shared_memory.SharedMemory | None] = [None] * depth
  free = list(range(depth))
  step = start_step + index

  def report(error: BaseException) -> None:
    try:
      pickled = pickle.dumps(error)
    except Exception:  # pylint: disable=broad-except
      pickled = None
    results.send(('error', step, pickled, type(error).__name__,
                  _first_line(error), traceback.format_exc()))
    control.recv()  # wait for the consumer to close the stream

  try:
    try:
      make = pickle.loads(make_bytes)  # e.g. reopens the source's folder
    except Exception as error:  # pylint: disable=broad-except
      report(error)
      return
    while True:
      # Blocks the consumer has copied out; EOF: the consumer is done.
      while control.poll(0 if free else None):
        free.append(control.recv())
      try:
        batch = _flatten(make(step))
      except BaseException as error:  # pylint: disable=broad-except
        report(error)
        return
      slot = free.pop(0)
      nbytes = max(1, sum(_aligned(array.nbytes) for _, array in batch))
      block = blocks[slot]
      if block is None or block.size < nbytes:
        if block is not None:
          block.close()  # the consumer unlinks it when it sees the new one
        block = blocks[slot] = shared_memory.SharedMemory(create=True,
                                                          size=nbytes)
        results.send(('block', slot, block.name))
      layout, offset = [], 0
      for key, array in batch:
        np.ndarray(array.shape, array.dtype, block.buf, offset)[...] = array
        layout.append((key, array.dtype.str, array.shape, offset))
        offset += _aligned(array.nbytes)
      results.send(('batch', step, slot, layout))
      step += num_workers
  except (EOFError, BrokenPipeError, KeyboardInterrupt):
    return
  finally:
    for block in blocks:
      if block is not None:
        block.close()


# ---- the consumer -----------------------------------------------------------

def _describe_exit(process: multiprocessing.process.BaseProcess) -> str:
  code = process.exitcode
  if code is not None and code < 0:
    try:
      return f'was killed by {signal.Signals(-code).name}'
    except ValueError:
      return f'was killed by signal {-code}'
  return f'exited with code {code}'


def worker_batches(make_bytes: bytes, start_step: int, num_workers: int,
                   depth: int = 2) -> Iterator[dict[str, np.ndarray]]:
  """Yields the batches of steps start_step, start_step + 1, ... built by
  `num_workers` processes from ``make`` (pickled by `picklable`), each with
  ``depth`` batches in flight.

  The workers start on the first ``next`` and are stopped and joined when
  the generator is closed or garbage collected.

  Raises:
    ReaderWorkerError: a worker died, or raised an error that does not
      pickle (one line naming the worker and the step).
    The worker's own error type, for one that pickles (the message then
      starts with the worker and the step).
  """
  if num_workers < 1 or depth < 1:
    raise ValueError(f'num_workers and depth must be >= 1, got {num_workers},'
                     f' {depth}')
  context = multiprocessing.get_context('spawn')
  processes, controls, results = [], [], []
  blocks: dict[tuple[int, int], shared_memory.SharedMemory] = {}
  try:
    for index in range(num_workers):
      control_r, control_w = context.Pipe(duplex=False)
      results_r, results_w = context.Pipe(duplex=False)
      process = context.Process(
          target=_worker_main, name=f'slotformer-reader-{index}',
          args=(index, num_workers, start_step, depth, make_bytes, control_r,
                results_w),
          daemon=True)
      _start(process, make_bytes)
      # The child has its own copies; closing ours lets it see our EOF.
      control_r.close()
      results_w.close()
      processes.append(process)
      controls.append(control_w)
      results.append(results_r)
    step = start_step
    while True:
      index = (step - start_step) % num_workers
      while True:
        message = _receive(results[index], processes[index], index, step)
        if message[0] == 'block':
          _, slot, name = message
          old = blocks.pop((index, slot), None)
          if old is not None:
            _release(old)
          blocks[(index, slot)] = _attach(name)
          continue
        if message[0] == 'error':
          raise _worker_error(index, processes[index].pid, *message[1:])
        break
      _, got_step, slot, layout = message
      if got_step != step:  # a bug, never the data
        raise ReaderWorkerError(f'reader worker {index} sent step {got_step}, '
                                f'expected {step}')
      buffer = blocks[(index, slot)].buf
      batch = {key: np.ndarray(shape, np.dtype(dtype), buffer, offset).copy()
               for key, dtype, shape, offset in layout}
      del buffer
      try:
        controls[index].send(slot)  # the slot is free again
      except OSError:  # BrokenPipeError: the worker died after this batch;
        pass  # its next `_receive` names it (after what it had sent)
      yield batch
      step += 1
  finally:
    for control in controls:
      control.close()  # EOF: each worker exits after its current batch
    for process in processes:
      process.join(_JOIN_TIMEOUT_S)
      if process.is_alive():
        warnings.warn(f'reader worker {process.name} did not stop within '
                      f'{_JOIN_TIMEOUT_S} s; killing it')
        process.kill()
        process.join(5.0)
    for connection in results:
      # Blocks a worker made but we never asked for: unlink them too.
      try:
        while connection.poll(0):
          message = connection.recv()
          if message[0] == 'block':
            _release(_attach(message[2]))
      except (EOFError, OSError):
        pass
      connection.close()
    for block in blocks.values():
      _release(block)


def _start(process: multiprocessing.process.BaseProcess,
           make_bytes: bytes) -> None:
  """Starts `process` without making it import the parent's main module
  (a spawned child re-imports it: the CLI's would import jax, flax and the
  models into every worker, seconds and hundreds of MB each), unless the
  pickled ``make`` refers to it (a source class defined in a script).

  SIGINT and SIGTERM are blocked in this thread while it starts the child,
  which inherits the mask through fork and exec: Ctrl-C or a scheduler's
  SIGTERM to the process group during the child's start-up (its imports,
  before `_worker_main` ignores them) stays pending instead of killing it.
  Here a blocked signal goes to another thread, or waits until the mask
  is restored: it is never lost."""
  main = sys.modules.get('__main__')
  swap = main is not None and b'__main__' not in make_bytes
  blocked = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
  try:
    if swap:
      # A module with neither __spec__ nor __file__: nothing to re-import.
      sys.modules['__main__'] = types.ModuleType('__main__')
    process.start()
  finally:
    if swap:
      sys.modules['__main__'] = main
    signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def _receive(results: mp_connection.Connection,
             process: multiprocessing.process.BaseProcess, index: int,
             step: int) -> tuple:
  """The worker's next message; a dead worker raises instead of hanging."""
  while True:
    if results.poll(_POLL_S):
      try:
        return results.recv()
      except EOFError:
        pass  # it died; say how below
    if not process.is_alive() or results.closed:
      process.join(1.0)
      raise ReaderWorkerError(
          f'training reader worker {index} (pid {process.pid}) '
          f'{_describe_exit(process)} before delivering the batch of step '
          f'{step}; re-run to resume (out of memory? see dmesg)')


def _worker_error(index: int, pid: int, step: int, pickled: bytes | None,
                  type_name: str, first_line: str, text: str
                  ) -> BaseException:
  where = f'training reader worker {index} (pid {pid}), step {step}'
  error = None
  if pickled is not None:
    try:
      error = pickle.loads(pickled)
    except Exception:  # pylint: disable=broad-except
      error = None
  if (isinstance(error, Exception) and error.args
      and isinstance(error.args[0], str)):
    error.args = (f'{where}: {error.args[0]}',) + tuple(error.args[1:])
    error.worker_traceback = text
    return error
  result = ReaderWorkerError(f'{where}: {type_name}: {first_line}')
  result.worker_traceback = text
  return result


def _attach(name: str) -> shared_memory.SharedMemory:
  # Python < 3.13 registers an attached block with the resource tracker as
  # if we had made it; we unlink it ourselves (`_release`), which
  # unregisters it again.
  return shared_memory.SharedMemory(name=name)


def _release(block: shared_memory.SharedMemory) -> None:
  try:
    block.close()
  except BufferError:
    pass  # a view still exists; the mapping goes with the process
  try:
    block.unlink()
  except FileNotFoundError:
    pass
