"""Anti-aliasing by supersampling: frames rendered at f x the resolution,
reduced to it.

Shared by the renderers of the generators (datasets/) and of the
PHYRE-like world, which planning renders at run time; integer arithmetic
only, so the frames are bit-exact across numpy versions.
"""

from __future__ import annotations

import numpy as np


def downsample_rgb(image: np.ndarray, factor: int) -> np.ndarray:
  """Area-averages uint8 [H*f, W*f, C] into uint8 [H, W, C] (anti-aliasing)."""
  if factor == 1:
    return image
  h, w, c = image.shape[0] // factor, image.shape[1] // factor, image.shape[2]
  blocks = image.reshape(h, factor, w, factor, c).astype(np.uint16)
  total = blocks.sum(axis=(1, 3), dtype=np.uint32)
  # Integer rounding keeps the result bit-exact across numpy versions.
  return ((total + factor * factor // 2) // (factor * factor)).astype(np.uint8)


def downsample_segmentation(seg: np.ndarray, factor: int) -> np.ndarray:
  """Majority vote over f x f blocks: [H*f, W*f] ids -> [H, W], same dtype.

  Unlike averaging, the vote keeps exact ids; ties go to the id seen first in
  raster order inside the block.
  """
  if factor == 1:
    return seg
  h, w = seg.shape[0] // factor, seg.shape[1] // factor
  blocks = seg.reshape(h, factor, w, factor).transpose(0, 2, 1, 3)
  blocks = blocks.reshape(h, w, factor * factor)
  # counts[..., i] = how many samples in the block share sample i's id.
  counts = (blocks[..., :, None] == blocks[..., None, :]).sum(-1)
  winner = counts.argmax(-1)
  return np.take_along_axis(blocks, winner[..., None], -1)[..., 0]


def downsample_by_label(values: np.ndarray, labels: np.ndarray,
                        voted: np.ndarray, factor: int) -> np.ndarray:
  """Per f x f block, the mean of the samples whose label is the block's
  voted one (`downsample_segmentation`'s): float [H*f, W*f, C] values with
  [H*f, W*f] labels -> float32 [H, W, C].

  So a pixel's value (depth, flow) is that of the surface its mask says it
  shows, never a blend of an object's and the floor's across its edge,
  which an area mean would make (a depth between the two surfaces, a
  motion neither has).
  """
  if factor == 1:
    return np.asarray(values, np.float32)
  h, w = labels.shape[0] // factor, labels.shape[1] // factor
  channels = values.shape[-1]
  blocks = values.reshape(h, factor, w, factor, channels).transpose(
      0, 2, 1, 3, 4).reshape(h, w, factor * factor, channels)
  names = labels.reshape(h, factor, w, factor).transpose(0, 2, 1, 3).reshape(
      h, w, factor * factor)
  chosen = (names == voted[..., None])[..., None]  # >= 1 sample per block
  total = np.where(chosen, blocks, 0.0).sum(axis=2)
  return (total / chosen.sum(axis=2)).astype(np.float32)
