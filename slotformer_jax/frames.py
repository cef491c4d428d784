"""Pixel ranges at the model boundary.

Frames arrive as uint8 and are mapped to [-1, 1] on device, the range the
official models were trained in (MSE values and the loss weight lambda are
in that scale).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def frames_to_model(frames: jax.Array) -> jax.Array:
  """uint8 [..., 3] in [0, 255] -> float32 in [-1, 1]."""
  return frames.astype(jnp.float32) / 127.5 - 1.0


def model_to_unit(frames: jax.Array) -> jax.Array:
  """Model output in [-1, 1] -> [0, 1], clipped."""
  return jnp.clip((frames + 1.0) * 0.5, 0.0, 1.0)
