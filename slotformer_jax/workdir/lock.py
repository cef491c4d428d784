"""An exclusive lock file holding its owner's pid, host and start time.

Used for a workdir (one writing run at a time) and for a dataset being
generated. A lock left by a dead process on this host is taken over (with a
warning); a live holder, or one on another host, is an error naming it.

A waiting lock (a dataset being generated, which the others wait for) is
also a heartbeat: its holder touches the file every `REFRESH_EVERY`
seconds. A holder on another host cannot be asked whether it lives, so a
lock untouched for `STALE_AFTER` seconds is one that run left behind: the
waiter stops with one line naming the file, its owner and how to clear it,
instead of waiting forever.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import threading
import time
from typing import Any

from slotformer_jax.errors import UserError
from slotformer_jax.workdir.paths import Paths

logger = logging.getLogger(__name__)

# Seconds between a waiting lock's heartbeats, and without one after which
# a holder on another host counts as gone.
REFRESH_EVERY = 10.0
STALE_AFTER = 120.0


def pid_alive(pid: int) -> bool:
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:
    return True
  return True


class FileLock:
  """`with FileLock(path, what=folder):` one holder at a time.

  Attributes:
    took_over: whether acquiring replaced a stale lock (a dead holder's work
      may be left half done).
  """

  def __init__(self, path: str, *, what: str, wait: bool = False,
               fix: str = 'use a folder you can write'):
    self.path = path
    self.what = what
    self.fix = fix  # what to do when the folder cannot be written
    self.wait = wait  # True: wait for a live holder instead of failing
    self.took_over = False
    self._held = False
    self._beating: threading.Event | None = None
    self._seen: tuple[float, float] | None = None  # lock mtime, when seen

  def acquire(self) -> None:
    try:
      self._acquire()
    except (FileExistsError, UserError):
      raise
    except OSError as error:
      # Read-only filesystem, no permission, a file where a folder should
      # be: the first write of a run, so this is where it shows.
      where = error.filename or self.path
      where = '' if os.fspath(where) in self.what else f' at {where}'
      raise UserError(f'cannot write {self.what} ({error.strerror or error}'
                      f'{where}); {self.fix}') from None

  def _acquire(self) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
    me = {'pid': os.getpid(), 'host': socket.gethostname(),
          'started': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}
    attempts = 0
    while True:
      attempts += 1
      if attempts > 5 and not self.wait:
        break
      try:
        # 0666 & ~umask, like every file of a run (files.py): a colleague
        # sharing the workdir can read who holds it.
        fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
      except FileExistsError:
        holder = self._holder()
        if holder is None:  # being written right now: look again
          time.sleep(0.5)
          holder = self._holder()
        stale = holder is None or (
            holder.get('host') == me['host']
            and not pid_alive(int(holder.get('pid', -1))))
        if not stale and self.wait:
          if attempts == 1:
            logger.info('waiting for process %s on %s to finish %s',
                        holder.get('pid'), holder.get('host'), self.what)
          if holder.get('host') != me['host']:
            self._check_heartbeat(holder)
          time.sleep(min(2.0, STALE_AFTER / 4))
          continue
        if not stale:
          raise UserError(
            f'{self.what} is in use by process {holder.get("pid")} on '
            f'{holder.get("host")} (since {holder.get("started")}). Wait for '
            'it, stop it, or use another folder; if that process is gone, '
            f'delete {self.path}.')
        logger.warning('taking over the stale lock %s (holder %s is gone)',
                       self.path, holder or 'unknown')
        with contextlib.suppress(FileNotFoundError):
          os.unlink(self.path)
        self.took_over = True
        continue
      with os.fdopen(fd, 'w') as f:
        json.dump(me, f)
        f.flush()
        os.fsync(f.fileno())
      self._held = True
      if self.wait:  # others wait for this one: keep telling them it lives
        self._beating = threading.Event()
        threading.Thread(target=self._beat, args=(self._beating,),
                         daemon=True, name='lock-heartbeat').start()
      return
    raise UserError(f'could not take the lock {self.path}; delete it if no '
                    'process uses it')

  def _holder(self) -> dict[str, Any] | None:
    try:
      with open(self.path) as f:
        return json.load(f)
    except (OSError, ValueError):
      return None

  def _beat(self, stop: threading.Event) -> None:
    while not stop.wait(REFRESH_EVERY):
      with contextlib.suppress(OSError):
        os.utime(self.path)

  def _check_heartbeat(self, holder: dict[str, Any]) -> None:
    """Raises when a holder on another host stopped touching the lock: its
    mtime unchanged for STALE_AFTER seconds of this host's clock (hosts'
    clocks may differ; only changes are compared)."""
    try:
      mtime = os.path.getmtime(self.path)
    except OSError:
      return  # released meanwhile
    now = time.monotonic()
    if self._seen is None or self._seen[0] != mtime:
      self._seen = (mtime, now)
    age = now - self._seen[1]
    if age > STALE_AFTER:
      raise UserError(
          f'{self.what} is locked by process {holder.get("pid")} on '
          f'{holder.get("host")} (since {holder.get("started")}), whose lock '
          f'file {self.path} has not been touched for {age:.0f} s (a live '
          f'holder touches it every {REFRESH_EVERY:g} s): that run ended '
          f'without releasing it. If nothing on {holder.get("host")} still '
          f'makes {self.what}, delete {self.path} and re-run.')

  def release(self) -> None:
    if self._beating is not None:
      self._beating.set()
      self._beating = None
    if self._held:
      with contextlib.suppress(FileNotFoundError):
        os.unlink(self.path)
      self._held = False

  def __enter__(self) -> FileLock:
    self.acquire()
    return self

  def __exit__(self, *exc) -> None:
    self.release()


def workdir_lock(paths: Paths) -> FileLock:
  """The lock of a run's workdir: one writing run at a time."""
  return FileLock(paths.lock, what=f'the workdir {paths.root}',
                  fix='give a --workdir you can write')
