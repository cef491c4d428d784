"""Optical flow and depth: how datasets store them, and how a source serves
them as the slot models' targets (`slotformer_jax/targets.py`'s contract).

Stored in Kubric's MOVi encoding: ``forward_flow`` / ``backward_flow``
uint16 [T, H, W, 2] and ``depth`` uint16 [T, H, W, 1], each with its
per-video ``<name>_range`` float32 [2]; value = stored / 65535 *
(high - low) + low. Flows are (delta row, delta column) in pixels; depth
is the distance from the camera centre.

Served (:func:`serve`, applied by ``Dataset.open`` to a folder storing
them, per clip at read time): ``flow`` float32 [T, H, W, 3] in [-1, 1]
(`targets.flow_to_rgb` of the backward flow), ``depth`` float32
[T, H, W, 1] (`targets.log_plus_depth`), and both flows decoded in pixels
(what data/augment.py rescales). The conventions in full:
docs/datasets.md, "Optical flow and depth".
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from slotformer_jax import targets

UINT16_MAX = 65535
FORWARD_FLOW = 'forward_flow'
BACKWARD_FLOW = 'backward_flow'
DEPTH = 'depth'
# The stored fields with their channels, each with '<name>_range'.
STORED: Mapping[str, int] = {FORWARD_FLOW: 2, BACKWARD_FLOW: 2, DEPTH: 1}
# What each served field is made of: the stored fields it reads.
_SOURCES: Mapping[str, str] = {
    targets.FLOW.field: BACKWARD_FLOW, targets.DEPTH.field: DEPTH,
    BACKWARD_FLOW: BACKWARD_FLOW, FORWARD_FLOW: FORWARD_FLOW}
# Ranges a stored file may state: flows within +-2^20 pixels, depth within
# [0, 2^20] scene units (MOVi's: flows of a few hundred pixels, depths of a
# few tens of units; the embedded scenes': a few pixels and units).
MAX_MAGNITUDE = float(1 << 20)


def range_field(name: str) -> str:
  """The field holding the range of stored field `name`."""
  return f'{name}_range'


def stored_in(fields: Iterable[str]) -> tuple[str, ...]:
  """The stored fields (with their ranges) among `fields`, in STORED's
  order."""
  fields = set(fields)
  return tuple(name for name in STORED
               if name in fields and range_field(name) in fields)


def served_fields(fields: Iterable[str]) -> tuple[str, ...]:
  """The fields a source serves when its folder holds `fields`: the ranges
  are consumed, `flow` added with a backward flow."""
  fields = tuple(fields)
  kept = stored_in(fields)
  out = [f for f in fields if f not in {range_field(k) for k in kept}]
  if BACKWARD_FLOW in kept:
    out.append(targets.FLOW.field)
  return tuple(out)


# ----------------------------------------------------------------------------
# The encoding
# ----------------------------------------------------------------------------


def check_range(value_range: Any, name: str, *, what: str) -> np.ndarray:
  """A stored range as float32 [2], checked: finite, low <= high, within
  +-MAX_MAGNITUDE (a depth's low >= 0).

  Raises:
    ValueError: one line naming `what` (the file) and the field.
  """
  values = np.asarray(value_range)
  if values.shape != (2,) or values.dtype.kind != 'f':
    raise ValueError(f'{what}: {range_field(name)} is {values.dtype} '
                     f'{values.shape}, not float32 (2,) (low, high)')
  low, high = (float(v) for v in values)
  lowest = 0.0 if name == DEPTH else -MAX_MAGNITUDE
  if not (np.isfinite(low) and np.isfinite(high) and lowest <= low <= high
          <= MAX_MAGNITUDE):
    raise ValueError(
        f'{what}: {range_field(name)} is [{low:.6g}, {high:.6g}], not a '
        f'range {lowest:g} <= low <= high <= {MAX_MAGNITUDE:g}')
  return values.astype(np.float32)


def decode(stored: np.ndarray, value_range: Any) -> np.ndarray:
  """uint16 values and their (low, high) -> float32 (Kubric's decoding)."""
  low, high = (np.float32(v) for v in np.asarray(value_range, np.float32))
  return (np.asarray(stored, np.float32) * ((high - low) / UINT16_MAX)
          + low).astype(np.float32)


def encode(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """float values -> (uint16 values, float32 [2] range (min, max)), the
  encoding `decode` undoes to within about half a step (the range is
  rounded to float32; a constant map: every value 0, range (v, v))."""
  values = np.asarray(values, np.float64)
  if not np.all(np.isfinite(values)):
    raise ValueError('flow / depth to encode holds NaN or infinity')
  low, high = ((float(values.min()), float(values.max())) if values.size
               else (0.0, 0.0))
  value_range = np.asarray([low, high], np.float32)
  low, high = (float(v) for v in value_range)  # as stored
  if high <= low:
    return np.zeros(values.shape, np.uint16), value_range
  scaled = np.round((values - low) / (high - low) * UINT16_MAX)
  return np.clip(scaled, 0, UINT16_MAX).astype(np.uint16), value_range


def rescale_flow(flow: np.ndarray, scale: Sequence[float]) -> np.ndarray:
  """Flow [..., 2] (delta row, delta column) in pixels of a frame resized
  by (row scale, column scale): each component times its scale, as SAVi's
  resize and crop ops rescale it."""
  flow = np.asarray(flow, np.float32)
  return flow * np.asarray(scale, np.float32)


def to_contract(clip: Mapping[str, Any]) -> dict[str, Any]:
  """Decoded fields -> the targets' contract: `backward_flow` (pixels)
  becomes `flow` = flow_to_rgb of it (at the clip's resolution); a `depth`
  already served is kept. Other fields pass through."""
  out = dict(clip)
  if BACKWARD_FLOW in out and targets.FLOW.field not in out:
    out[targets.FLOW.field] = targets.flow_to_rgb(out.pop(BACKWARD_FLOW))
  return out


# ----------------------------------------------------------------------------
# Serving them
# ----------------------------------------------------------------------------


class FlowDepthSource:
  """A video source whose stored flows and depth are served decoded (the
  module docstring): `flow` and `depth` in the targets' contract,
  `backward_flow` / `forward_flow` in pixels; the ranges are consumed.
  Clips read only what they need (the stored fields of the requested ones,
  and the video's header for their ranges)."""

  def __init__(self, source: Any, stored: Sequence[str]):
    self.source = source
    self.stored = tuple(stored)

  def __len__(self) -> int:
    return len(self.source)

  def _decode(self, raw: Mapping[str, Any], header: Mapping[str, Any],
              fields: Sequence[str], index: int) -> dict[str, np.ndarray]:
    out = {}
    for field in fields:
      name = _SOURCES[field]
      value = decode(raw[name], check_range(
          header[range_field(name)], name,
          what=f'video {index}'))
      if field == targets.FLOW.field:
        value = targets.flow_to_rgb(value)
      elif field == targets.DEPTH.field:
        value = targets.log_plus_depth(value)
      out[field] = value
    return out

  def _served(self, field: str) -> bool:
    return field in _SOURCES and _SOURCES[field] in self.stored

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    item = dict(self.source[index])
    fields = [f for f in (*self.stored, targets.FLOW.field)
              if self._served(f)]
    decoded = self._decode(item, item, fields, index)
    for name in self.stored:
      item.pop(range_field(name), None)
    item.update(decoded)
    return item

  @property
  def supports_clips(self) -> bool:
    return bool(getattr(self.source, 'supports_clips', False))

  @property
  def time_fields(self) -> tuple[str, ...]:
    have = tuple(getattr(self.source, 'time_fields', ()))
    extra = (targets.FLOW.field,) if BACKWARD_FLOW in self.stored else ()
    return have + tuple(f for f in extra if f not in have)

  def num_frames(self, index: int) -> int:
    return self.source.num_frames(index)

  def clip(self, index: int, start: int, length: int, stride: int = 1,
           fields: Sequence[str] = ('video',)) -> dict[str, np.ndarray]:
    """As the source's clip, with the served fields decoded."""
    fields = tuple(fields)
    served = [f for f in fields if self._served(f)]
    if not served:
      return self.source.clip(index, start, length, stride, fields)
    stored = sorted({_SOURCES[f] for f in served})
    others = [f for f in fields if f not in served]
    raw = self.source.clip(index, start, length, stride,
                           tuple(others) + tuple(
                               s for s in stored if s not in others))
    header = self.source.header(index)
    out = dict(raw)
    out.update(self._decode(raw, header, served, index))
    return {field: out[field] for field in fields}

  def header(self, index: int) -> dict[str, Any]:
    header = dict(self.source.header(index))
    for name in self.stored:
      header.pop(range_field(name), None)
    return header

  def __repr__(self) -> str:
    return f'FlowDepthSource({self.source!r}, {", ".join(self.stored)})'


def serve(source: Any, fields: Iterable[str]) -> Any:
  """`source` serving its stored flows and depth decoded (a
  `FlowDepthSource`), or `source` itself when `fields` (what its folder
  holds) has none: a folder without them reads exactly as before."""
  stored = stored_in(fields)
  return FlowDepthSource(source, stored) if stored else source
