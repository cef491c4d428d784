"""Decoding and resizing helpers shared by the real-dataset converters.

Every failure that is a property of one input video (unreadable or truncated
file, inconsistent frame sizes, broken per-video annotation) is raised as
:class:`SkipVideo`, which the writer logs, counts and reports at the end of a
conversion instead of aborting it. Anything else (a bug) propagates.

Videos are decoded with the ffmpeg binary shipped by ``imageio-ffmpeg`` (no
system ffmpeg needed): it is a plain subprocess per video that streams raw
RGB frames through a pipe, and the container's declared duration lets us
detect truncated files (ffmpeg itself just stops early on them).
"""

from __future__ import annotations

import math
import os
import re
import struct
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from slotformer_jax.errors import shown
from slotformer_jax.files import open_regular
from slotformer_jax.files import UntrustedFileError
from slotformer_jax.files import read_untrusted_json


class SkipVideo(Exception):
  """One video cannot be converted; it is skipped, counted and reported.

  Attributes:
    reason: short machine-readable category, e.g. 'truncated_video'; the
      conversion report counts skips per reason.
    message: human-readable detail naming the offending file.
  """

  def __init__(self, reason: str, message: str):
    super().__init__(f'{reason}: {message}')
    self.reason = reason
    self.message = message


def natural_key(name: str) -> tuple[Any, ...]:
  """Sort key that orders embedded numbers numerically ('v2' < 'v10')."""
  return tuple(int(part) if part.isdigit() else part
               for part in re.split(r'(\d+)', name))


def resize_frames(frames: np.ndarray, size: Sequence[int]) -> np.ndarray:
  """Resizes uint8 [T, h, w, 3] frames to uint8 [T, H, W, 3].

  The whole frame is resized (no crop; the aspect ratio changes when it
  differs, as in the official SlotFormer preprocessing). PIL's bilinear
  filter widens its support when downsampling, i.e. it is antialiased, so
  thin edges do not alias at 64x64. Identity when the size already matches.
  """
  height, width = int(size[0]), int(size[1])
  if frames.shape[1:3] == (height, width):
    return np.ascontiguousarray(frames)
  out = np.empty((frames.shape[0], height, width, 3), np.uint8)
  for t, frame in enumerate(frames):
    image = Image.fromarray(np.ascontiguousarray(frame))
    out[t] = np.asarray(image.resize((width, height), Image.BILINEAR))
  return out


def nearest_indices(in_size: int, out_size: int) -> np.ndarray:
  """int64 [out_size]: source index of each output pixel for nearest resizing.

  PyTorch's 'nearest' convention, ``floor(i * in / out)``, which the
  official code uses for masks (``torchvision.transforms.functional.resize``
  with NEAREST); exact integer arithmetic avoids float rounding at edges.
  """
  return (np.arange(out_size, dtype=np.int64) * in_size) // out_size


def resize_labels(labels: np.ndarray, size: Sequence[int]) -> np.ndarray:
  """Nearest-neighbour resize of integer maps [..., h, w] -> [..., H, W]."""
  rows = nearest_indices(labels.shape[-2], int(size[0]))
  cols = nearest_indices(labels.shape[-1], int(size[1]))
  return labels[..., rows[:, None], cols[None, :]]


_PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'


def png_size(head: bytes) -> tuple[int, int] | None:
  """(width, height) that a PNG's header (its first 24 bytes) states, read
  before any decoder sees the file; None if `head` is not a PNG's."""
  if len(head) < 24 or not head.startswith(_PNG_SIGNATURE) or (
      head[12:16] != b'IHDR'):
    return None
  return struct.unpack('>II', head[16:24])


# Pixels of one image file a converter decodes (OBJ3D's frames are 64 x 64,
# a PHYRE rollout strip 15 frames of 256 x 256): a header may claim any
# size, and is checked before anything is decoded.
MAX_IMAGE_PIXELS = 64 << 20


def read_image(path: Path, *, max_pixels: int = MAX_IMAGE_PIXELS
               ) -> np.ndarray:
  """uint8 [h, w, 3] RGB of an image file; alpha is dropped. Its size is
  read from the header first: more than `max_pixels` is refused before
  decoding.

  Raises:
    SkipVideo('unreadable_frame'): missing, truncated, too large, not an
      image, or not a regular file (a FIFO, a device).
  """
  try:
    # A regular file only: a FIFO would block the read, a link to
    # /dev/zero never end it.
    with open_regular(path, what='frame') as f:
      stated = png_size(f.read(24))
      if stated is not None and stated[0] * stated[1] > max_pixels:
        raise SkipVideo('unreadable_frame', f'{path}: its PNG header says '
                        f'{stated[0]}x{stated[1]} pixels, more than the '
                        f'{max_pixels} a frame may have')
      f.seek(0)
      return _decoded(f, path, max_pixels)
  except SkipVideo:
    raise
  except UntrustedFileError as error:
    raise SkipVideo('unreadable_frame', str(error)) from None
  except Exception as error:  # pylint: disable=broad-except
    # OSError, SyntaxError, PIL's bomb errors, anything a crafted file makes
    # a decoder raise: this video is skipped, naming the file.
    raise SkipVideo('unreadable_frame',
                    f'{path}: {shown(str(error), 200)}') from None


def _decoded(f, path: Path, max_pixels: int) -> np.ndarray:
  """uint8 [h, w, 3] of the open image file `f` (`read_image`)."""
  with warnings.catch_warnings():
    warnings.simplefilter('error', Image.DecompressionBombWarning)
    with Image.open(f) as image:
      width, height = image.size
      if width * height > max_pixels:
        raise SkipVideo('unreadable_frame', f'{path}: its header says '
                        f'{width}x{height} pixels, more than the '
                        f'{max_pixels} a frame may have')
      # convert('RGB') drops an alpha channel without compositing, like the
      # official OBJ3D loader; load() forces the full decode here, so a
      # truncated file fails now rather than later.
      image.load()
      return np.asarray(image.convert('RGB'))


def load_json(path: Path, what: str) -> Any:
  """Parses a per-video JSON file.

  Raises:
    SkipVideo('missing_<what>' or 'bad_<what>'): absent or unparsable.
  """
  try:
    return read_untrusted_json(path, what=what)
  except FileNotFoundError:
    raise SkipVideo(f'missing_{what}', f'{path} does not exist') from None
  except OSError as error:
    raise SkipVideo(f'bad_{what}', f'{path}: {error.strerror or error}'
                    ) from None
  except UntrustedFileError as error:
    raise SkipVideo(f'bad_{what}', str(error)) from None


# A truncated file decodes to fewer frames than its container declares; the
# declared count (duration x fps) can be off by a frame or two for valid
# files, so we only flag a shortfall beyond this tolerance.
_MIN_FRAME_TOLERANCE = 2
_REL_FRAME_TOLERANCE = 0.02


def declared_frame_tolerance(declared: int) -> int:
  """Frames a valid video may fall short of its container's declared count."""
  return max(_MIN_FRAME_TOLERANCE, math.ceil(_REL_FRAME_TOLERANCE * declared))


def decode_video(path: Path, *, max_frames: int | None = None,
                 threads: int = 1) -> tuple[np.ndarray, int | None]:
  """Decodes an mp4 (or any ffmpeg-readable video) to RGB frames.

  Args:
    path: the video file.
    max_frames: decode only the first ``max_frames`` frames (None: all).
    threads: ffmpeg decoding threads; 1 by default because conversions run
      one worker process per core.

  Returns:
    frames: uint8 [T, h, w, 3] RGB.
    declared: frames the container declares (round(duration * fps)), or
      None if it does not say.

  Raises:
    SkipVideo('unreadable_video'): ffmpeg cannot open or decode the file.
    SkipVideo('truncated_video'): fewer frames than the container declares
      (beyond :func:`declared_frame_tolerance`), or than ``max_frames`` when
      the container declares at least that many.
  """
  # Imported here: only the video datasets need it, and the error message
  # below is clearer than an ImportError at package import time.
  try:
    import imageio_ffmpeg  # pylint: disable=g-import-not-at-top
  except ImportError as error:
    raise ImportError('Decoding videos needs imageio-ffmpeg (it ships its '
                      'own ffmpeg): pip install imageio-ffmpeg') from error
  if not path.is_file():
    raise SkipVideo('unreadable_video', f'{path} does not exist')
  output_params = ['-frames:v', str(int(max_frames))] if max_frames else []
  frames = []
  reader = imageio_ffmpeg.read_frames(
      os.fspath(path), input_params=['-threads', str(int(threads))],
      output_params=output_params)
  try:
    meta = next(reader)
    width, height = (int(v) for v in meta['size'])
    for raw in reader:
      if len(raw) != width * height * 3:
        raise SkipVideo('frame_size_mismatch',
                        f'{path}: a frame of {len(raw)} bytes, expected '
                        f'{height}x{width}x3')
      frames.append(np.frombuffer(raw, np.uint8).reshape(height, width, 3))
  except (OSError, RuntimeError, StopIteration, ValueError) as error:
    first_line = str(error).strip().splitlines()[0] if str(error) else ''
    raise SkipVideo('unreadable_video', f'{path}: {first_line}') from None
  finally:
    reader.close()  # also stops ffmpeg when we leave early
  duration, fps = float(meta.get('duration') or 0), float(meta.get('fps') or 0)
  declared = round(duration * fps) if duration > 0 and fps > 0 else None
  if not frames:
    raise SkipVideo('unreadable_video', f'{path}: no frame could be decoded')
  if declared is not None:
    tolerance = declared_frame_tolerance(declared)
    if max_frames is not None and declared >= max_frames + tolerance:
      # The file surely holds max_frames frames, so all must decode.
      required = max_frames
    else:
      required = min(declared, max_frames or declared) - tolerance
    if len(frames) < required:
      raise SkipVideo('truncated_video',
                      f'{path}: decoded {len(frames)} frames but the file '
                      f'declares {declared}')
  return np.stack(frames), declared
