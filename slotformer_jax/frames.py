"""Pixel ranges at the model boundary, and labelled pictures of frames.

Frames arrive as uint8 and are mapped to [-1, 1] on device, the range the
official models were trained in (MSE values and the loss weight lambda are
in that scale).
"""

from __future__ import annotations

from collections.abc import Mapping

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
