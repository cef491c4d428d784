"""Pure training and inference steps (jitted by the caller).

Frames arrive as uint8 and are mapped to [-1, 1] on device, the range the
official models were trained in (MSE values and the loss weight lambda are
in that scale).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.modules.slot_lstm import SlotLSTM
from slotformer_jax.train.state import TrainState

Batch = dict[str, jax.Array]
Metrics = dict[str, jax.Array]
# loss_fn(params, batch, frozen_params, rng) -> (loss, metrics)
LossFn = Callable[[Any, Batch, Any, jax.Array], tuple[jax.Array, Metrics]]


def frames_to_model(frames: jax.Array) -> jax.Array:
  """uint8 [..., 3] in [0, 255] -> float32 in [-1, 1]."""
  return frames.astype(jnp.float32) / 127.5 - 1.0


def model_to_unit(frames: jax.Array) -> jax.Array:
  """Model output in [-1, 1] -> [0, 1], clipped."""
  return jnp.clip((frames + 1.0) * 0.5, 0.0, 1.0)


def train_step(state: TrainState, batch: Batch, frozen_params: Any, *,
               loss_fn: LossFn, optimizer: optax.GradientTransformation,
               seed: int) -> tuple[TrainState, Metrics]:
  """One optimiser update. The step's RNG is derived from (seed, step)."""
  rng = jax.random.fold_in(jax.random.key(seed), state.step)
  grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
  (loss, metrics), grads = grad_fn(state.params, batch, frozen_params, rng)
  updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
  params = optax.apply_updates(state.params, updates)
  metrics = dict(metrics, loss=loss, grad_norm=optax.tree.norm(grads),
                 param_norm=optax.tree.norm(params))
  return TrainState(step=state.step + 1, params=params,
                    opt_state=opt_state), metrics


def savi_loss(params: Any, batch: Batch, frozen_params: Any, rng: jax.Array,
              *, model: SAVi, kl_weight: float) -> tuple[jax.Array, Metrics]:
  """Frame reconstruction MSE (+ kl_weight * KL for stochastic SAVi).

  batch['video']: uint8 [B, T, H, W, 3]. The KL is summed over the slot
  dimensions and averaged over batch, frames and slots.
  """
  del frozen_params
  video = frames_to_model(batch['video'])
  sample_rng, dropout_rng = jax.random.split(rng)
  # deterministic=False: the predictor's dropout (0.1 officially) is on.
  output = model.apply({'params': params}, video, deterministic=False,
                       rngs={'sample': sample_rng, 'dropout': dropout_rng})
  recon_loss = jnp.mean(jnp.square(output.decoded.recon - video))
  kl = jnp.mean(output.kl)
  loss = recon_loss + kl_weight * kl
  return loss, {'recon_loss': recon_loss, 'kl': kl}


def slotformer_loss(params: Any, batch: Batch, decoder_params: Any,
                    rng: jax.Array, *, model: SlotFormer | SlotLSTM,
                    decoder: SpatialBroadcastDecoder, rollout: int,
                    image_loss_weight: float, teacher_forcing: bool
                    ) -> tuple[jax.Array, Metrics]:
  """L = L_S + lambda * L_I on the model's own rollout.

  batch['slots']: float32 [B, burn_in + rollout, N, D];
  batch['video']: uint8 [B, burn_in + rollout, H, W, 3] (needed when
  lambda > 0). L_S is the MSE between predicted and extracted slots, L_I
  the MSE between frames decoded from the predicted slots by the *frozen*
  SAVi decoder and the real frames (both averaged over every element, as the
  official implementation).
  """
  burn_in = model.burn_in
  history = batch['slots'][:, :burn_in]
  target_slots = batch['slots'][:, burn_in:burn_in + rollout]
  predicted = model.apply(
      {'params': params}, history, rollout,
      teacher_slots=target_slots if teacher_forcing else None,
      deterministic=False, rngs={'dropout': rng})
  slot_loss = jnp.mean(jnp.square(predicted - target_slots))
  metrics = {'slot_loss': slot_loss}
  loss = slot_loss
  if image_loss_weight > 0:
    frames = frames_to_model(batch['video'][:, burn_in:burn_in + rollout])
    decoded = decoder.apply({'params': jax.lax.stop_gradient(decoder_params)},
                            predicted)
    image_loss = jnp.mean(jnp.square(decoded.recon - frames))
    metrics['image_loss'] = image_loss
    loss = loss + image_loss_weight * image_loss
  return loss, metrics


def savi_encode(params: Any, video: jax.Array, rng: jax.Array, carry: Any,
                *, model: SAVi):
  """uint8 video [B, T, H, W, 3] -> (slots [B, T, N, D], carry).

  `carry` continues SAVi's state from the previous chunk (None: fresh).
  """
  slots, _, carry = model.apply(
      {'params': params}, frames_to_model(video), carry,
      method=SAVi.encode, rngs={'sample': rng})
  return slots, carry


def decode_slots(decoder_params: Any, slots: jax.Array, *,
                 decoder: SpatialBroadcastDecoder):
  """slots [..., N, D] -> DecodedSlots; `recon` and `rgb` in [0, 1]."""
  decoded = decoder.apply({'params': decoder_params}, slots)
  return decoded.replace(recon=model_to_unit(decoded.recon),
                         rgb=model_to_unit(decoded.rgb))


def rollout_slots(params: Any, burn_in_slots: jax.Array, *,
                  model: SlotFormer | SlotLSTM,
                  num_steps: int) -> jax.Array:
  """[B, burn_in, N, D] -> [B, num_steps, N, D] (deterministic)."""
  return model.apply({'params': params}, burn_in_slots, num_steps)


def copy_last_rollout(burn_in_slots: jax.Array, num_steps: int) -> jax.Array:
  """The copy-last-slots baseline: the last observed slots, repeated."""
  last = burn_in_slots[:, -1:]
  return jnp.repeat(last, num_steps, axis=1)


def init_params(module: nn.Module, rng: jax.Array, *args, **kwargs) -> Any:
  """Parameters of `module` for example inputs (all RNG streams from rng)."""
  params_rng, sample_rng, dropout_rng = jax.random.split(rng, 3)
  return module.init(
      {'params': params_rng, 'sample': sample_rng, 'dropout': dropout_rng},
      *args, **kwargs)['params']
