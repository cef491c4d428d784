"""The pure training step (jitted by the caller) and parameter init.

The losses live in `losses.py`, inference in `inference.py`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import optax

from slotformer_jax.train.state import TrainState

Batch = dict[str, jax.Array]
Metrics = dict[str, jax.Array]
# loss_fn(params, batch, frozen_params, rng) -> (loss, metrics)
LossFn = Callable[[Any, Batch, Any, jax.Array], tuple[jax.Array, Metrics]]


def train_step(state: TrainState, batch: Batch, frozen_params: Any, *,
               loss_fn: LossFn, optimizer: optax.GradientTransformation,
               seed: int | jax.Array, rng_stream: int | None = None
               ) -> tuple[TrainState, Metrics]:
  """One optimiser update. The step's RNG is derived from (seed, step), or
  from (seed, rng_stream, step): it drives dropout and every sample the loss
  draws (slot noise, ...)."""
  key = jax.random.key(seed)
  if rng_stream is not None:
    key = jax.random.fold_in(key, rng_stream)
  rng = jax.random.fold_in(key, state.step)
  grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
  (loss, metrics), grads = grad_fn(state.params, batch, frozen_params, rng)
  updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
  params = optax.apply_updates(state.params, updates)
  metrics = dict(metrics, loss=loss, grad_norm=optax.tree.norm(grads),
                 param_norm=optax.tree.norm(params))
  return TrainState(step=state.step + 1, params=params,
                    opt_state=opt_state), metrics


def init_params(module: nn.Module, rng: jax.Array, *args, **kwargs) -> Any:
  """Parameters of `module` for example inputs (all RNG streams from rng)."""
  params_rng, sample_rng, dropout_rng = jax.random.split(rng, 3)
  return module.init(
      {'params': params_rng, 'sample': sample_rng, 'dropout': dropout_rng},
      *args, **kwargs)['params']
