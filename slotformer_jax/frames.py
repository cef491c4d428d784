"""Pixel ranges at the model boundary, and labelled pictures of frames
(slot-mask overlays, rows of frames with their labels), shared by the
TensorBoard summaries, the pictures and the run explorer.

Frames arrive as uint8 and are mapped to [-1, 1] on device, the range the
official models were trained in (MSE values and the loss weight lambda are
in that scale).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image
from PIL import ImageDraw


def frames_to_model(frames: jax.Array) -> jax.Array:
  """uint8 [..., 3] in [0, 255] -> float32 in [-1, 1]."""
  return frames.astype(jnp.float32) / 127.5 - 1.0


def model_to_unit(frames: jax.Array) -> jax.Array:
  """Model output in [-1, 1] -> [0, 1], clipped."""
  return jnp.clip((frames + 1.0) * 0.5, 0.0, 1.0)


def labelled_rows(strips: Mapping[str, np.ndarray], label_width: int
                  ) -> np.ndarray:
  """{label: uint8 [h, w, 3] strip} -> uint8 [R * h, label_width + w, 3]:
  the strips stacked on white, each label written at its row's left."""
  height = max(s.shape[0] for s in strips.values())
  width = max(s.shape[1] for s in strips.values())
  canvas = Image.new('RGB', (label_width + width, height * len(strips)),
                     (255, 255, 255))
  draw = ImageDraw.Draw(canvas)
  for i, (label, strip) in enumerate(strips.items()):
    canvas.paste(Image.fromarray(strip), (label_width, i * height))
    draw.text((3, i * height + height // 2 - 5), label, fill=(0, 0, 0))
  return np.asarray(canvas)


# Slot colours of the segmentation overlays (slot k: SLOT_COLOURS[k % 10]).
SLOT_COLOURS = np.array([[230, 25, 75], [60, 180, 75], [255, 225, 25],
                         [0, 130, 200], [245, 130, 48], [145, 30, 180],
                         [70, 240, 240], [240, 50, 230], [210, 245, 60],
                         [250, 190, 212]], np.float32) / 255.0


def mask_overlay(frames: np.ndarray, alpha_masks: np.ndarray) -> np.ndarray:
  """frames [..., H, W, 3] in [0, 1], alpha_masks [..., N, H, W] -> the
  frames half-tinted by each pixel's argmax slot colour."""
  ids = np.argmax(alpha_masks, axis=-3)
  return 0.5 * frames + 0.5 * SLOT_COLOURS[ids % len(SLOT_COLOURS)]


def to_uint8(frames: Any) -> np.ndarray:
  """Frames in [0, 1] -> uint8."""
  return (np.clip(np.asarray(frames, np.float32), 0.0, 1.0) * 255 + 0.5
          ).astype(np.uint8)


# Room for a row label at the left of a grid of frames.
GRID_LABEL_WIDTH = 96


def labelled_grid(rows: Mapping[str, np.ndarray], scale: int = 2
                  ) -> np.ndarray:
  """{row label: uint8 [T, H, W, 3]} -> uint8 [R * H', L + T * W', 3]: one
  row of frames per entry, its label written at the left (H' = scale * H)."""
  strips = {}
  for label, row in rows.items():
    row = np.asarray(row)
    if scale > 1:
      row = row.repeat(scale, axis=1).repeat(scale, axis=2)
    strips[label] = np.concatenate(list(row), axis=1)
  return labelled_rows(strips, GRID_LABEL_WIDTH)
