"""Chunked video records: a training clip reads only the frames it holds.

A video is a header record (its per-video fields, when it has any) followed
by records of K consecutive frames of every time-axis field
(:func:`time_fields`: ``video`` and every other tensor of rank >= 2 whose
first dimension is the video's), in TFDS version folder ``2.0.0``.
``video_chunks.json`` (``INDEX_FILE``) holds K and every video's frame count
and first record, so a reader knows a video's length without decoding it and
reads a clip from ``ceil``-many chunks; values are bit-identical to the
whole-video records (``1.0.0``). The layout, and why K = 4
(:data:`FRAMES_PER_CHUNK`) and uncompressed chunks: docs/datasets.md,
"Record layout".

This module is the layout and its index as the reader sees them (reading
never writes); ``data/write/records.py`` and ``data/write/convert.py`` write
it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.errors import UserError
from slotformer_jax.files import read_json

LAYOUT = 'chunked'
LAYOUT_VERSION = 1
# The TFDS version folder of a dataset in this layout (1.0.0: whole videos).
TFDS_VERSION = '2.0.0'
INDEX_FILE = 'video_chunks.json'  # = integrity.CHUNK_INDEX_FILE
FRAMES_PER_CHUNK = 4
# One record per group: reading a chunk reads (decompresses) it alone. The
# whole-video layout keeps array_record's default compression (as TFDS
# writes it); chunks are written uncompressed unless asked (`Layout`).
RECORD_OPTIONS = 'group_size:1'
UNCOMPRESSED_RECORD_OPTIONS = 'group_size:1,uncompressed'


def time_fields(features: tfds.features.FeaturesDict) -> tuple[str, ...]:
  """The fields with a time axis: ``video`` and every Tensor of rank >= 2
  whose first dimension is the video's."""
  frames = features['video'].shape[0]
  out = []
  for key, feature in features.items():
    shape = getattr(feature, 'shape', None)
    if key == 'video' or (
        isinstance(feature, tfds.features.Tensor) and shape is not None
        and len(shape) >= 2 and shape[0] == frames):
      out.append(key)
  return tuple(out)


def _free_time(feature: tfds.features.Tensor) -> tfds.features.Tensor:
  return tfds.features.Tensor(
      shape=(None,) + tuple(feature.shape[1:]), dtype=feature.np_dtype,
      encoding=feature._encoding)  # pylint: disable=protected-access


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
  """How one dataset's videos become records (and back).

  Attributes:
    features: the videos' features (what ``features.json`` describes).
    frames_per_chunk: K; 0 is the whole-video layout (one record per video
      with ``features``), which the writers keep for tests and benchmarks.
    compressed: the chunks are compressed (array_record's default, zstd);
      False (default) writes them uncompressed: 1.45x the disk of the
      rendered-like fixture and 2.7-2.9x the clips per core (module
      docstring). Whole-video records are always compressed. Readers need
      not know: array_record reads either.
  """

  features: tfds.features.FeaturesDict
  frames_per_chunk: int = FRAMES_PER_CHUNK
  compressed: bool = False

  @property
  def record_options(self) -> str:
    """The array_record writer options of this layout's records."""
    if self.compressed or not self.frames_per_chunk:
      return RECORD_OPTIONS
    return UNCOMPRESSED_RECORD_OPTIONS

  @functools.cached_property
  def time(self) -> tuple[str, ...]:
    return time_fields(self.features)

  @functools.cached_property
  def header(self) -> tuple[str, ...]:
    return tuple(k for k in self.features if k not in self.time)

  @functools.cached_property
  def chunk_features(self) -> tfds.features.FeaturesDict:
    return tfds.features.FeaturesDict(
        {k: _free_time(self.features[k]) for k in self.time})

  @functools.cached_property
  def header_features(self) -> tfds.features.FeaturesDict | None:
    if not self.header:
      return None
    return tfds.features.FeaturesDict(
        {k: self.features[k] for k in self.header})

  def num_records(self, num_frames: int) -> int:
    if not self.frames_per_chunk:
      return 1
    return bool(self.header) + math.ceil(num_frames / self.frames_per_chunk)

  def index(self, split_frames: Mapping[str, Sequence[int]]
            ) -> dict[str, Any]:
    """The contents of ``INDEX_FILE`` for {split: frame count per video}."""
    splits = {}
    for split, frames in sorted(split_frames.items()):
      counts = [self.num_records(int(t)) for t in frames]
      first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
      splits[split] = {'num_frames': [int(t) for t in frames],
                       'first_record': [int(r) for r in first],
                       'num_records': int(sum(counts))}
    return {'layout': LAYOUT, 'layout_version': LAYOUT_VERSION,
            'frames_per_chunk': self.frames_per_chunk,
            'compressed': bool(self.compressed or not self.frames_per_chunk),
            'time_fields': list(self.time), 'header_fields': list(self.header),
            'splits': splits}


def read_index(dataset_dir: str | os.PathLike[str]) -> dict[str, Any] | None:
  """The folder's chunk index; None for a whole-video (1.0.0) folder.

  Raises:
    UserError: an index of a layout this code does not know.
  """
  path = Path(dataset_dir) / INDEX_FILE
  if not path.is_file():
    return None
  index = read_json(path, fix=f'Delete {dataset_dir} and prepare it again.')
  if (index.get('layout') != LAYOUT
      or index.get('layout_version') != LAYOUT_VERSION):
    raise UserError(
        f'{dataset_dir} is in layout {index.get("layout")!r} version '
        f'{index.get("layout_version")!r}; this code reads {LAYOUT!r} '
        f'version {LAYOUT_VERSION} and whole-video folders. Update the code '
        'or prepare the dataset again.')
  return index
