"""OBJ3D (G-SWM's release, as used by SlotFormer): the dataset, its layout
and its conversion.

Published layout (the download from the G-SWM repository, unpacked)::

    <source>/
      train/  0/test_1.png ... test_100.png   # one folder per video
              1/...
      val/    ...
      test/   ...

Folder names are video numbers; frames are PNGs ``test_<k>.png`` numbered
from 1 (100 per video). Following G-SWM and SlotFormer we keep the first 50
frames (``test_1 .. test_50``; most interactions are over by then), resized to
the training resolution (64x64 in the paper). PNGs with alpha are reduced to
RGB by dropping alpha, as the official loader does.

Stored item (one per video folder, folders in numeric order):

* ``video``: uint8 [50, H, W, 3] RGB.
* ``video_name``: the folder name (bytes).

OBJ3D has no masks or boxes.
"""

from __future__ import annotations

import os

import dataclasses
import functools
from pathlib import Path

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import media
from slotformer_jax.datasets import base

NAME = 'obj3d'
SPLITS: tuple[str, ...] = ('train', 'val', 'test')
DEFAULT_RESOLUTION = (64, 64)
FRAME_TEMPLATE = 'test_{}.png'  # 1-based frame numbers
# Bump when the stored content changes for identical options (it is part of
# the folder name, so stale conversions are never picked up).
CONVERTER_VERSION = 1

LAYOUT = """\
<source>/train/<video number>/test_1.png ... test_100.png
<source>/val/<video number>/test_1.png ...
<source>/test/<video number>/test_1.png ...
(the OBJ3D archive linked from https://github.com/zhixuan-lin/G-SWM, unpacked)"""


@dataclasses.dataclass(frozen=True)
class Options(base.ConversionOptions):
  """Conversion parameters.

  Attributes:
    resolution: (H, W) of the stored frames.
    num_frames: leading frames kept per video (``test_1 .. test_<n>``).
  """

  resolution: tuple[int, int] = DEFAULT_RESOLUTION
  num_frames: int = 50
  version = CONVERTER_VERSION


@dataclasses.dataclass(frozen=True)
class VideoJob:
  """One video folder."""

  key: str
  folder: Path


layout_error = functools.partial(base.layout_error, 'OBJ3D', LAYOUT)


def discover(source: Path, split: str, options: Options) -> list[VideoJob]:
  """The video folders of ``split`` in numeric order.

  Raises:
    FileNotFoundError: the split folder is missing or holds no video folder.
  """
  del options  # the listing does not depend on them
  split_dir = source / split
  if not split_dir.is_dir():
    raise layout_error(source, split_dir)
  folders = sorted((p for p in split_dir.iterdir()
                    if p.is_dir() and not p.name.startswith('.')),
                   key=lambda p: media.natural_key(p.name))
  if not folders:
    raise layout_error(source, split_dir / '<video number>',
                       ' (the split folder has no video folders)')
  return [VideoJob(key=folder.name, folder=folder) for folder in folders]


def convert_video(job: VideoJob, options: Options) -> dict[str, object]:
  """Reads frames ``test_1 .. test_<num_frames>`` of one video folder.

  Raises:
    media.SkipVideo: 'truncated_video' (fewer frames), 'unreadable_frame',
      'frame_size_mismatch' (frames of different sizes in one video).
  """
  frames = []
  for number in range(1, options.num_frames + 1):
    path = job.folder / FRAME_TEMPLATE.format(number)
    # What exists but is no regular file (a FIFO, a link to /dev/zero) is
    # named as such by read_image, not called missing.
    if not os.path.lexists(path):
      available = len(list(job.folder.glob(FRAME_TEMPLATE.format('*'))))
      raise media.SkipVideo(
          'truncated_video',
          f'{job.folder}: {path.name} is missing ({available} frames, '
          f'{options.num_frames} needed)')
    frame = media.read_image(path)
    if frames and frame.shape != frames[0].shape:
      raise media.SkipVideo(
          'frame_size_mismatch',
          f'{path} is {frame.shape[1]}x{frame.shape[0]} but '
          f'{FRAME_TEMPLATE.format(1)} is {frames[0].shape[1]}x'
          f'{frames[0].shape[0]}')
    frames.append(frame)
  video = media.resize_frames(np.stack(frames), options.resolution)
  return {'video': video, 'video_name': job.key}


def features(options: Options) -> tfds.features.FeaturesDict:
  h, w = options.resolution
  return tfds.features.FeaturesDict({
      'video': base.tensor((options.num_frames, h, w, 3), np.uint8),
      'video_name': tfds.features.Text(),
  })


def describe(options: Options) -> str:
  return (f'OBJ3D (G-SWM): first {options.num_frames} frames per video at '
          f'{options.resolution[0]}x{options.resolution[1]}, RGB.')


DATASET = base.register(base.Converted(
    names=(NAME,), label='OBJ3D', command=NAME, splits=SPLITS, layout=LAYOUT,
    features=functools.partial(features, Options()),
    # The official models read the PNGs with PIL.
    official_channel_order='rgb',
    options=Options, discover=discover, convert=convert_video,
    stored=features, describe=describe))
