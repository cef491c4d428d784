"""The training state: a plain pytree, so it checkpoints and shards as is."""

from __future__ import annotations

from typing import Any

from flax import struct
import jax
import jax.numpy as jnp
import optax


@struct.dataclass
class TrainState:
  """step: int32 scalar (number of updates applied); params; opt_state."""

  step: jax.Array
  params: Any
  opt_state: Any

  @classmethod
  def create(cls, params: Any, optimizer: optax.GradientTransformation
             ) -> TrainState:
    return cls(step=jnp.zeros((), jnp.int32), params=params,
               opt_state=optimizer.init(params))
