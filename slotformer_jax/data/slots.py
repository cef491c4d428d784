"""Per-frame arrays a model computed once per split, on disk: the extracted
slots, and STEVE's dVAE tokens; the sources that serve them with the frames.

One folder per split, either kind::

    slots.f32 / tokens.u16   rows (float32 [num_slots * slot_size] / uint16
                     [num_tokens], h * w raster order), all videos
                     concatenated along time (read back as a memmap)
    video_index.npy  int64 [num_videos, 2]: (first row, number of frames)
    meta.json        num_videos, the row shape (num_slots, slot_size /
                     num_tokens), the model's step, parent (the run id + step
                     that made them), complete, checksums (crc32 of both
                     files); slots also their extraction settings (fields)

A raw file + index (rather than one .npy) lets extraction append batch after
batch without knowing the total length in advance, and serves videos of
different lengths.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from slotformer_jax.data.integrity import file_crc32
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic

SLOTS_FILE = 'slots.f32'
TOKENS_FILE = 'tokens.u16'
INDEX_FILE = 'video_index.npy'
META_FILE = 'meta.json'


def read_meta(directory: str) -> dict[str, Any] | None:
  """The split's meta.json, or None if the folder holds nothing yet."""
  path = os.path.join(directory, META_FILE)
  if not os.path.exists(path):
    return None
  return read_json(path, fix=f'Delete {directory} and compute it again '
                   '(--mode=extract_slots or --mode=tokenize_frames).')


class RowWriter:
  """Writes the per-frame rows of one split, video by video, in any index
  order; ``meta`` is recorded with them (``complete`` once closed).

  Args:
    directory: the split's folder.
    data_file: SLOTS_FILE or TOKENS_FILE.
    dtype: of the stored rows.
    row_shape: of one frame's row (checked by :meth:`add`).
    meta: what meta.json records besides ``num_videos`` and ``complete``.
    what: the rows in messages ('slots'), and what computes them
      ('slot extraction').
  """

  def __init__(self, directory: str, num_videos: int, data_file: str,
               dtype: Any, row_shape: Sequence[int], meta: dict[str, Any], *,
               what: tuple[str, str]):
    os.makedirs(directory, exist_ok=True)
    self._directory = directory
    self._data_file = data_file
    self._dtype = np.dtype(dtype)
    self._row_shape = tuple(row_shape)
    self._what = what
    self._meta = dict(num_videos=num_videos, **meta, complete=False)
    self._write_meta()
    self._index = np.full((num_videos, 2), -1, np.int64)
    self._file = open(os.path.join(directory, data_file), 'wb')
    self._rows = 0

  def _write_meta(self):
    write_json_atomic(os.path.join(self._directory, META_FILE), self._meta)

  def add(self, video_index: int, rows: np.ndarray) -> None:
    """rows: [num_frames, *row_shape] of one video."""
    if rows.ndim != 1 + len(self._row_shape) or (
        rows.shape[1:] != self._row_shape):
      raise ValueError(f'{self._what[0]} {rows.shape} do not match '
                       f'[T, {", ".join(map(str, self._row_shape))}]')
    self._file.write(np.ascontiguousarray(rows, self._dtype).tobytes())
    self._index[video_index] = (self._rows, len(rows))
    self._rows += len(rows)

  def close(self) -> None:
    """Marks the split complete; fails if a video was never added."""
    self._file.flush()
    os.fsync(self._file.fileno())
    self._file.close()
    missing = np.flatnonzero(self._index[:, 0] < 0)
    if missing.size:
      raise RuntimeError(
          f'{self._what[1]} missed {missing.size} videos, e.g. '
          f'{missing[:5]}')
    index_path = os.path.join(self._directory, INDEX_FILE)
    with open(index_path, 'wb') as f:
      np.save(f, self._index)
      f.flush()
      os.fsync(f.fileno())
    self._meta['checksums'] = {
        name: file_crc32(os.path.join(self._directory, name))
        for name in (self._data_file, INDEX_FILE)}
    self._meta['complete'] = True
    self._write_meta()


def open_rows(directory: str, data_file: str, dtype: Any,
              row_shape: Sequence[str], missing: Exception, *,
              verify: bool = False
              ) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
  """(meta, index int64 [num_videos, 2], rows memmap [total frames,
  *row_shape]) of a complete split; ``row_shape``: the meta keys of the row
  shape. Raises ``missing`` when the split is not complete."""
  meta = read_meta(directory)
  if meta is None or not meta.get('complete'):
    raise missing
  if verify:
    verify_files(directory, meta)
  index = np.load(os.path.join(directory, INDEX_FILE))
  rows = np.memmap(os.path.join(directory, data_file), dtype=dtype,
                   mode='r').reshape(-1, *(meta[key] for key in row_shape))
  return meta, index, rows


def SlotWriter(directory: str, num_videos: int, num_slots: int,  # pylint: disable=invalid-name
               slot_size: int, savi_step: int, *,
               parent: dict[str, Any] | None = None,
               fields: dict[str, Any] | None = None) -> RowWriter:
  """The writer of a split's extracted slots (float32 [T, N, D] per
  video)."""
  return RowWriter(directory, num_videos, SLOTS_FILE, np.float32,
                   (num_slots, slot_size),
                   dict(num_slots=num_slots, slot_size=slot_size,
                        savi_step=savi_step, parent=parent, fields=fields),
                   what=('slots', 'slot extraction'))


def TokenWriter(directory: str, num_videos: int, num_tokens: int,  # pylint: disable=invalid-name
                dvae_step: int, *, parent: dict[str, Any] | None = None
                ) -> RowWriter:
  """The writer of a split's dVAE tokens (int [T, L] per video, < 2**16
  codes)."""
  return RowWriter(directory, num_videos, TOKENS_FILE, np.uint16,
                   (num_tokens,),
                   dict(num_tokens=num_tokens, dvae_step=dvae_step,
                        parent=parent),
                   what=('tokens', 'tokenization'))


class SlotSource:
  """Random access to extracted slots, optionally with the video's frames.

  Items: {'slots': float32 [T, N, D]} plus the requested fields of
  `video_source[i]` (e.g. 'video' uint8 [T, H, W, 3]), which must have the
  same number of frames.

  `video_from`: a training clip (`clip`) reads the video fields from its
  ``video_from``-th frame on, e.g. SlotFormer's image loss, which compares
  only the rollout frames: {'slots': [L, N, D], 'video': [L - video_from,
  H, W, 3]}. Whole items (``source[i]``) are unaffected.
  """

  def __init__(self, directory: str, video_source: Any = None,
               video_fields: tuple[str, ...] = ('video',), *,
               verify: bool = True, video_from: int = 0):
    self.meta, self._index, self._slots = open_rows(
        directory, SLOTS_FILE, np.float32, ('num_slots', 'slot_size'),
        MissingInputError(f'no complete slot extraction in {directory}; run '
                          '`--mode=extract_slots` first'), verify=verify)
    self._video_source = video_source
    self._video_fields = tuple(video_fields)
    if video_from < 0:
      raise ValueError(f'video_from must be >= 0, got {video_from}')
    self._video_from = video_from
    if video_source is not None and len(video_source) != len(self):
      raise ValueError(
          f'{directory} holds slots of {len(self)} videos but the video '
          f'source has {len(video_source)}')

  def __len__(self) -> int:
    return len(self._index)

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    start, length = self._index[index]
    # A read-only view of the memory map, not a copy: a training clip
    # copies only its own frames (pipeline._slice_item, then np.stack), not
    # the whole video's (Physion: 25 of 150 frames).
    item = {'slots': np.asarray(self._slots[start:start + length])}
    if self._video_source is not None and self._video_fields:
      video_item = self._video_source[index]
      for field in self._video_fields:
        value = video_item[field]
        if len(value) != length:
          raise ValueError(
              f'video {index}: {field} has {len(value)} frames but '
              f'{length} slots were extracted')
        item[field] = value
    return item


  # Clips (pipeline.make_train_batch): the slots are a memory map, so a clip
  # reads its own rows; the frames come from the video source's clip reader
  # when it has one (chunked TFDS folders), else from the whole video.
  supports_clips = True

  @property
  def time_fields(self) -> tuple[str, ...]:
    return ('slots',) + (self._video_fields
                         if self._video_source is not None else ())

  def num_frames(self, index: int) -> int:
    return int(self._index[index][1])

  def clip(self, index: int, start: int, length: int, stride: int = 1,
           fields: tuple[str, ...] = ('slots',)) -> dict[str, np.ndarray]:
    """As ``pipeline._slice_item(self[index], fields, ...)``, except that
    the video fields start `video_from` frames into the clip."""
    first, num_frames = (int(v) for v in self._index[index])
    end = start + (length - 1) * stride + 1
    if length < 1 or stride < 1 or start < 0 or end > num_frames:
      raise ValueError(
          f'video {index} has {num_frames} frames; a clip of {length} frames '
          f'with stride {stride} from frame {start} does not fit')
    out = {}
    video_fields = [f for f in fields if f != 'slots']
    if video_fields and self._video_from >= length:
      raise ValueError(f'a clip of {length} frames has no video frames '
                       f'from frame {self._video_from} on')
    # Only the frames the clip's video fields keep are read.
    video_start = start + self._video_from * stride
    video_length = length - self._video_from
    if video_fields:
      if (self._video_source is None
          or any(f not in self._video_fields for f in video_fields)):
        raise KeyError(f'item {index} has no field(s) {video_fields}; it has '
                       f'{["slots", *self._video_fields]}')
      if getattr(self._video_source, 'supports_clips', False):
        have = self._video_source.num_frames(index)
        if have != num_frames:
          raise ValueError(
              f'video {index}: the video has {have} frames but '
              f'{num_frames} slots were extracted')
        frames = self._video_source.clip(index, video_start, video_length,
                                         stride, video_fields)
      else:
        from slotformer_jax.data import pipeline  # pylint: disable=g-import-not-at-top
        item = self[index]
        frames = pipeline._slice_item(item, video_fields, index,  # pylint: disable=protected-access
                                      video_start, video_length, stride)
    for field in fields:
      out[field] = (np.asarray(self._slots[first + start:first + end:stride])
                    if field == 'slots' else frames[field])
    return out


def verify_files(directory: str, meta: dict[str, Any]) -> None:
  """Compares the files with the checksums stored with them.

  Raises:
    UserError: a file changed since (garbled, truncated); names the fix.
  """
  for name, expected in (meta.get('checksums') or {}).items():
    path = os.path.join(directory, name)
    actual = file_crc32(path) if os.path.exists(path) else 'missing'
    if actual != expected:
      raise UserError(
          f'{path} is damaged (crc32 {actual}, extraction wrote {expected}). '
          f'Delete {directory} and re-run --mode=extract_slots.')


class TokenSource:
  """A video source's items plus 'tokens' uint16 [T, L] of the same frames."""

  def __init__(self, directory: str, video_source: Any):
    _, self._index, self._tokens = open_rows(
        directory, TOKENS_FILE, np.uint16, ('num_tokens',),
        FileNotFoundError(f'no complete tokens under {directory}'))
    self._videos = video_source
    if len(self._index) != len(video_source):
      raise ValueError(f'{directory} has tokens of {len(self._index)} videos, '
                       f'the video source has {len(video_source)}')

  def __len__(self) -> int:
    return len(self._videos)

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    item = dict(self._videos[index])
    start, length = self._index[index]
    item['tokens'] = np.asarray(self._tokens[start:start + length])
    return item

  # Clips (pipeline.make_train_batch) when the video source reads clips
  # (chunked TFDS folders): the tokens are a memory map, so a clip reads
  # its own rows, and the frames only the chunks that hold them.
  @property
  def supports_clips(self) -> bool:
    return bool(getattr(self._videos, 'supports_clips', False))

  @property
  def time_fields(self) -> tuple[str, ...]:
    return tuple(getattr(self._videos, 'time_fields', ())) + ('tokens',)

  def num_frames(self, index: int) -> int:
    return self._videos.num_frames(index)

  def clip(self, index: int, start: int, length: int, stride: int = 1,
           fields: tuple[str, ...] = ('video', 'tokens')
           ) -> dict[str, np.ndarray]:
    """As ``pipeline._slice_item(self[index], fields, ...)``."""
    video_fields = [f for f in fields if f != 'tokens']
    out = (dict(self._videos.clip(index, start, length, stride,
                                  video_fields)) if video_fields else {})
    if 'tokens' in fields:
      first, count = (int(v) for v in self._index[index])
      num_frames = self._videos.num_frames(index)
      if count != num_frames:
        raise ValueError(
            f'item {index}: field \'tokens\' has {count} steps on its first '
            f'axis but the video has {num_frames}; every requested '
            'non-scalar field must have time first')
      end = start + (length - 1) * stride + 1
      out['tokens'] = np.asarray(self._tokens[first + start:first + end:stride])
    return {field: out[field] for field in fields}
