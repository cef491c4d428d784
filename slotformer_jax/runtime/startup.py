"""The start of a run of several processes: every process comes within a
bounded time, and all agree on what they run before any work.

* `Startup` bounds `jax.distributed.initialize`: a process that does not
  come within `--startup_timeout` seconds is named (from the heartbeat
  folder of `processes.PeerWatchdog`) before jax's own initialisation
  timeout aborts with a stack dump.
* `agree`: every process publishes what it was started with (the resolved
  config, the mode, the code, the workdir it sees) through jax's key-value
  store, and a difference is one line on every process.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import secrets
import socket
import sys
import threading
import time
from typing import Any

import jax

from slotformer_jax.errors import UserError
from slotformer_jax.errors import shown
from slotformer_jax.runtime.processes import LOST_PROCESS_EXIT
from slotformer_jax.runtime.processes import PeerWatchdog

class Startup:
  """Bounds `initialize`: if it has not returned `timeout` seconds after
  `begin`, one line names the processes that gave no sign of life in the
  heartbeat folder (each writes `starting <pid> <host> <time>` there before
  it connects), and this process exits with status 1. jax's own
  initialisation timeout, set after this one, would abort with a stack
  dump. `process_id` / `num_processes` are None when jax detects the
  cluster: then the line cannot name the missing ones.
  """

  def __init__(self, directory: str, process_id: int | None,
               num_processes: int | None, *, timeout: float,
               coordinator: str | None):
    self.directory = directory
    self.process_id = process_id
    self.num_processes = num_processes
    self.timeout = timeout
    self.coordinator = coordinator
    self.started = time.time()
    self.deadline = time.monotonic() + timeout
    self._done = threading.Event()

  def begin(self) -> Startup:
    """Writes this process's starting record and starts the timer.

    Raises:
      UserError: the heartbeat folder cannot be written.
    """
    if self.process_id is not None:
      record = (f'starting {os.getpid()} {socket.gethostname()} '
                f'{self.started:.3f}')
      try:
        os.makedirs(self.directory, exist_ok=True)
        temporary = os.path.join(self.directory,
                                 f'{self.process_id}.{os.getpid()}.tmp')
        with open(temporary, 'w') as f:
          f.write(record)
        os.replace(temporary, os.path.join(self.directory,
                                           str(self.process_id)))
      except OSError as error:
        raise UserError(f'cannot write the workdir\'s heartbeat folder '
                        f'{self.directory} ({error.strerror or error}); give '
                        'a --workdir that every process can write') from None
    threading.Thread(target=self._watch, daemon=True,
                     name='startup-timer').start()
    return self

  def end(self) -> None:
    self._done.set()

  def remaining(self) -> float:
    return max(self.deadline - time.monotonic(), 1.0)

  def _watch(self) -> None:
    if self._done.wait(self.timeout):
      return
    print(f'error: {self.missing()}; stopping process '
          f'{"?" if self.process_id is None else self.process_id} too. Start '
          'every process with the same command (only --process_id differs), '
          'or raise --startup_timeout.', file=sys.stderr, flush=True)
    os._exit(LOST_PROCESS_EXIT)  # pylint: disable=protected-access

  def missing(self) -> str:
    """What the line says: which processes gave no sign of life."""
    waited = f'within {self.timeout:g} s (--startup_timeout)'
    if self.process_id is None or self.num_processes is None:
      return (f'not every process of this run started {waited}: jax could '
              'not connect them all')
    absent = [i for i in range(self.num_processes)
              if i != self.process_id and not self._came(i)]
    if absent:
      names = ', '.join(map(str, absent))
      return (f'process{"es" if len(absent) > 1 else ""} {names} of '
              f'{self.num_processes} never started (no sign of '
              f'{"them" if len(absent) > 1 else "it"} in {self.directory} '
              f'{waited}; if it runs, its --workdir is not this folder)')
    return (f'every process wrote to {self.directory}, but they did not all '
            f'reach the coordinator at {self.coordinator} {waited}: check '
            '--coordinator_address and that its port is open to every host')

  def _came(self, index: int) -> bool:
    """Whether `index` wrote a record since this run's start (its own
    clock: other hosts' clocks may differ by as much as the timeout)."""
    try:
      with open(os.path.join(self.directory, str(index))) as f:
        text = f.read()
      stamp = float(text.split()[3]) if text.startswith('starting ') else (
          os.path.getmtime(os.path.join(self.directory, str(index))))
    except (OSError, ValueError, IndexError):
      return False
    return stamp >= self.started - self.timeout


def code_version() -> dict[str, str]:
  """What the code of this process is: a hash of this package's sources
  (the same checkout everywhere gives the same hash) and jax's version."""
  package = pathlib.Path(__file__).resolve().parent.parent
  digest = hashlib.sha256()
  for path in sorted(package.rglob('*.py')):
    digest.update(str(path.relative_to(package)).encode())
    digest.update(path.read_bytes())
  return {'slotformer_jax': digest.hexdigest()[:12], 'jax': jax.__version__}


def _flat(tree: Any, prefix: str = '') -> dict[str, Any]:
  if isinstance(tree, dict):
    out = {}
    for key, value in tree.items():
      out.update(_flat(value, f'{prefix}.{key}' if prefix else str(key)))
    return out
  return {prefix: tree}


# Fields of a run that may differ between hosts: where each reads its data
# from and how many cores it converts with.
_PER_HOST = ('config.data.data_dir', 'config.data.num_workers')
_KEY = 'slotformer_jax/agree/'
_TOKEN_FILE = 'run'


class Disagreement(UserError):
  """The processes of one run were not started alike."""


def agree(config: dict[str, Any], mode: str, workdir: str, *,
          directory: str, startup: Startup,
          watchdog: PeerWatchdog | None = None) -> None:
  """Every process publishes (resolved config, mode, code version, the
  workdir it sees) and compares them all, before any work.

  The workdir is compared by content, not by path (mount points may
  differ): process 0 writes a random token into `directory` and every other
  process must read that token there.

  Raises:
    Disagreement: one line naming every difference (the same line on every
      process); each process has read every record by then.
    UserError: a process gave no record within the startup time.
  """
  # Imported here: jax's private client exists only after initialize.
  from jax._src.distributed import global_state  # pylint: disable=g-import-not-at-top
  client = global_state.client
  index, count = jax.process_index(), jax.process_count()
  mine = {'config': json.loads(json.dumps(config, default=repr)),
          'mode': mode, 'code': code_version(), 'workdir': workdir}
  if index == 0:
    token = secrets.token_hex(8)
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, _TOKEN_FILE), 'w') as f:
      f.write(token)
    mine['folder'] = token
    client.key_value_set(f'{_KEY}0', json.dumps(mine))
    records = {0: mine}
  else:
    records = {0: _record(client, 0, count, startup)}
    mine['folder'] = _read_token(directory, records[0].get('folder'),
                                 startup)
    client.key_value_set(f'{_KEY}{index}', json.dumps(mine))
    records[index] = mine
  for other in range(count):
    if other not in records:
      records[other] = _record(client, other, count, startup)
  differences = differences_between(records)
  if differences:
    if watchdog is not None:
      watchdog.stop_watching()
    try:  # every process has its verdict before any of them leaves
      client.wait_at_barrier('slotformer_jax/disagree',
                             int(startup.remaining() * 1000))
    except Exception:  # pylint: disable=broad-except
      pass
    raise Disagreement(
        f'the {count} processes of this run were not started alike: '
        + '; '.join(differences[:6])
        + (f'; and {len(differences) - 6} more' if len(differences) > 6
           else '')
        + '. Start every process with the same command and code (only '
        '--process_id differs), on one shared --workdir.')


def _record(client: Any, index: int, count: int,
            startup: Startup) -> dict[str, Any]:
  try:
    text = client.blocking_key_value_get(f'{_KEY}{index}',
                                         int(startup.remaining() * 1000))
  except Exception:  # pylint: disable=broad-except
    raise UserError(
        f'process {index} of {count} did not say what it was started with '
        f'within {startup.timeout:g} s (--startup_timeout): it is stuck, or '
        'runs another version of this code') from None
  try:
    record = json.loads(text)
  except ValueError:
    record = None
  if not isinstance(record, dict):
    raise UserError(f'process {index} of {count} sent an unreadable record: '
                    'it runs another version of this code')
  return record


def _read_token(directory: str, token: Any, startup: Startup) -> str:
  """The token process 0 wrote into the workdir, as this process sees it
  (a shared filesystem may show a new file a few seconds late)."""
  path = os.path.join(directory, _TOKEN_FILE)
  give_up = time.monotonic() + min(10.0, startup.remaining())
  while True:
    try:
      with open(path) as f:
        seen = f.read().strip()
    except OSError:
      seen = ''
    if seen == token or time.monotonic() > give_up:
      return seen or '(none)'
    time.sleep(0.2)


def differences_between(records: dict[int, dict[str, Any]]) -> list[str]:
  """['--mode: train_savi on process 0, evaluate on process 1', ...]: every
  field in which a process differs from process 0."""
  reference = records[0]
  out = []
  for index in sorted(records):
    if index == 0:
      continue
    record = records[index]
    if record.get('folder') != reference.get('folder'):
      out.append(f'process {index} sees another folder as its --workdir '
                 f'({shown(record.get("workdir"), 120)} there, '
                 f'{shown(reference.get("workdir"), 120)} on process 0)')
    if record.get('code') != reference.get('code'):
      out.append(f'process {index} runs other code '
                 f'({shown(_code(record.get("code")), 80)} there, '
                 f'{shown(_code(reference.get("code")), 80)} on process 0)')
    if record.get('mode') != reference.get('mode'):
      out.append(f'--mode: {shown(reference.get("mode"), 40)} on process 0, '
                 f'{shown(record.get("mode"), 40)} on process {index}')
    ours = _flat({'config': reference.get('config')})
    theirs = _flat({'config': record.get('config')})
    for name in sorted(set(ours) | set(theirs)):
      if name in _PER_HOST or ours.get(name) == theirs.get(name):
        continue
      missing = '(absent)'
      out.append(f'--{shown(name, 80)}: '
                 f'{shown(ours.get(name, missing), 60)} on process 0, '
                 f'{shown(theirs.get(name, missing), 60)} on process {index}')
  return out


def _code(code: Any) -> str:
  if not isinstance(code, dict):
    return repr(code)
  return ', '.join(f'{k} {v}' for k, v in sorted(code.items()))
