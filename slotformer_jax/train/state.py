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


@struct.dataclass
class SeedsState(TrainState):
  """The TrainStates of K seeds stacked on a leading axis (step: int32 [K],
  every leaf of params / opt_state [K, ...]), checkpointed as one state.

  diverged_at: int32 [K]; 0 while seed k trains, else the update in which
  its loss or parameters became non-finite (its parameters and optimiser
  state stay those from before that update).
  """

  diverged_at: jax.Array

  @classmethod
  def stack(cls, states: list[TrainState]) -> SeedsState:
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *states)
    return cls(step=stacked.step, params=stacked.params,
               opt_state=stacked.opt_state,
               diverged_at=jnp.zeros((len(states),), jnp.int32))

  def train_state(self) -> TrainState:
    """The stacked TrainState without `diverged_at`."""
    return TrainState(step=self.step, params=self.params,
                      opt_state=self.opt_state)

  def seed(self, index: int) -> TrainState:
    """Seed `index`'s TrainState (as the one-seed run would hold it)."""
    return jax.tree.map(lambda x: x[index], self.train_state())
