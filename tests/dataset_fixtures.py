"""Helpers that write tiny dataset fixtures in the published file formats.

Used by tests/test_datasets_*.py: mp4 files through imageio-ffmpeg's bundled
ffmpeg, COCO run-length-encoded masks, PNG frames.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image


def write_mp4(path: Path, frames: np.ndarray, *, fps: int = 25,
              lossless: bool = True) -> Path:
  """Writes uint8 [T, H, W, 3] RGB frames (H, W even) as an H.264 mp4.

  ``lossless`` uses 4:4:4 chroma with a constant rate factor of 0, so decoded
  pixels differ from the input only by colour-conversion rounding. The moov
  atom goes first (``+faststart``), so a file cut short still opens and
  decodes its first frames, like a download interrupted mid-file.
  """
  import imageio_ffmpeg  # pylint: disable=g-import-not-at-top
  path.parent.mkdir(parents=True, exist_ok=True)
  height, width = frames.shape[1:3]
  params = ['-movflags', '+faststart']
  if lossless:
    params += ['-crf', '0']
  writer = imageio_ffmpeg.write_frames(
      str(path), (width, height), fps=fps, macro_block_size=1,
      pix_fmt_out='yuv444p' if lossless else 'yuv420p',
      output_params=params, ffmpeg_log_level='error', quality=None)
  writer.send(None)
  for frame in frames:
    writer.send(np.ascontiguousarray(frame))
  writer.close()
  return path


def truncate(path: Path, fraction: float) -> Path:
  """Keeps the first ``fraction`` of the file's bytes."""
  data = path.read_bytes()
  path.write_bytes(data[:int(len(data) * fraction)])
  return path


def encode_rle(mask: np.ndarray) -> dict[str, Any]:
  """COCO compressed RLE {'size': [h, w], 'counts': str} of a bool [h, w].

  Runs alternate background / foreground over the column-major pixels,
  starting with background; from the fourth run on each is stored as the
  difference to the run two before, in 5-bit groups offset by 48 (0x20:
  another group follows; 0x10 in the last group: negative).
  """
  flat = np.asarray(mask, bool).T.reshape(-1)
  change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
  bounds = np.concatenate([[0], change, [flat.size]])
  runs = list(np.diff(bounds))
  if flat.size and flat[0]:
    runs = [0] + runs
  chars = []
  for i, run in enumerate(runs):
    value = int(run) - (int(runs[i - 2]) if i > 2 else 0)
    more = True
    while more:
      group = value & 0x1f
      value >>= 5
      more = value != -1 if group & 0x10 else value != 0
      if more:
        group |= 0x20
      chars.append(chr(group + 48))
  return {'size': [int(mask.shape[0]), int(mask.shape[1])],
          'counts': ''.join(chars)}


def write_png(path: Path, image: np.ndarray) -> Path:
  path.parent.mkdir(parents=True, exist_ok=True)
  Image.fromarray(image).save(path)
  return path


def write_json(path: Path, payload: Any) -> Path:
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text(json.dumps(payload))
  return path


def noise_video(num_frames: int, height: int, width: int,
                seed: int = 0) -> np.ndarray:
  """Incompressible frames: a truncated file of them loses whole frames."""
  rng = np.random.default_rng(seed)
  return rng.integers(0, 256, (num_frames, height, width, 3), np.uint8)


def marker_video(num_frames: int, height: int, width: int,
                 step: int = 10, offset: int = 20) -> np.ndarray:
  """Flat frames whose grey level ``offset + step * t`` identifies frame t."""
  levels = offset + step * np.arange(num_frames)
  return np.broadcast_to(levels[:, None, None, None].astype(np.uint8),
                         (num_frames, height, width, 3)).copy()
