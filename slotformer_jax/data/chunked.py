"""Chunked video records: a training clip reads only the frames it holds.

Layout ``chunked`` version 1 (TFDS version folder ``2.0.0`` of the converted
and embedded datasets; the whole-video layout before it is ``1.0.0``). The
folder stays an ``array_record`` TFDS folder (``dataset_info.json``,
``features.json`` describing the *videos*, as before, and shard files
``<name>-<split>.array_record-<i>-of-<n>``), but the records of one video
are::

    [header]  the video's per-video fields (scalars, strings, per-object
              arrays), when the dataset has any
    chunk 0   frames 0 .. K-1 of every time-axis field (video,
              segmentations, boxes, visible, ...)
    chunk 1   frames K .. 2K-1
    ...       (the last chunk holds the remaining 1..K frames)

each record compressed on its own (``group_size:1``), videos one after the
other in index order. ``video_chunks.json`` (this module's ``INDEX_FILE``,
covered by ``checksums.json``) holds the layout, ``K``, the time-axis fields
and, per split, every video's frame count and first record, so a reader
knows a video's length without decoding it and reads a clip's frames from
``ceil``-many chunks instead of the whole video.

Time-axis fields are the ``video`` and every other ``Tensor`` feature of
rank >= 2 whose first dimension is the video's (``(T, ...)`` or ``(None,
...)``); :func:`time_fields`. Records are TFDS-serialised examples of
derived feature dicts (time fields with their first dimension free; the
header: the other fields), decoded with TFDS's numpy decoder as the
whole-video records were, so values are bit-identical across layouts.

Chunk size ``K`` (:data:`FRAMES_PER_CHUNK`), measured with
``benchmarks/clip_reader.py --chunks=1,2,4,8`` on one pinned core (table in
docs/datasets.md, "Record layout"): smaller chunks read fewer unneeded
frames but pay the per-record cost (lookup, decompression set-up, proto)
more often and compress worse; larger ones decompress more unneeded frames.
Delivered clip frames/s per core, whole videos -> K=1 / 2 / 4 / 8:

* OBJ3D SAVi (6 of 50 frames): 2,519 -> 12,172 / 14,103 / 12,838 / 11,210
* CLEVRER SAVi (6 of 128): 959 -> 11,379 / 14,380 / 14,061 / 10,369
* OBJ3D SlotFormer L_I (16 of 50 + slots): 6,965 -> 13,778 / 18,113 /
  18,571 / 16,662
* CLEVRER SlotFormer L_I (16 stride 2 of 128 + slots): 2,144 -> 6,249 /
  9,233 / 9,736 / 9,806
* Physion dVAE (1 of 150, 128x128): 21 -> 2,853 / 1,764 / 1,082 / 591
* file size relative to whole videos: +19 % / +15 % / +10 % / +7 %

K = 4: best or within 10 % of the best for 6- and 16-frame clips, for
10 % more disk.

Why not an uncompressed memory map: CLEVRER's 10k training videos of 128
frames are 15.7 GB of raw 64x64 frames (63 GB at 128x128); the compressed
records of rendered scenes are a fraction of that, and the checksums,
resumable conversion and TFDS metadata keep working unchanged.

:func:`write_folder` writes a complete folder (the embedded families and
:func:`relayout`); ``data/convert/writer.py`` writes converted datasets shard
by shard with :class:`Layout`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import shutil
import uuid
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic

LAYOUT = 'chunked'
LAYOUT_VERSION = 1
# The TFDS version folder of a dataset in this layout (1.0.0: whole videos).
TFDS_VERSION = '2.0.0'
INDEX_FILE = 'video_chunks.json'  # = integrity.CHUNK_INDEX_FILE
FRAMES_PER_CHUNK = 4
# One record per compression group: reading a chunk decompresses it alone.
RECORD_OPTIONS = 'group_size:1'


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
    frames_per_chunk: K; 0 writes the whole-video layout (one record per
      video with ``features``), kept for tests and :func:`relayout`.
  """

  features: tfds.features.FeaturesDict
  frames_per_chunk: int = FRAMES_PER_CHUNK

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

  @functools.cached_property
  def _serializers(self) -> tuple[Any, Any]:
    from tensorflow_datasets.core import example_serializer  # pylint: disable=g-import-not-at-top
    make = lambda f: example_serializer.ExampleSerializer(
        f.get_serialized_info()) if f is not None else None
    if not self.frames_per_chunk:
      return make(self.features), None
    return make(self.chunk_features), make(self.header_features)

  def records(self, example: Mapping[str, Any]) -> tuple[list[bytes], int]:
    """The serialised records of one video, and its frame count.

    Raises:
      ValueError: a time-axis field with another frame count than ``video``.
    """
    num_frames = int(np.shape(example['video'])[0])
    if not self.frames_per_chunk:
      serializer, _ = self._serializers
      return [serializer.serialize_example(
          self.features.encode_example(example))], num_frames
    for key in self.time:
      if np.shape(example[key])[0] != num_frames:
        raise ValueError(f'field {key!r} has {np.shape(example[key])[0]} '
                         f'frames but video has {num_frames}')
    chunk_serializer, header_serializer = self._serializers
    out = []
    if header_serializer is not None:
      out.append(header_serializer.serialize_example(
          self.header_features.encode_example(
              {k: example[k] for k in self.header})))
    k = self.frames_per_chunk
    for start in range(0, num_frames, k):
      chunk = {key: np.asarray(example[key])[start:start + k]
               for key in self.time}
      out.append(chunk_serializer.serialize_example(
          self.chunk_features.encode_example(chunk)))
    return out, num_frames

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
            'time_fields': list(self.time), 'header_fields': list(self.header),
            'splits': splits}


def write_index(dataset_dir: str | os.PathLike[str], layout: Layout,
                split_frames: Mapping[str, Sequence[int]]) -> None:
  """Writes ``INDEX_FILE`` (nothing for the whole-video layout)."""
  if layout.frames_per_chunk:
    write_json_atomic(Path(dataset_dir) / INDEX_FILE,
                      layout.index(split_frames))


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
    from slotformer_jax.errors import UserError  # pylint: disable=g-import-not-at-top
    raise UserError(
        f'{dataset_dir} is in layout {index.get("layout")!r} version '
        f'{index.get("layout_version")!r}; this code reads {LAYOUT!r} '
        f'version {LAYOUT_VERSION} and whole-video folders. Update the code '
        'or prepare the dataset again.')
  return index


def write_records(path: str | os.PathLike[str],
                  records: Iterable[bytes]) -> int:
  """Writes records into one array_record file; how many."""
  from array_record.python import array_record_module  # pylint: disable=g-import-not-at-top
  writer = array_record_module.ArrayRecordWriter(os.fspath(path),
                                                 RECORD_OPTIONS)
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
    videos_per_shard: videos per shard file.
    metadata: stored in the TFDS metadata.
    extra_files: copied into the folder (e.g. ``video_names.json``).
  """
  # Imported here: checksums imports integrity, which is import-light.
  from slotformer_jax.data.convert.checksums import record_checksums  # pylint: disable=g-import-not-at-top
  dataset_dir = Path(dataset_dir)
  layout = Layout(features, frames_per_chunk)
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
            records, num_frames = layout.records(next(iterator))
            frames.append(num_frames)
            yield from records
        path = tmp / shard_filename(name, split, shard, num_shards)
        lengths.append(write_records(path, shard_records()))
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
            dataset_dir.name) else TFDS_VERSION,
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


def relayout(source_dir: str | os.PathLike[str],
             target_dir: str | os.PathLike[str], *,
             frames_per_chunk: int = FRAMES_PER_CHUNK) -> Path:
  """Writes the videos of a TFDS folder (either layout) in another layout
  (``frames_per_chunk=0``: whole-video records) into ``target_dir``.

  The benchmark's way to compare layouts on the same videos, and the tests'
  way to make whole-video folders; other files of the folder (e.g.
  ``video_names.json``) are copied.
  """
  from slotformer_jax.data import sources  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data.integrity import CHECKSUMS_FILE  # pylint: disable=g-import-not-at-top
  source_dir = Path(source_dir)
  builder = tfds.builder_from_directory(os.fspath(source_dir))
  info = builder.info
  split_names = sorted(info.splits)
  opened = {s: sources.TfdsVideoSource(source_dir, s) for s in split_names}
  skip = {'dataset_info.json', 'features.json', 'metadata.json',
          CHECKSUMS_FILE, INDEX_FILE}
  extra = [p for p in sorted(source_dir.iterdir())
           if p.is_file() and p.name not in skip
           and '.array_record' not in p.name]
  return write_folder(
      target_dir, name=info.name, features=info.features,
      description=info.description or '',
      splits={s: (src[i] for i in range(len(src)))
              for s, src in opened.items()},
      sizes={s: len(src) for s, src in opened.items()},
      frames_per_chunk=frames_per_chunk,
      metadata=dict(info.metadata or {}), extra_files=extra)
