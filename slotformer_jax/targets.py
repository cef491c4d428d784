"""What a slot model reconstructs: its targets, the batch field and range of
each, and how each is drawn.

SlotFormer's SAVi reconstructs RGB frames, SAVi's MOVi models optical flow
rendered as colour, SAVi++ flow and depth. ``config.savi.targets`` names
them; the decoder has one readout head per target and the loss one term per
target (``losses.savi_loss``). The data contract (the data side makes them;
each is compared as it arrives):

  rgb    'video'  uint8 [B, T, H, W, 3] in [0, 255] (the model: [-1, 1])
  flow   'flow'   float32 [B, T, H, W, 3] in [-1, 1]: `flow_to_rgb` of the
                  backward flow, in pixels of the delivered H x W
  depth  'depth'  float32 [B, T, H, W, 1] >= 0: `log_plus_depth` of the
                  distance from the camera

Details and the official configs: docs/savi_plus_plus.md.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import dataclasses
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class Target:
  """One reconstruction target.

  Attributes:
    name: its name in `config.savi.targets` and in the loss metrics
      (`recon_loss_<name>`).
    channels: C, the decoder's readout channels for it.
    field: the batch field holding it.
    label: how pictures name it.
  """

  name: str
  channels: int
  field: str
  label: str


RGB = Target('rgb', 3, 'video', 'frames')
FLOW = Target('flow', 3, 'flow', 'flow')
DEPTH = Target('depth', 1, 'depth', 'depth')
TARGETS: dict[str, Target] = {t.name: t for t in (RGB, FLOW, DEPTH)}
NAMES = tuple(TARGETS)
# What a config without `savi.targets` (a workdir made before the field)
# reconstructs: RGB frames, as every model before it.
DEFAULT = (RGB.name,)

# SAVi's flow colouring: a displacement of hypot(H, W) / 50 pixels or more
# is fully saturated (`flow_tensor_to_rgb_tensor(flow_scaling_factor=50)`).
FLOW_SCALING = 50.0


def of(names: Sequence[str] | None) -> tuple[Target, ...]:
  """The targets named (in order); None: `DEFAULT`.

  Raises:
    ValueError: an unknown name, a repeated one, or none.
  """
  names = DEFAULT if names is None else tuple(names)
  unknown = [n for n in names if n not in TARGETS]
  if unknown or not names or len(set(names)) != len(names):
    raise ValueError(f'targets must be a non-empty selection of {NAMES}, '
                     f'each once, got {names!r}')
  return tuple(TARGETS[n] for n in names)


def besides_frames(slot_model: Any) -> list[Target]:
  """The targets other than the frames a slot model reconstructs (a SAVi's
  flow / depth; none for the others), the ones pictures draw in rows of
  their own."""
  return [t for t in getattr(slot_model, 'targets', ()) if t != RGB]


def channels(names: Sequence[str] | None) -> tuple[tuple[str, int], ...]:
  """((name, channels), ...) of the targets named: what the decoder reads
  out (`SpatialBroadcastDecoder.targets`)."""
  return tuple((t.name, t.channels) for t in of(names))


def flow_to_rgb(flow: np.ndarray) -> np.ndarray:
  """Optical flow -> SAVi's colour picture of it, in [-1, 1].

  flow [..., H, W, >=2] float (channel 0: delta row, 1: delta column, in
  pixels; further channels are ignored, as SAVi does) -> float32 [..., H, W,
  3]. Hue is the angle atan2(channel 1, channel 0) mapped to [0, 1],
  saturation the length times FLOW_SCALING / hypot(H, W) clipped to 1,
  value 1: still pixels are white, and the colour wheel is SAVi's. SAVi
  rounds the picture to 8 bits before using it; here it stays float.
  """
  flow = np.asarray(flow, np.float32)
  height, width = flow.shape[-3:-1]
  first, second = flow[..., 0], flow[..., 1]
  hue = (np.arctan2(second, first) / np.pi + 1.0) / 2.0
  scale = FLOW_SCALING / np.hypot(height, width)
  saturation = np.clip(np.hypot(first, second) * scale, 0.0, 1.0)
  return hsv_to_rgb(hue, saturation) * 2.0 - 1.0


def hsv_to_rgb(hue: np.ndarray, saturation: np.ndarray) -> np.ndarray:
  """HSV with value 1 -> float32 RGB [..., 3] in [0, 1] (hue, saturation in
  [0, 1]; hue 0 and 1 are red)."""
  sector = hue[..., None] * 6.0
  offsets = np.array([5.0, 3.0, 1.0], np.float32)  # R, G, B
  k = np.mod(offsets + sector, 6.0)
  ramp = np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
  return (1.0 - saturation[..., None] * ramp).astype(np.float32)


def log_plus_depth(depth: np.ndarray) -> np.ndarray:
  """Depth -> SAVi's 'log_plus' transform, log(1 + depth), float32 (the
  same shape; depth >= 0)."""
  return np.log1p(np.asarray(depth, np.float32)).astype(np.float32)


def depth_range(depth: np.ndarray) -> tuple[float, float]:
  """(low, high) of a depth picture's values, for drawing it and its
  prediction on one grey scale (high > low)."""
  depth = np.asarray(depth, np.float32)
  low, high = float(np.min(depth)), float(np.max(depth))
  return low, max(high, low + 1e-6)


def grey_scale(target: Target, values: np.ndarray
               ) -> tuple[float, float] | None:
  """The scale a target is drawn on: depth's `depth_range` of `values`;
  None for the colour targets (frames, flow)."""
  return depth_range(values) if target.channels == 1 else None


def labelled(text: str, value_range: tuple[float, float] | None,
             separator: str = ' ') -> str:
  """A row label with a grey scale's range ('depth 2.1..3.1') when it has
  one."""
  if value_range is None:
    return text
  return f'{text}{separator}{value_range[0]:.2g}..{value_range[1]:.2g}'


def picture(target: Target, values: np.ndarray,
            value_range: tuple[float, float] | None = None) -> np.ndarray:
  """A target's values in its data range -> float32 RGB [..., H, W, 3] in
  [0, 1] to draw: frames and flow as they are coloured, depth as a grey map
  from `value_range` (low: black, high: white; default: its own range)."""
  values = np.asarray(values, np.float32)
  if target.channels == 1:
    low, high = value_range or depth_range(values)
    grey = np.clip((values - low) / (high - low), 0.0, 1.0)
    return np.repeat(grey, 3, axis=-1)
  return np.clip((values + 1.0) * 0.5, 0.0, 1.0)


def picture_rows(targets: Sequence[Target], truth: Mapping[str, np.ndarray],
                 decoded: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
  """{row label: float RGB [T, H, W, 3] in [0, 1]}: for every target other
  than RGB, its data (when `truth` has it) and its reconstruction, a depth
  pair on the data's grey scale, labelled with that scale's range."""
  rows = {}
  for target in targets:
    if target.name == RGB.name:
      continue
    value_range = grey_scale(
        target, truth.get(target.name, decoded[target.name]))
    label = labelled(target.label, value_range)
    if target.name in truth:
      rows[label] = picture(target, truth[target.name], value_range)
    rows[f'{target.label} recon.'] = picture(target, decoded[target.name],
                                             value_range)
  return rows
