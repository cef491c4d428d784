"""Writing the chunked record layout (``data/chunked.py``): videos into
records, whole folders, and the checksums the readers verify.

:func:`write_folder` writes a complete TFDS folder (the generated datasets;
tests and benchmarks with ``frames_per_chunk=0`` for the whole-video
layout); ``convert.py`` writes converted datasets shard by shard with
:class:`VideoSerializer` and :func:`write_index`; :func:`record_checksums`
writes ``checksums.json`` (``data/integrity.py`` verifies it).
"""

from __future__ import annotations

import math
import os
import shutil
import uuid
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data.chunked import FRAMES_PER_CHUNK
from slotformer_jax.data.chunked import INDEX_FILE
from slotformer_jax.data.chunked import Layout
from slotformer_jax.data.chunked import RECORD_OPTIONS
from slotformer_jax.data.chunked import UNCOMPRESSED_RECORD_OPTIONS
from slotformer_jax.data.chunked import TFDS_VERSION
from slotformer_jax.data.integrity import CHECKSUMS_FILE
from slotformer_jax.data.integrity import checksummed_files
from slotformer_jax.data.integrity import file_entry
from slotformer_jax.files import write_json_atomic

# The TFDS version folder of the whole-video layout before the chunked one.
WHOLE_VIDEO_VERSION = '1.0.0'


def record_checksums(dataset_dir: str | os.PathLike[str]) -> None:
  """Writes checksums.json for every record / metadata file of the folder."""
  dataset_dir = Path(dataset_dir)
  write_json_atomic(dataset_dir / CHECKSUMS_FILE, {
      p.name: file_entry(p) for p in checksummed_files(dataset_dir)})


def _serializer(features: tfds.features.FeaturesDict | None) -> Any:
  from tensorflow_datasets.core import example_serializer  # pylint: disable=g-import-not-at-top
  if features is None:
    return None
  return example_serializer.ExampleSerializer(features.get_serialized_info())


class VideoSerializer:
  """Serialises one video's example into the records of a :class:`Layout`."""

  def __init__(self, layout: Layout):
    self.layout = layout
    if layout.frames_per_chunk:
      self._chunks = _serializer(layout.chunk_features)
      self._header = _serializer(layout.header_features)
    else:
      self._whole = _serializer(layout.features)

  def records(self, example: Mapping[str, Any]) -> tuple[list[bytes], int]:
    """The serialised records of one video, and its frame count.

    Raises:
      ValueError: a time-axis field with another frame count than ``video``.
    """
    layout = self.layout
    num_frames = int(np.shape(example['video'])[0])
    if not layout.frames_per_chunk:
      return [self._whole.serialize_example(
          layout.features.encode_example(example))], num_frames
    for key in layout.time:
      if np.shape(example[key])[0] != num_frames:
        raise ValueError(f'field {key!r} has {np.shape(example[key])[0]} '
                         f'frames but video has {num_frames}')
    out = []
    if self._header is not None:
      out.append(self._header.serialize_example(
          layout.header_features.encode_example(
              {k: example[k] for k in layout.header})))
    k = layout.frames_per_chunk
    for start in range(0, num_frames, k):
      chunk = {key: np.asarray(example[key])[start:start + k]
               for key in layout.time}
      out.append(self._chunks.serialize_example(
          layout.chunk_features.encode_example(chunk)))
    return out, num_frames


def write_index(dataset_dir: str | os.PathLike[str], layout: Layout,
                split_frames: Mapping[str, Sequence[int]]) -> None:
  """Writes ``INDEX_FILE`` (nothing for the whole-video layout)."""
  if layout.frames_per_chunk:
    write_json_atomic(Path(dataset_dir) / INDEX_FILE,
                      layout.index(split_frames))


def write_records(path: str | os.PathLike[str], records: Iterable[bytes],
                  options: str = RECORD_OPTIONS) -> int:
  """Writes records into one array_record file with writer `options`
  (`Layout.record_options`); how many."""
  from array_record.python import array_record_module  # pylint: disable=g-import-not-at-top
  if options not in (RECORD_OPTIONS, UNCOMPRESSED_RECORD_OPTIONS):
    raise ValueError(f'unknown record options {options!r}')
  writer = array_record_module.ArrayRecordWriter(os.fspath(path), options)
  count = 0
  try:
    for record in records:
      writer.write(record)
      count += 1
  finally:
    writer.close()
  return count


def shard_filename(name: str, split: str, index: int, num_shards: int) -> str:
  """TFDS's default shard naming, which ``write_metadata`` parses back."""
  return f'{name}-{split}.array_record-{index:05d}-of-{num_shards:05d}'


def write_folder(dataset_dir: str | os.PathLike[str], *, name: str,
                 features: tfds.features.FeaturesDict, description: str,
                 splits: Mapping[str, Iterable[Mapping[str, Any]]],
                 sizes: Mapping[str, int],
                 frames_per_chunk: int = FRAMES_PER_CHUNK,
                 compressed: bool = False,
                 videos_per_shard: int = 256,
                 metadata: Mapping[str, Any] | None = None,
                 extra_files: Sequence[Path] = ()) -> Path:
  """Writes a complete folder: records, TFDS metadata, index, checksums.

  Written into a temporary sibling (``incomplete.<id>_<name>``, which the
  embedded writers clean up after an interrupted run) and renamed, so
  ``dataset_info.json`` appears only in a finished folder.

  Args:
    dataset_dir: the TFDS version folder to make (must not exist).
    name: the dataset name (shard-file prefix).
    features: the videos' features.
    description: stored in ``dataset_info.json``.
    splits: {split: examples in index order}.
    sizes: {split: number of examples} (for the shard plan).
    frames_per_chunk: K (0: whole-video records).
    compressed: compress the chunks (`Layout.compressed`).
    videos_per_shard: videos per shard file.
    metadata: stored in the TFDS metadata.
    extra_files: copied into the folder (e.g. ``video_names.json``).
  """
  dataset_dir = Path(dataset_dir)
  layout = Layout(features, frames_per_chunk, compressed)
  serializer = VideoSerializer(layout)
  tmp = dataset_dir.parent / f'incomplete.{uuid.uuid4().hex}_{dataset_dir.name}'
  tmp.mkdir(parents=True)
  try:
    split_infos, split_frames = [], {}
    for split, examples in splits.items():
      size = int(sizes[split])
      num_shards = max(1, math.ceil(size / videos_per_shard))
      iterator = iter(examples)
      frames, lengths, num_bytes = [], [], 0
      for shard in range(num_shards):
        count = min(videos_per_shard, size - shard * videos_per_shard)

        def shard_records(count=count):
          for _ in range(count):
            records, num_frames = serializer.records(next(iterator))
            frames.append(num_frames)
            yield from records
        path = tmp / shard_filename(name, split, shard, num_shards)
        lengths.append(write_records(path, shard_records(),
                                     layout.record_options))
        num_bytes += path.stat().st_size
      split_frames[split] = frames
      split_infos.append(tfds.core.SplitInfo(
          name=split, shard_lengths=lengths, num_bytes=num_bytes))
    for path in extra_files:
      shutil.copy2(path, tmp / Path(path).name)
    write_index(tmp, layout, split_frames)
    tfds.folder_dataset.write_metadata(
        data_dir=os.fspath(tmp), features=features, split_infos=split_infos,
        version=dataset_dir.name if tfds.core.Version.is_valid(
            dataset_dir.name) else (TFDS_VERSION if frames_per_chunk
                                    else WHOLE_VIDEO_VERSION),
        check_data=False, description=description,
        metadata=tfds.core.MetadataDict(metadata or {}))
    record_checksums(tmp)
    try:
      os.replace(tmp, dataset_dir)
    except OSError:
      # Another writer finished the same folder first: keep theirs.
      if not (dataset_dir / 'dataset_info.json').is_file():
        raise
  finally:
    if tmp.exists():
      shutil.rmtree(tmp, ignore_errors=True)
  return dataset_dir
