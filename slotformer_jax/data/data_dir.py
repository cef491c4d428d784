"""Where datasets and caches live on disk (no other project imports, so
both the readers and the offline writers can use it)."""

from __future__ import annotations

import os
from pathlib import Path

DATA_DIR_ENV = 'SLOTFORMER_DATA_DIR'


def default_data_dir() -> Path:
  """``$SLOTFORMER_DATA_DIR`` if set, else ``~/.cache/slotformer_jax``."""
  env = os.environ.get(DATA_DIR_ENV)
  if env:
    return Path(env).expanduser()
  return Path('~/.cache/slotformer_jax').expanduser()


def resolve_data_dir(data_dir: str | os.PathLike[str] | None) -> Path:
  """``data_dir`` as a Path, or the default when it is None / empty."""
  if data_dir is None or not os.fspath(data_dir):
    return default_data_dir()
  return Path(data_dir).expanduser()
