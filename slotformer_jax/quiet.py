"""Libraries that print at import time, imported without it.

pybullet's C extension prints its build time ('pybullet build time: ...')
to the process's standard error when it is imported, and every command
imports it (the embedded datasets' generators): the first line of every
command, `--help` included, and of every conversion worker. It is imported
here with file descriptors 1 and 2 pointed at /dev/null; an import that
fails still raises (the exception is not output).
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
from collections.abc import Iterator
from types import ModuleType


@contextlib.contextmanager
def no_output() -> Iterator[None]:
  """Whatever C code or Python writes to standard output or error inside is
  dropped."""
  for stream in (sys.stdout, sys.stderr):
    if stream is not None:
      stream.flush()
  saved = []
  try:
    with open(os.devnull, 'wb') as null:
      for fd in (1, 2):
        try:
          saved.append((fd, os.dup(fd)))
        except OSError:  # not open: nothing to silence
          continue
        os.dup2(null.fileno(), fd)
    yield
  finally:
    for fd, copy in saved:
      os.dup2(copy, fd)
      os.close(copy)


def import_quietly(name: str) -> ModuleType:
  """``importlib.import_module(name)`` without its import-time output."""
  if name in sys.modules:
    return sys.modules[name]
  with no_output():
    return importlib.import_module(name)
