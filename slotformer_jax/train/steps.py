"""The pure training step (jitted by the caller) and parameter init.

The losses live in `losses.py`, inference in `inference.py`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from slotformer_jax.train.state import SeedsState
from slotformer_jax.train.state import TrainState

Batch = dict[str, jax.Array]
Metrics = dict[str, jax.Array]
# loss_fn(params, batch, frozen_params, rng) -> (loss, metrics)
LossFn = Callable[[Any, Batch, Any, jax.Array], tuple[jax.Array, Metrics]]


def train_step(state: TrainState, batch: Batch, frozen_params: Any, *,
               loss_fn: LossFn, optimizer: optax.GradientTransformation,
               seed: int | jax.Array) -> tuple[TrainState, Metrics]:
  """One optimiser update. The step's RNG is derived from (seed, step): it
  drives dropout and every sample the loss draws (slot noise, ...)."""
  rng = jax.random.fold_in(jax.random.key(seed), state.step)
  grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
  (loss, metrics), grads = grad_fn(state.params, batch, frozen_params, rng)
  updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
  params = optax.apply_updates(state.params, updates)
  metrics = dict(metrics, loss=loss, grad_norm=optax.tree.norm(grads),
                 param_norm=optax.tree.norm(params))
  return TrainState(step=state.step + 1, params=params,
                    opt_state=opt_state), metrics


def seeds_train_step(state: SeedsState, batch: Batch, frozen_params: Any,
                     seeds: jax.Array, *, loss_fn: LossFn,
                     optimizer: optax.GradientTransformation,
                     per_seed_batches: bool = False,
                     per_seed_frozen: bool = False, loop: str = 'vmap'
                     ) -> tuple[SeedsState, Metrics]:
  """`train_step` of K seeds at once, in one program.

  `loop`: 'vmap' batches the K steps into one (wider kernels: what fills an
  accelerator); 'unroll' writes the one-seed step K times into the program
  (the one-seed kernels, what suits XLA:CPU; K times the compile time).
  `jax.lax.map` (a loop in the program) ran 2.8-5.4x slower than K
  one-seed steps on XLA:CPU, so it is not offered.

  Args:
    state: K TrainStates stacked ([K, ...] leaves).
    batch: one batch every seed sees ([B, ...]), or with `per_seed_batches`
      one per seed ([K, B, ...]).
    frozen_params: shared by every seed, or with `per_seed_frozen` one
      tree per seed ([K, ...] leaves; seed k's SlotFormer decodes L_I with
      stage-1 seed k's decoder).
    seeds: int32 [K]; seed k's step RNG is train_step's for seeds[k].

  Returns:
    (state, metrics [K] each). A seed whose loss or updated parameters are
    non-finite keeps its state from before the update, and `diverged_at`
    records the update (an already diverged seed stays as it is).
  """
  def one(train_state, seed, seed_batch, seed_frozen):
    return train_step(train_state, seed_batch, seed_frozen,
                      loss_fn=loss_fn, optimizer=optimizer, seed=seed)

  def pick(tree, k, per_seed):
    return jax.tree.map(lambda x: x[k], tree) if per_seed else tree

  if loop == 'vmap':
    new, metrics = jax.vmap(one, in_axes=(
        0, 0, 0 if per_seed_batches else None,
        0 if per_seed_frozen else None)
    )(state.train_state(), seeds, batch, frozen_params)
  elif loop == 'unroll':
    stacked = state.train_state()
    outs = [one(pick(stacked, k, True), seeds[k],
                pick(batch, k, per_seed_batches),
                pick(frozen_params, k, per_seed_frozen))
            for k in range(seeds.shape[0])]
    new, metrics = jax.tree.map(lambda *xs: jnp.stack(xs), *outs)
  else:
    raise ValueError(f"loop must be 'vmap' or 'unroll', got {loop!r}")
  training = state.diverged_at == 0
  keep = training & jnp.isfinite(metrics['loss']) & jnp.isfinite(
      metrics['param_norm'])

  def select(updated, old):
    return jnp.where(keep.reshape((-1,) + (1,) * (updated.ndim - 1)),
                     updated, old)

  return SeedsState(
      step=new.step,
      params=jax.tree.map(select, new.params, state.params),
      opt_state=jax.tree.map(select, new.opt_state, state.opt_state),
      diverged_at=jnp.where(training & ~keep, new.step, state.diverged_at),
  ), metrics


def init_params(module: nn.Module, rng: jax.Array, *args, **kwargs) -> Any:
  """Parameters of `module` for example inputs (all RNG streams from rng)."""
  params_rng, sample_rng, dropout_rng = jax.random.split(rng, 3)
  return module.init(
      {'params': params_rng, 'sample': sample_rng, 'dropout': dropout_rng},
      *args, **kwargs)['params']
