"""Makes a generated dataset: the data stage's one entry point
(`stages/data.py`), and a script's or test's that needs the data without a
run.

A generated dataset (``datasets/base.py:Generated``) writes only through the
:class:`Output` handed to its ``generate``: TFDS folders in the chunked
layout (``<data_dir>/<name>/<slug>/2.0.0``, the slug encoding every
generation parameter, so a changed recipe never reuses a stale cache; record
``i`` of a split is example ``i``), arrays and text files, each appearing
whole.
"""

from __future__ import annotations

import functools
import os
import shutil
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, TypeVar

import ml_collections
import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import sources
from slotformer_jax.data.write.pool import ordered_map
from slotformer_jax.data.write.records import write_folder
from slotformer_jax.datasets.base import Generated
from slotformer_jax.files import write_atomic
from slotformer_jax.workdir.lock import FileLock

T = TypeVar('T')


class Output:
  """What a generator writes with (``datasets/base.py:Output``).

  Args:
    data_dir: the root of the data.
    num_workers: generator processes (None: the available cores; 1: this
      process).
  """

  def __init__(self, data_dir: str | os.PathLike[str],
               num_workers: int | None = None):
    self.data_dir = Path(data_dir)
    self.num_workers = num_workers

  def map(self, make: Callable[[int], T], count: int) -> Iterator[T]:
    return ordered_map(make, count, self.num_workers)

  def tfds_folder(self, path: Path, *, name: str,
                  features: tfds.features.FeaturesDict, description: str,
                  split_sizes: Mapping[str, int],
                  make: Callable[[str, int], dict[str, Any]],
                  metadata: Mapping[str, Any] | None = None,
                  lock: str | None = None) -> Path:
    if sources.is_complete(path):
      return path
    if lock is None:
      return self._write_tfds(path, name, features, description, split_sizes,
                              make, metadata)
    # A generator killed earlier left its temporary folder behind, which
    # the lock holder may remove.
    with FileLock(os.fspath(path.parent / f'.{path.name}.lock'), what=lock,
                  wait=True, fix='set $SLOTFORMER_DATA_DIR or '
                  '--config.data.data_dir to a folder you can write'):
      if sources.is_complete(path):  # made while we waited
        return path
      return self._write_tfds(path, name, features, description, split_sizes,
                              make, metadata)

  def _write_tfds(self, path, name, features, description, split_sizes, make,
                  metadata) -> Path:
    # Written to a temporary sibling and renamed when complete.
    for leftover in path.parent.glob(f'incomplete.*_{path.name}'):
      shutil.rmtree(leftover, ignore_errors=True)
    sizes = {s: n for s, n in split_sizes.items() if n > 0}
    return write_folder(
        path, name=name, features=features, description=description,
        splits={s: self.map(functools.partial(make, s), n)
                for s, n in sizes.items()},
        sizes=sizes, metadata=metadata)

  def save_array(self, path: Path, array: np.ndarray) -> None:
    with _replaced(path) as f:
      np.save(f, array)

  def save_arrays(self, path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    with _replaced(path) as f:
      np.savez(f, **arrays)

  def write_text(self, path: Path, text: str) -> None:
    write_atomic(path, text)


class _replaced:
  """A binary file object on a temporary name, renamed to ``path`` when the
  block ends without an error (removed otherwise)."""

  def __init__(self, path: Path):
    self.path = Path(path)
    self.tmp = self.path.with_name(f'.{self.path.name}.tmp.{os.getpid()}')

  def __enter__(self):
    self.path.parent.mkdir(parents=True, exist_ok=True)
    self.file = open(self.tmp, 'wb')
    return self.file

  def __exit__(self, exc_type, exc, tb) -> bool:
    self.file.close()
    if exc_type is None:
      os.replace(self.tmp, self.path)
    else:
      self.tmp.unlink(missing_ok=True)
    return False


def make_dataset(dataset: Generated, data_config: ml_collections.ConfigDict) -> Path:
  """Generates the dataset ``data_config`` names unless it is there; the
  folder its reader opens. Deterministic (``data.num_workers`` does not
  matter)."""
  return dataset.generate(dataset.parameters(data_config),
                          output(data_config))


def output(data_config: ml_collections.ConfigDict) -> Output:
  """The :class:`Output` of the data ``data_config`` names."""
  return Output(sources.resolve_data_dir(data_config.data_dir),
                data_config.num_workers)


def discard_dataset(path: str | os.PathLike[str]) -> None:
  """Removes a (damaged) generated dataset folder so it is made again."""
  shutil.rmtree(path, ignore_errors=True)
