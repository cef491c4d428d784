"""Several processes (one per host) as one run: starting them, agreeing on a
stop, and noticing a lost one.

* `initialize` calls `jax.distributed.initialize` with the given coordinator
  address, process count and id (or auto-detection when none is given), with
  gloo collectives for CPU devices and without jax's own preemption notifier:
  the trainer notes SIGTERM/SIGINT itself, and `agreed_signal` tells every
  process, after the same step, whether any of them was signalled.
* `PeerWatchdog` is a heartbeat file per process in the shared workdir. A
  process whose heartbeat stops (killed, its host gone) or that ended with an
  error is named in one line by every survivor, which then exits at once
  (within `timeout` seconds), instead of waiting in a collective until jax's
  coordination service aborts it with a stack dump. A process that ends
  early for any reason (Ctrl-C, an error, outside training too) `leave`s: it
  writes why, and the others stop with one line naming it and the reason.
  Process 0 runs jax's coordination service, whose end aborts the others:
  it always leaves last. Before it ends, the `before_exit` hooks run
  (bounded): the digest of a checkpoint committed just before is written.

The start (a bounded wait for every process, and their agreement on what
they run) is `startup.py`.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable

import jax
import numpy as np

from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import one_line
from slotformer_jax.errors import shown

# Exit statuses that end a process as planned (done, SIGINT, SIGTERM).
CLEAN_EXITS = (0, 128 + 2, 128 + 15)
LOST_PROCESS_EXIT = 1

# What the watchdog's exit (`os._exit`, no atexit) runs first, each hook
# given the seconds left of `EXIT_GRACE_SECONDS` in all: the digest of a
# checkpoint orbax has committed (checkpoint.py registers it while one is
# in flight). A registry, not an import: checkpoint.py imports this module.
EXIT_GRACE_SECONDS = 5.0
_before_exit: list[Callable[[float], None]] = []


def before_exit(hook: Callable[[float], None]) -> None:
  """Runs `hook(seconds_left)` before the watchdog ends the process."""
  _before_exit.append(hook)


def not_before_exit(hook: Callable[[float], None]) -> None:
  """Undoes `before_exit(hook)` (nothing if it was not registered)."""
  try:
    _before_exit.remove(hook)
  except ValueError:
    pass


def _run_before_exit(seconds: float) -> None:
  """Every registered hook, within `seconds` in all; errors ignored (the
  process is ending for another reason, already said)."""
  deadline = time.monotonic() + seconds
  for hook in list(_before_exit):
    left = deadline - time.monotonic()
    if left <= 0:
      return
    try:
      hook(left)
    except Exception:  # pylint: disable=broad-except
      pass


def check_flags(coordinator_address: str | None, num_processes: int | None,
                process_id: int | None) -> bool:
  """Whether explicit flags were given (all three, consistent).

  Raises:
    ConfigError: a partial set, or an id outside [0, num_processes).
  """
  given = {'--coordinator_address': coordinator_address,
           '--num_processes': num_processes, '--process_id': process_id}
  missing = [name for name, value in given.items() if value is None]
  if len(missing) == len(given):
    return False
  if missing:
    raise ConfigError(
        '--coordinator_address, --num_processes and --process_id go '
        f'together; missing {", ".join(missing)} (or give none of them to '
        'let jax.distributed detect the cluster)')
  if ':' not in coordinator_address:
    raise ConfigError(f'--coordinator_address={coordinator_address} needs a '
                    'port: HOST:PORT, e.g. 10.0.0.1:1234')
  if num_processes < 1 or not 0 <= process_id < num_processes:
    raise ConfigError(f'--process_id={process_id} must be in [0, '
                    f'--num_processes={num_processes})')
  return True


def initialize(coordinator_address: str | None = None,
               num_processes: int | None = None,
               process_id: int | None = None, *,
               heartbeat_timeout: int = 100,
               initialization_timeout: int = 300) -> None:
  """jax.distributed.initialize; before any jax backend is started.
  `initialization_timeout` must come after `Startup`'s: jax aborts with a
  stack dump when it runs out."""
  # Collectives between the CPU devices of several processes (a no-op for
  # GPU/TPU devices); jax 0.10 has none on CPU unless one is chosen.
  jax.config.update('jax_cpu_collectives_implementation', 'gloo')
  # Its SIGTERM handler would swallow the signal outside training; the
  # trainer agrees on a stop itself (`agreed_signal`).
  jax.config.update('jax_enable_preemption_service', False)
  jax.distributed.initialize(
      coordinator_address=coordinator_address, num_processes=num_processes,
      process_id=process_id, heartbeat_timeout_seconds=heartbeat_timeout,
      initialization_timeout=initialization_timeout)


def agreed_signal(local_signal: int) -> tuple[int, list[int]]:
  """(signal to stop on, indices of the signalled processes), the same on
  every process; every process must call it after the same step. 0: none."""
  # Imported here: multihost_utils is only needed with several processes.
  from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
  signals = np.asarray(multihost_utils.process_allgather(
      np.int32(local_signal))).reshape(-1)
  signalled = [int(i) for i in np.flatnonzero(signals)]
  return int(signals.max()), signalled


def gathered(values: list[int]) -> np.ndarray:
  """Every process's `values` as int64 [process_count, len(values)], the
  same on every process (a collective: each calls it with as many values,
  at the same point)."""
  from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
  rows = multihost_utils.process_allgather(np.asarray(values, np.int64))
  return np.asarray(rows).reshape(jax.process_count(), len(values))


class PeerWatchdog:
  """Heartbeats of every process under `directory` (shared by all).

  Each process rewrites `<directory>/<index>` every `interval` seconds with a
  counter, and ends it with `exit <status>`. A thread reads the others: a
  counter unchanged for `timeout` seconds (by this host's clock: no clock
  skew between hosts matters) or an unclean exit status makes this process
  print one line naming that process and exit with status 1 at once. A
  peer that has written no heartbeat yet (slower to start: imports, config
  loading on a loaded host) is given `startup_timeout` (default
  max(60 s, 2 x timeout): under the 3 x timeout, at least 100 s, of
  jax's own heartbeat) before it counts as lost.
  """

  def __init__(self, directory: str, process_id: int, num_processes: int, *,
               timeout: float, interval: float = 1.0,
               startup_timeout: float | None = None):
    self.directory = directory
    self.process_id = process_id
    self.num_processes = num_processes
    self.timeout = timeout
    self.startup_timeout = (max(60.0, 2 * timeout) if startup_timeout is None
                            else max(startup_timeout, timeout))
    self.interval = min(interval, timeout / 4)
    self._beats = 0
    self._stop = threading.Event()
    self._verdict = threading.Event()  # a peer is lost: this process ends
    self._thread = threading.Thread(target=self._watch, daemon=True,
                                    name='peer-watchdog')

  def _path(self, index: int) -> str:
    return os.path.join(self.directory, str(index))

  def _write(self, text: str) -> None:
    path = self._path(self.process_id)
    temporary = f'{path}.{os.getpid()}.tmp'
    with open(temporary, 'w') as f:
      f.write(text)
    os.replace(temporary, path)

  def _read(self, index: int) -> str:
    try:
      with open(self._path(index)) as f:
        return f.read()
    except OSError:
      return ''

  def start(self) -> PeerWatchdog:
    os.makedirs(self.directory, exist_ok=True)
    self._write(f'{os.getpid()} 0')
    self._thread.start()
    return self

  def finish(self, status: int) -> None:
    """Stops beating and tells the others how this process ended."""
    self._stop.set()
    try:
      self._write(f'exit {status}')
    except OSError:
      pass

  def _watch(self) -> None:
    peers = [i for i in range(self.num_processes) if i != self.process_id]
    last_text = {i: self._read(i) for i in peers}
    last_change = {i: time.monotonic() for i in peers}
    while not self._stop.wait(self.interval):
      self._beats += 1
      try:
        self._write(f'{os.getpid()} {self._beats}')
      except OSError:
        pass  # a full disk is the trainer's to report
      now = time.monotonic()
      for i in peers:
        text = self._read(i)
        if text.startswith('left ') and not self._stop.is_set():
          _, status, reason = (text.split(' ', 2) + ['', ''])[:3]
          self._lost(f'process {i} of {self.num_processes} stopped '
                     f'(exit status {shown(status, 8)}: '
                     f'{shown(reason, 300) or "no reason given"})')
        if text.startswith('exit '):
          status = int(text.split()[1])
          if status in CLEAN_EXITS:
            continue
          self._lost(f'process {i} of {self.num_processes} ended with exit '
                     f'status {status} (its log says why)')
        if text != last_text[i]:
          last_text[i], last_change[i] = text, now
        elif not text and now - last_change[i] > self.startup_timeout:
          self._lost(f'process {i} of {self.num_processes} never started '
                     f'(no heartbeat within {self.startup_timeout:g} s)')
        elif text and now - last_change[i] > self.timeout:
          self._lost(f'process {i} of {self.num_processes} is lost (no '
                     f'heartbeat for {self.timeout:g} s: killed, or its host '
                     'is down)')

  def _lost(self, what: str) -> None:
    if self._stop.is_set():
      return
    self._verdict.set()
    print(f'error: {what}; stopping process {self.process_id} too. Re-run '
          'every process with the same command: training resumes from the '
          'last saved checkpoint.', file=sys.stderr, flush=True)
    self.finish(LOST_PROCESS_EXIT)
    self._exit(LOST_PROCESS_EXIT)

  def _exit(self, status: int) -> None:
    """Ends this process now. Not sys.exit: the main thread may be blocked
    in a collective with a lost process, and jax's exit handlers would wait
    for it (then abort). Process 0 first waits (up to `timeout`) for the
    others to end: it holds jax's coordination service, and its end aborts
    every process still connected, with a stack dump. Before either, the
    `before_exit` hooks (up to `EXIT_GRACE_SECONDS`): a checkpoint committed
    just before a peer died keeps its digest, so the rerun can resume from
    it."""
    _run_before_exit(EXIT_GRACE_SECONDS)
    if self.process_id == 0:
      self._wait_for_peers_to_end()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)  # pylint: disable=protected-access

  def _wait_for_peers_to_end(self) -> None:
    peers = [i for i in range(self.num_processes) if i != self.process_id]
    deadline = time.monotonic() + self.timeout
    seen = {i: (self._read(i), time.monotonic()) for i in peers}
    while peers and time.monotonic() < deadline:
      time.sleep(0.1)
      now = time.monotonic()
      for i in list(peers):
        text = self._read(i)
        if text.startswith(('exit ', 'left ')):
          peers.remove(i)
        elif text != seen[i][0]:
          seen[i] = (text, now)
        elif now - seen[i][1] > 3 * self.interval + 1:
          peers.remove(i)  # silent: gone without a word (or never came)
    time.sleep(0.3)  # a process that wrote its record is ending

  def leave(self, status: int, reason: str) -> None:
    """Ends this process early (an error, Ctrl-C, a stage outside training)
    and tells the others why: they stop with one line naming this process
    and the reason. Never returns."""
    self._stop.set()
    try:
      self._write(f'left {status} {one_line(reason, 300)}')
    except OSError:
      pass  # a full disk: the others see the heartbeat stop instead
    self._exit(status)

  def stop_watching(self) -> None:
    """Stops naming other processes (this one is about to leave itself, for
    a reason they share)."""
    self._stop.set()

  def wait_for_verdict(self) -> None:
    """Blocks up to the timeout: the watchdog ends the process if a peer is
    lost (an error in a collective usually means one is)."""
    if self._thread.is_alive():
      self._thread.join(self.timeout + 4 * self.interval)
      if self._verdict.is_set():
        # It is ending the process; process 0 first waits for the others
        # (up to `timeout`), so the verdict alone is not the end: returning
        # now would print the collective's traceback after the one line.
        self._thread.join(self.timeout + 4 * self.interval + 2)

