"""The digest of a checkpoint step: `<step>/sha256.json`, the size and
SHA-256 of every file orbax wrote for it, and `digests.json` beside the
steps, the first step of the folder saved with a digest.

Both are read as the untrusted files they are (a shared run folder, a
disk fault, someone's hand): a regular file only (a FIFO or a device is
refused without waiting; no link), at most `MAX_DIGEST_BYTES` and three
levels deep, every number range-checked, every listed name confined to the
step and a regular file there, every file of the step listed. Anything
else is a phrase saying why the step is damaged, never an exception: the
caller sets the step aside.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import stat
from typing import Any

from slotformer_jax.errors import brief
from slotformer_jax.errors import shown
from slotformer_jax.files import confined
from slotformer_jax.files import depth_of
from slotformer_jax.files import int_in_range
from slotformer_jax.files import open_regular
from slotformer_jax.files import OutsideFolderError
from slotformer_jax.files import UntrustedFileError
from slotformer_jax.files import write_json_atomic

DIGEST_FILE = 'sha256.json'
SINCE_FILE = 'digests.json'
_DIGEST_FORMAT = 'slotformer_jax checkpoint digest'
_SINCE_FORMAT = 'slotformer_jax checkpoint digests since'
# 16 MiB: about 100,000 listed files; an OCDBT step has a few dozen.
MAX_DIGEST_BYTES = 16 << 20
_MAX_DEPTH = 3  # {'files': {name: {'bytes': ..., 'sha256': ...}}}
_MAX_FILE_BYTES = 1 << 50
_MAX_STEP = (1 << 63) - 1
_SHA256 = re.compile(r'[0-9a-f]{64}')


class _Unreadable(Exception):
  """A digest file that is not what this module writes (one phrase)."""


def _sha256(f) -> str:
  """Hex SHA-256 of an open binary file (hashlib.file_digest is 3.11+)."""
  digest = hashlib.sha256()
  while chunk := f.read(1 << 20):
    digest.update(chunk)
  return digest.hexdigest()


def write_digest(step_directory: str) -> None:
  """Records the size and SHA-256 of every file of a finished step."""
  listed = {}
  for root, folders, names in os.walk(step_directory):
    folders.sort()
    for name in sorted(names):
      path = os.path.join(root, name)
      relative = os.path.relpath(path, step_directory)
      if relative == DIGEST_FILE or not os.path.isfile(path):
        continue
      with open(path, 'rb') as f:
        listed[relative.replace(os.sep, '/')] = {
            'bytes': os.fstat(f.fileno()).st_size,
            'sha256': _sha256(f)}
  write_json_atomic(os.path.join(step_directory, DIGEST_FILE),
                    {'format': _DIGEST_FORMAT, 'version': 1, 'files': listed})


def _read_small_json(path: str, limit: int) -> Any:
  """The JSON value of a regular file of at most `limit` bytes and
  `_MAX_DEPTH` levels.

  Raises:
    _Unreadable: anything else (FileNotFoundError stays itself).
  """
  try:
    with open_regular(path, what='', follow_links=False) as f:
      size = os.fstat(f.fileno()).st_size
      if size > limit:
        raise _Unreadable(f'holds {size} bytes, more than {limit}')
      data = f.read(limit + 1)
  except UntrustedFileError as error:
    # 'a FIFO, not a regular file' (the caller names the file).
    raise _Unreadable('is ' + str(error).rsplit(' is ', 1)[-1]) from None
  except FileNotFoundError:
    raise
  except OSError as error:
    raise _Unreadable(f'cannot be read ({brief(error, 80)})') from None
  try:
    value = json.loads(data.decode('utf-8'))
  except RecursionError:
    raise _Unreadable('is nested too deeply') from None
  except (UnicodeDecodeError, ValueError):
    raise _Unreadable('is not valid JSON') from None
  if depth_of(value) > _MAX_DEPTH:
    raise _Unreadable('is nested too deeply')
  return value


def _listed(step_directory: str) -> list[tuple[str, int, str]]:
  """(name, bytes, sha256) of each file `sha256.json` lists.

  Raises:
    _Unreadable, FileNotFoundError.
  """
  digest = _read_small_json(os.path.join(step_directory, DIGEST_FILE),
                            MAX_DIGEST_BYTES)
  if not isinstance(digest, dict) or digest.get('format') != _DIGEST_FORMAT:
    raise _Unreadable('is not a checkpoint digest')
  listed = digest.get('files')
  if digest.get('version') != 1 or not isinstance(listed, dict):
    raise _Unreadable('is not a version 1 checkpoint digest')
  expected = []
  for name, entry in listed.items():
    if not isinstance(entry, dict):
      raise _Unreadable(f'lists {shown(name, 60)} without size and hash')
    try:
      size = int_in_range(entry.get('bytes'), 0, _MAX_FILE_BYTES,
                          what=f'the size of {shown(name, 60)}')
    except UntrustedFileError as error:
      raise _Unreadable(f'says {error}') from None
    sha256 = entry.get('sha256')
    if not isinstance(sha256, str) or not _SHA256.fullmatch(sha256):
      raise _Unreadable(f'gives {shown(name, 60)} no SHA-256')
    expected.append((name, size, sha256))
  return expected


def digests_since(directory: str) -> int:
  """The first step of checkpoint folder `directory` saved by code that
  writes digests: a step from then on without one is not intact. No
  `digests.json`: every step may lack one (a folder from before digests);
  a damaged one: 0 (every step must have one)."""
  try:
    since = _read_small_json(os.path.join(directory, SINCE_FILE), 4096)
    return int_in_range(since.get('since_step') if isinstance(since, dict)
                        and since.get('format') == _SINCE_FORMAT else None,
                        0, _MAX_STEP, what='since_step')
  except FileNotFoundError:
    return _MAX_STEP + 1
  except (_Unreadable, UntrustedFileError):
    return 0


def record_digests_since(directory: str, step: int) -> None:
  """Writes `digests.json` (before step `step` is saved) unless there is
  one: from `step` on, every step of the folder has a digest."""
  if not os.path.lexists(os.path.join(directory, SINCE_FILE)):
    write_json_atomic(os.path.join(directory, SINCE_FILE),
                      {'format': _SINCE_FORMAT, 'since_step': int(step)})


def _unlisted(step_directory: str, listed: set[str]) -> str | None:
  """A file of the step that its digest does not list (one its digest was
  edited to leave unchecked), or None."""
  for root, folders, names in os.walk(step_directory):
    folders.sort()
    for name in sorted(names):
      relative = os.path.relpath(os.path.join(root, name), step_directory)
      relative = relative.replace(os.sep, '/')
      if relative != DIGEST_FILE and relative not in listed:
        return relative
  return None


def damage_of(step_directory: str, *, required: bool = False) -> str | None:
  """Why a step's files are not what was saved (one phrase), or None: they
  match its sha256.json, or it has none and none is `required` (a step
  saved before digests)."""
  try:
    expected = _listed(step_directory)
  except FileNotFoundError:
    if not required:
      return None
    return (f'it has no {DIGEST_FILE}: the run stopped before recording it, '
            'so its bytes cannot be checked')
  except _Unreadable as why:
    return f'its {DIGEST_FILE} is unreadable: it {why}'
  unlisted = _unlisted(step_directory, {name for name, _, _ in expected})
  if unlisted is not None:
    return f'{shown(unlisted, 120)} is not in its {DIGEST_FILE}'
  # Sizes first: a truncated file is found without hashing the rest.
  files = []
  for name, size, sha256 in expected:
    try:
      file = confined(step_directory, name, what='a file of sha256.json',
                      nested=True)
      status = os.lstat(file)
    except OutsideFolderError:
      return (f'its {DIGEST_FILE} is unreadable: it lists '
              f'{shown(name, 60)}, outside the step')
    except OSError:
      return f'{shown(name, 120)} is missing'
    if not stat.S_ISREG(status.st_mode):
      return f'{shown(name, 120)} is not a regular file'
    if status.st_size != size:
      return (f'{shown(name, 120)} holds {status.st_size} bytes, {size} were '
              'saved')
    files.append((name, file, sha256))
  for name, file, sha256 in files:
    try:
      with open_regular(file, what='', follow_links=False) as f:
        actual = _sha256(f)
    except (OSError, UntrustedFileError) as error:
      return f'{shown(name, 120)} cannot be read ({brief(error, 80)})'
    if actual != sha256:
      return f'{shown(name, 120)} holds other bytes than were saved'
  return None
