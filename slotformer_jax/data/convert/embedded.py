"""One TFDS ``array_record`` writer for the embedded task families.

The contact (OCP) and PHYRE-like families are generated on first use into
``<data_dir>/<name>/<slug>/1.0.0`` (the slug encodes every generation
parameter, so a changed recipe never reuses a stale cache) and read back with
:class:`slotformer_jax.data.sources.TfdsVideoSource`, like the OBJ3D-like
dataset. Record ``i`` of a split is example ``i`` (no shuffling).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data.convert import synthetic
from slotformer_jax.data.convert.pool import ordered_map

VERSION = '1.0.0'


def tensor(shape: tuple[int, ...], dtype: Any) -> tfds.features.Tensor:
  """A raw-bytes tensor feature (see SyntheticObj3d.TENSOR_ENCODING)."""
  return tfds.features.Tensor(shape=shape, dtype=dtype,
                              encoding=synthetic.SyntheticObj3d.TENSOR_ENCODING)


@dataclasses.dataclass(frozen=True)
class Family:
  """What to write: ``make(split, index)`` -> one example of ``features``."""

  name: str
  slug: str
  description: str
  features: Mapping[str, tfds.features.FeatureConnector]
  split_sizes: Mapping[str, int]
  make: Callable[[str, int], dict[str, np.ndarray]]


@dataclasses.dataclass(eq=False)
class _BuilderConfig(tfds.core.BuilderConfig):
  family: Family | None = None


class _EmbeddedBuilder(tfds.core.GeneratorBasedBuilder,
                       skip_registration=True):
  VERSION = tfds.core.Version(VERSION)
  RELEASE_NOTES = {'1.0.0': 'Initial release.'}

  def __init__(self, *, family: Family, num_workers: int | None = None,
               **kwargs: Any):
    self.name = family.name
    self._num_workers = num_workers
    super().__init__(config=_BuilderConfig(name=family.slug, family=family,
                                           description=family.description),
                     file_format='array_record', **kwargs)

  @tfds.core.utils.classproperty
  @classmethod
  def code_path(cls) -> None:
    return None  # nothing to download; see SyntheticObj3d.code_path

  def _info(self) -> tfds.core.DatasetInfo:
    family = self.builder_config.family
    return self.dataset_info_from_configs(
        description=family.description,
        features=tfds.features.FeaturesDict(dict(family.features)),
        disable_shuffling=True)

  def _split_generators(self, dl_manager: Any) -> dict[str, Iterator[Any]]:
    del dl_manager
    family = self.builder_config.family
    return {split: self._generate_examples(split)
            for split, size in family.split_sizes.items() if size > 0}

  def _generate_examples(self, split: str
                         ) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    family = self.builder_config.family
    # Index order whatever the worker count: every example depends on its
    # (split, index) alone (the families seed per video).
    yield from enumerate(ordered_map(functools.partial(family.make, split),
                                     family.split_sizes[split],
                                     self._num_workers))


def dataset_dir(family: Family, data_dir: str | os.PathLike[str]) -> Path:
  return Path(data_dir) / family.name / family.slug / VERSION


def build(family: Family, data_dir: str | os.PathLike[str], *,
          num_workers: int | None = None) -> Path:
  """Writes ``family`` under ``data_dir`` unless it is there; its folder.

  ``num_workers`` generator processes (default: the available cores; 1
  generates in this process); ``family.make`` must then be picklable.
  """
  path = dataset_dir(family, data_dir)
  if (path / 'dataset_info.json').is_file():
    return path
  builder = _EmbeddedBuilder(family=family, num_workers=num_workers,
                             data_dir=os.fspath(data_dir))
  builder.download_and_prepare(
      download_config=tfds.download.DownloadConfig(try_download_gcs=False))
  if Path(builder.data_dir) != path:
    raise RuntimeError(f'tfds wrote to {builder.data_dir}, expected {path}')
  return path
