"""Atomic small files: a reader sees the old file or the new one, never a
torn or empty one (disk full, kill -9, power loss).

Every JSON / CSV / index the project writes goes through `write_atomic`:
the bytes go to a temporary file in the same folder, are fsynced, and the
temporary file is renamed over the target (rename is atomic on POSIX).

Files get the usual permissions, 0666 & ~umask (0644 under umask 022, 0664
under 002), as `open(path, 'w')` would give, so a colleague or a server
running as another user can read a run's results on a shared filesystem;
`tempfile.mkstemp` would leave them 0600. Folders are made by
`os.makedirs` (0777 & ~umask).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import secrets
from typing import Any, Iterator

from slotformer_jax.errors import UserError


def write_atomic(path: str | os.PathLike[str], data: bytes | str) -> None:
  """Replaces `path` with `data` atomically (creating its folder)."""
  path = os.fspath(path)
  directory = os.path.dirname(os.path.abspath(path))
  os.makedirs(directory, exist_ok=True)
  if isinstance(data, str):
    data = data.encode('utf-8')
  fd, tmp = _create_temporary(directory, f'.{os.path.basename(path)}.tmp.')
  try:
    with os.fdopen(fd, 'wb') as f:
      f.write(data)
      f.flush()
      os.fsync(f.fileno())
    os.replace(tmp, path)
  except BaseException:
    with contextlib.suppress(OSError):
      os.unlink(tmp)
    raise
  _fsync_dir(directory)


# Mode of the temporary file before the umask (and any default ACL of the
# folder) applies: what `open(path, 'w')` asks for.
_FILE_MODE = 0o666


def _create_temporary(directory: str, prefix: str) -> tuple[int, str]:
  """(fd, path) of a new, empty file in `directory`, as `tempfile.mkstemp`
  (O_EXCL under a random name) but created with mode 0666 so the kernel
  applies the process umask: the renamed file ends up 0666 & ~umask. Its
  name starts with '.', so folder listings of results skip it."""
  flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, 'O_CLOEXEC', 0)
  for _ in range(100):
    path = os.path.join(directory, prefix + secrets.token_hex(6))
    try:
      return os.open(path, flags, _FILE_MODE), path
    except FileExistsError:
      continue
  raise FileExistsError(f'no free temporary name for {prefix}* in '
                        f'{directory}')


def _fsync_dir(directory: str) -> None:
  """Makes the rename itself durable (best effort: not every FS allows it)."""
  with contextlib.suppress(OSError):
    fd = os.open(directory, os.O_RDONLY)
    try:
      os.fsync(fd)
    finally:
      os.close(fd)


def write_json_atomic(path: str | os.PathLike[str], payload: Any,
                      **kwargs) -> None:
  kwargs.setdefault('indent', 1)
  kwargs.setdefault('sort_keys', True)
  write_atomic(path, json.dumps(payload, **kwargs) + '\n')


def append_line_atomic(path: str | os.PathLike[str], line: str) -> None:
  """Appends one line by rewriting the file atomically (for small logs:
  a torn last line can never appear)."""
  path = os.fspath(path)
  old = b''
  if os.path.exists(path):
    with open(path, 'rb') as f:
      old = f.read()
    # A file left by an older, non-atomic writer may end in a torn line.
    if old and not old.endswith(b'\n'):
      old = old[:old.rfind(b'\n') + 1]
  write_atomic(path, old + line.rstrip('\n').encode('utf-8') + b'\n')


@contextlib.contextmanager
def atomic_text(path: str | os.PathLike[str], newline: str | None = None
                ) -> Iterator[io.StringIO]:
  """`with atomic_text(p) as f: csv.writer(f)...`: written on success only."""
  buffer = io.StringIO(newline=newline)
  yield buffer
  write_atomic(path, buffer.getvalue())


def read_json(path: str | os.PathLike[str], *, fix: str | None = None) -> Any:
  """json.load that names the file (and the fix) when it is empty or torn."""
  path = os.fspath(path)
  with open(path, 'rb') as f:
    data = f.read()
  try:
    return json.loads(data)
  except (json.JSONDecodeError, UnicodeDecodeError) as error:
    what = 'empty' if not data.strip() else f'not valid JSON ({error})'
    raise UserError(
        f'{path} is {what}: it was torn by an interrupted write (disk full, '
        f'crash) of an older version. {fix or "Delete it and re-run the same command; the step that writes it runs again."}'
    ) from None
