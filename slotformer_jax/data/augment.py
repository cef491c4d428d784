"""Training augmentation of video clips: SAVi's random resized crop.

SAVi++ trains on random crops (google-research/slot-attention-video,
``savi/lib/preprocessing.py`` ``RandomResizedCrop``, which
``configs/movi/savi++_conditional.py`` applies with
``min_object_covered=0.75`` and the op's defaults: aspect ratios 3/4..4/3,
areas 0.08..1 of the frame, 100 attempts). One crop box per clip, for all
its frames, resized back to the clip's H x W, every spatial field alike:

  video            uint8 [T, H, W, 3]   bilinear (half-pixel centres, as
                                        tf.image.resize), rounded
  segmentations    uint8 [T, H, W]      nearest neighbour
  boxes            float32 [T, O, 4]    normalised (ymin, xmin, ymax, xmax)
                                        moved into the crop and clipped to
                                        it; a box left empty becomes SAVi's
                                        no-track box (0, 0, 0, 0), which
                                        stays as it is
  backward_flow,   float32 [T, H, W, 2] bilinear, then row x H / crop
  forward_flow     pixels               height, column x W / crop width
  depth            float32 [T, H, W, 1] the contract's log(1 + d):
                                        bilinear on d, as SAVi crops the
                                        distance before its log transform

Other fields pass through. The contract's `flow` (a colour picture) cannot
be rescaled: a clip to crop carries `backward_flow` and gets `flow` after
(`flow_depth.to_contract`). Everything here is numpy on one clip, drawn from
the generator it is given (the input pipeline's, per step and row).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from slotformer_jax import targets
from slotformer_jax.data import flow_depth

NO_TRACK_BOX = (0.0, 0.0, 0.0, 0.0)
_FLOWS = (flow_depth.BACKWARD_FLOW, flow_depth.FORWARD_FLOW)


@dataclasses.dataclass(frozen=True)
class RandomResizedCrop:
  """SAVi's random resized crop of a clip (the module docstring).

  Attributes:
    min_object_covered: the smallest share of the frame a crop keeps
      (SAVi++: 0.75; the box it must cover is the whole frame).
    aspect_ratio_range: (low, high) of the crop's width / height.
    area_range: (low, high) of the crop's area over the frame's.
    max_attempts: draws before falling back to the whole frame.
  """

  min_object_covered: float = 0.75
  aspect_ratio_range: tuple[float, float] = (3 / 4, 4 / 3)
  area_range: tuple[float, float] = (0.08, 1.0)
  max_attempts: int = 100

  def sample(self, rng: np.random.Generator, height: int, width: int
             ) -> tuple[int, int, int, int]:
    """(top, left, crop height, crop width) in pixels, drawn as TF's
    ``sample_distorted_bounding_box`` draws one over the whole frame: an
    aspect ratio uniformly, then an integer height uniformly among those
    whose area (width = round(height * ratio)) can lie in `area_range`;
    kept when it fits, its area is in range and covers
    `min_object_covered`; the offsets uniform over every position (TF's
    never reach the last one). The whole frame after `max_attempts`."""
    frame = height * width
    low_area, high_area = (a * frame for a in self.area_range)
    for _ in range(self.max_attempts):
      ratio = float(rng.uniform(*self.aspect_ratio_range))
      lowest = int(round(math.sqrt(low_area / ratio)))
      highest = min(int(round(math.sqrt(high_area / ratio))), height,
                    int((width + 0.5) / ratio))
      crop_h = (lowest if lowest >= highest
                else int(rng.integers(lowest, highest + 1)))
      crop_w = int(round(crop_h * ratio))
      area = crop_h * crop_w
      if not (1 <= crop_h <= height and 1 <= crop_w <= width
              and low_area <= area <= high_area
              and area >= self.min_object_covered * frame):
        continue
      top = int(rng.integers(0, height - crop_h + 1))
      left = int(rng.integers(0, width - crop_w + 1))
      return top, left, crop_h, crop_w
    return 0, 0, height, width

  def __call__(self, clip: Mapping[str, Any], rng: np.random.Generator
               ) -> dict[str, Any]:
    """`clip` cropped at a box drawn from `rng` (its frames' H x W)."""
    height, width = np.shape(clip['video'])[1:3]
    return crop_clip(clip, self.sample(rng, height, width))


def crop_clip(clip: Mapping[str, Any], box: tuple[int, int, int, int]
              ) -> dict[str, Any]:
  """`clip` cropped at `box` = (top, left, height, width) in pixels and
  resized back to its H x W (the module docstring says how, per field).

  Raises:
    ValueError: a `flow` in the contract's colours (not rescalable).
  """
  if targets.FLOW.field in clip:
    raise ValueError("the contract's 'flow' cannot be cropped (its colours "
                     "do not rescale): crop 'backward_flow', then "
                     'flow_depth.to_contract')
  height, width = np.shape(clip['video'])[1:3]
  top, left, crop_h, crop_w = box
  rows = _bilinear(top, crop_h, height, height)
  cols = _bilinear(left, crop_w, width, width)
  out = dict(clip)
  for field, value in clip.items():
    if field == 'video':
      frames = _resize(np.asarray(value, np.float32), rows, cols)
      out[field] = np.clip(np.round(frames), 0, 255).astype(np.uint8)
    elif field == 'segmentations':
      value = np.asarray(value)
      out[field] = value[:, _nearest(top, crop_h, height)[:, None],
                         _nearest(left, crop_w, width)[None, :]]
    elif field == 'boxes':
      out[field] = crop_boxes(np.asarray(value, np.float32), box,
                              (height, width))
    elif field in _FLOWS:
      flow = _resize(np.asarray(value, np.float32), rows, cols)
      out[field] = flow_depth.rescale_flow(flow, (height / crop_h,
                                                  width / crop_w))
    elif field == targets.DEPTH.field:
      distance = np.expm1(np.asarray(value, np.float32))
      out[field] = targets.log_plus_depth(
          np.maximum(_resize(distance, rows, cols), 0.0))
  return out


def crop_boxes(boxes: np.ndarray, box: tuple[int, int, int, int],
               size: tuple[int, int]) -> np.ndarray:
  """Normalised (ymin, xmin, ymax, xmax) boxes [..., 4] of a frame of
  `size` (H, W) in the crop `box` = (top, left, height, width): moved,
  scaled, clipped to [0, 1]; a box with no area left is the no-track box
  (SAVi's crop_or_pad_boxes), and no-track boxes stay."""
  top, left, crop_h, crop_w = box
  height, width = size
  scale = np.asarray([height, width, height, width], np.float32)
  offset = np.asarray([top, left, top, left], np.float32)
  extent = np.asarray([crop_h, crop_w, crop_h, crop_w], np.float32)
  moved = np.clip((boxes * scale - offset) / extent, 0.0, 1.0)
  kept = np.all(moved[..., 2:] - moved[..., :2] > 0, axis=-1, keepdims=True)
  moved = np.where(kept, moved, np.float32(0.0))
  untracked = np.all(boxes == np.asarray(NO_TRACK_BOX, np.float32), axis=-1,
                     keepdims=True)
  return np.where(untracked, boxes, moved).astype(np.float32)


def _bilinear(start: int, length: int, size: int, out: int) -> np.ndarray:
  """float32 [out, size]: row i reads the crop [start, start + length) of a
  `size` axis at its half-pixel centre (i + 0.5) * length / out - 0.5,
  clamped to the crop."""
  position = (np.arange(out) + 0.5) * (length / out) - 0.5
  position = np.clip(position, 0.0, length - 1)
  lower = np.floor(position).astype(np.int64)
  upper = np.minimum(lower + 1, length - 1)
  fraction = (position - lower).astype(np.float32)
  weights = np.zeros((out, size), np.float32)
  np.add.at(weights, (np.arange(out), start + lower), 1.0 - fraction)
  np.add.at(weights, (np.arange(out), start + upper), fraction)
  return weights


def _nearest(start: int, length: int, out: int) -> np.ndarray:
  """int64 [out]: the crop pixel each output pixel takes (half-pixel
  centres, as tf.image.resize's nearest neighbour)."""
  index = np.floor((np.arange(out) + 0.5) * (length / out)).astype(np.int64)
  return start + np.minimum(index, length - 1)


def _resize(values: np.ndarray, rows: np.ndarray, cols: np.ndarray
            ) -> np.ndarray:
  """float32 [T, H, W, C] through the row and column weights."""
  return np.einsum('ih,thwc,jw->tijc', rows, values, cols,
                   optimize=True).astype(np.float32)


def from_config(section: Any) -> RandomResizedCrop | None:
  """The crop `config.savi.random_resized_crop` asks for; None: off (or a
  config from before the field)."""
  if section is None or not section.get('enabled', False):
    return None
  return RandomResizedCrop(
      min_object_covered=float(section.min_object_covered),
      aspect_ratio_range=tuple(float(v) for v in section.aspect_ratio_range),
      area_range=tuple(float(v) for v in section.area_range),
      max_attempts=int(section.max_attempts))


def config_problems(section: Any, name: str) -> list[str]:
  """One line per bad setting of a crop section (`name` its place in the
  config); none for a config without it."""
  if section is None:
    return []
  problems = []

  def number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)

  if not isinstance(section.get('enabled'), bool):
    problems.append(f'{name}.enabled must be True or False, got '
                    f'{section.get("enabled")!r}')
  covered = section.get('min_object_covered')
  if not (number(covered) and 0.0 <= covered <= 1.0):
    problems.append(f'{name}.min_object_covered must be in [0, 1], got '
                    f'{covered!r}')
  for field, most in (('aspect_ratio_range', None), ('area_range', 1.0)):
    value = section.get(field)
    if not (isinstance(value, (tuple, list)) and len(value) == 2
            and all(number(v) for v in value)
            and 0.0 < value[0] <= value[1]
            and (most is None or value[1] <= most)):
      bound = '' if most is None else f' <= {most:g}'
      problems.append(f'{name}.{field} must be (low, high) with 0 < low <= '
                      f'high{bound}, got {value!r}')
  attempts = section.get('max_attempts')
  if not (isinstance(attempts, int) and not isinstance(attempts, bool)
          and attempts >= 1):
    problems.append(f'{name}.max_attempts must be an integer >= 1, got '
                    f'{attempts!r}')
  return problems
