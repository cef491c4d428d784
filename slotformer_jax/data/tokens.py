"""The frozen dVAE's tokens of every frame of a split, computed once.

One folder per split::

    tokens.u16       uint16 rows of [num_tokens] (h * w, raster order), all
                     videos concatenated along time (read back as a memmap)
    video_index.npy  int64 [num_videos, 2]: (first row, number of frames)
    meta.json        num_videos, num_tokens, dvae_step, parent (the dVAE's
                     run id and step, see steve_workdir.py), complete

`TokenSource` serves a video source's items with their 'tokens' [T, L]
added, so STEVE's training clips take frames and tokens from the same steps.
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

TOKENS_FILE = 'tokens.u16'
INDEX_FILE = 'video_index.npy'
META_FILE = 'meta.json'


def read_meta(directory: str) -> dict[str, Any] | None:
  path = os.path.join(directory, META_FILE)
  if not os.path.exists(path):
    return None
  with open(path) as f:
    return json.load(f)


class TokenWriter:
  """Writes the tokens of one split, video by video, in any index order."""

  def __init__(self, directory: str, num_videos: int, num_tokens: int,
               dvae_step: int, *, parent: dict[str, Any] | None = None):
    os.makedirs(directory, exist_ok=True)
    self._directory = directory
    self._meta = dict(num_videos=num_videos, num_tokens=num_tokens,
                      dvae_step=dvae_step, parent=parent,
                      complete=False)
    self._write_meta()
    self._index = np.full((num_videos, 2), -1, np.int64)
    self._file = open(os.path.join(directory, TOKENS_FILE), 'wb')
    self._rows = 0

  def _write_meta(self):
    with open(os.path.join(self._directory, META_FILE), 'w') as f:
      json.dump(self._meta, f, indent=1)

  def add(self, video_index: int, tokens: np.ndarray) -> None:
    """tokens: int [num_frames, num_tokens] of one video (< 2**16 codes)."""
    if tokens.ndim != 2 or tokens.shape[1] != self._meta['num_tokens']:
      raise ValueError(f'tokens {tokens.shape} do not match '
                       f'[T, {self._meta["num_tokens"]}]')
    self._file.write(np.ascontiguousarray(tokens, np.uint16).tobytes())
    self._index[video_index] = (self._rows, len(tokens))
    self._rows += len(tokens)

  def close(self) -> None:
    """Marks the split complete; fails if a video was never added."""
    self._file.close()
    missing = np.flatnonzero(self._index[:, 0] < 0)
    if missing.size:
      raise RuntimeError(
          f'tokenization missed {missing.size} videos, e.g. {missing[:5]}')
    np.save(os.path.join(self._directory, INDEX_FILE), self._index)
    self._meta['complete'] = True
    self._write_meta()


class TokenSource:
  """A video source's items plus 'tokens' uint16 [T, L] of the same frames."""

  def __init__(self, directory: str, video_source: Any):
    meta = read_meta(directory)
    if not meta or not meta.get('complete'):
      raise FileNotFoundError(f'no complete tokens under {directory}')
    self._videos = video_source
    self._index = np.load(os.path.join(directory, INDEX_FILE))
    if len(self._index) != len(video_source):
      raise ValueError(f'{directory} has tokens of {len(self._index)} videos, '
                       f'the video source has {len(video_source)}')
    self._tokens = np.memmap(os.path.join(directory, TOKENS_FILE),
                             np.uint16, 'r').reshape(-1, meta['num_tokens'])

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
