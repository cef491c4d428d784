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
import pathlib
import secrets
import stat
from typing import Any, BinaryIO, Iterator

import numpy as np

from slotformer_jax.errors import UserError
from slotformer_jax.errors import shown


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


class OutsideFolderError(UserError, ValueError):
  """A name from a file would lead out of the folder it must stay in."""


def confined(folder: str | os.PathLike[str], name: str, *, what: str,
             nested: bool = False) -> pathlib.Path:
  """`folder / name` for a `name` read from a file (a dataset's own name, a
  video id, a listed path), refused unless it stays inside `folder`.

  `name` must be one plain path component (`nested=True`: several, joined
  by '/'): not empty, not '.' or '..', not absolute, with no backslash, NUL
  or character a terminal acts on (`errors.shown`). Symbolic links the user
  made inside `folder` are followed as they are: what is refused is a name
  that leads out by itself.

  Raises:
    OutsideFolderError: naming `what` and the name, escaped.
  """
  text = name if isinstance(name, str) else None
  parts = [] if text is None else text.split('/')
  why = None
  if text is None:
    why = f'is a {type(name).__name__}, not a text'
  elif not text:
    why = 'is empty'
  elif '..' in parts:
    why = 'leads out of the folder'
  elif text.startswith('/'):
    why = 'is an absolute path'
  elif not nested and len(parts) > 1:
    why = 'holds a "/"'
  elif any(part in ('', '.') for part in parts):
    why = 'has an empty or "." part'
  elif '\\' in text or shown(text, len(text)) != text:
    why = 'holds a backslash, NUL or control character'
  if why is not None:
    quoted = shown(repr(name) if text is None else text, 120)
    raise OutsideFolderError(
        f"{what} '{quoted}' {why}; a name read from a file must stay inside "
        f'{folder}')
  return pathlib.Path(folder).joinpath(*parts)


class UntrustedFileError(UserError, ValueError):
  """A file from elsewhere (a download, a shared run folder) that is not
  what it should be: the message names the file and what is wrong."""


def int_in_range(value: Any, low: int, high: int, *, what: str) -> Any:
  """An integer read from a file (JSON, a record, a pickle), checked before
  anything casts it: a Python or NumPy int (not a bool; not a float, even
  3.0), or an integer NumPy array (every element), with low <= value <=
  high. Returns a Python int (an array: the array, unchanged), so that a
  later cast to int32 (or uint16, ...) can no longer wrap 2**32 + 5 to 5.

  Raises:
    UntrustedFileError: one line naming `what` (the file and the field).
  """
  if isinstance(value, np.ndarray):
    if value.dtype.kind not in 'iu':
      raise UntrustedFileError(f'{what} holds {value.dtype} values, not '
                               'integers')
    if value.size and not (low <= int(value.min())
                           and int(value.max()) <= high):
      bad = int(value.min()) if int(value.min()) < low else int(value.max())
      raise UntrustedFileError(f'{what} holds {bad}, outside [{low}, '
                               f'{high}]')
    return value
  if isinstance(value, (bool, np.bool_)) or not isinstance(
      value, (int, np.integer)):
    raise UntrustedFileError(f'{what} is {shown(repr(value), 40)}, not an '
                             'integer')
  value = int(value)
  if not low <= value <= high:
    shown_value = (str(value) if value.bit_length() <= 128
                   else f'a {value.bit_length()}-bit integer')
    raise UntrustedFileError(f'{what} is {shown_value}, outside [{low}, '
                             f'{high}]')
  return value


def _kind(mode: int) -> str:
  """What a non-regular file is, in a word or two."""
  for test, name in ((stat.S_ISDIR, 'a folder'), (stat.S_ISFIFO, 'a FIFO'),
                     (stat.S_ISCHR, 'a character device'),
                     (stat.S_ISBLK, 'a block device'),
                     (stat.S_ISSOCK, 'a socket'), (stat.S_ISLNK, 'a link')):
    if test(mode):
      return name
  return 'not a regular file'


def open_regular(path: str | os.PathLike[str], *, what: str,
                 follow_links: bool = True) -> BinaryIO:
  """`open(path, 'rb')` of a file from outside that must be a regular file:
  a FIFO (whose open and read block until a writer comes), a device
  (/dev/zero never ends) or a socket is refused without waiting, and with
  `follow_links=False` a symbolic link is too.

  Raises:
    UntrustedFileError: one line naming `what`, the file and its kind; a
      missing file stays FileNotFoundError.
  """
  path = os.fspath(path)
  flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, 'O_CLOEXEC', 0)
  if not follow_links:
    flags |= os.O_NOFOLLOW
  try:
    fd = os.open(path, flags)
  except OSError as error:
    if not follow_links and os.path.islink(path):
      raise UntrustedFileError(f'{what} {shown(path)} is a link, not a '
                               'regular file') from None
    raise error
  mode = os.fstat(fd).st_mode
  if not stat.S_ISREG(mode):
    os.close(fd)
    raise UntrustedFileError(f'{what} {shown(path)} is {_kind(mode)}, not a '
                             'regular file')
  return os.fdopen(fd, 'rb')


def depth_of(value: Any) -> int:
  """Nesting of lists and dicts in `value` (a scalar: 0), without
  recursion (the value may come from a hostile file)."""
  deepest, stack = 0, [(value, 1)]
  while stack:
    node, depth = stack.pop()
    if isinstance(node, dict):
      children = node.values()
    elif isinstance(node, list):
      children = node
    else:
      continue
    deepest = max(deepest, depth)
    stack.extend((child, depth + 1) for child in children)
  return deepest


def read_untrusted_text(path: str | os.PathLike[str], *, what: str,
                        max_bytes: int) -> str:
  """The UTF-8 text of a regular file of at most `max_bytes`, read in one
  allocation of the file's size (not the limit).

  Raises:
    UntrustedFileError: larger, not UTF-8, not a regular file.
  """
  path = os.fspath(path)
  with open_regular(path, what=what) as f:
    size = os.fstat(f.fileno()).st_size
    if size > max_bytes:
      raise UntrustedFileError(f'{what} {path} holds {size} bytes, more '
                               f'than the {max_bytes} such a file may have')
    data = f.read(size + 1)
  if len(data) > max_bytes:
    raise UntrustedFileError(f'{what} {path} grew beyond {max_bytes} bytes '
                             'while it was read')
  try:
    return data.decode('utf-8')
  except UnicodeDecodeError as error:
    raise UntrustedFileError(
        f'{what} {path} is not UTF-8 text (byte {error.start})') from None


def read_untrusted_json(path: str | os.PathLike[str], *, what: str,
                        max_bytes: int = 64 << 20, max_depth: int = 32
                        ) -> Any:
  """A JSON file from outside, read with limits: at most `max_bytes` (the
  parse is linear in it, so this bounds the time too), strict UTF-8, at most
  `max_depth` levels of lists and dicts; a regular file only
  (`open_regular`: a FIFO or a device is refused, never waited on). The
  caller still checks every field's type.

  Raises:
    UntrustedFileError: one line naming the file (`what` says which) and
      the problem; a missing file stays FileNotFoundError.
  """
  path = os.fspath(path)
  text = read_untrusted_text(path, what=what, max_bytes=max_bytes)
  try:
    value = json.loads(text)
  except json.JSONDecodeError as error:
    raise UntrustedFileError(f'{what} {path} is not valid JSON (line '
                             f'{error.lineno}, column {error.colno}: '
                             f'{error.msg})') from None
  except (RecursionError, ValueError) as error:
    # Deeper than the parser goes; or an int of more digits than Python
    # converts.
    what_wrong = ('nested too deeply' if isinstance(error, RecursionError)
                  else shown(str(error), 120))
    raise UntrustedFileError(f'{what} {path} cannot be read: '
                             f'{what_wrong}') from None
  if depth_of(value) > max_depth:
    raise UntrustedFileError(f'{what} {path} nests lists and objects deeper '
                             f'than {max_depth} levels')
  return value
