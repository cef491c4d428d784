"""STEVE's losses and steps (jitted by the caller): dVAE reconstruction with
an annealed Gumbel-softmax temperature, STEVE's token cross-entropy.

Both plug into `train.trainer.fit` through the usual
`loss_fn(params, batch, frozen_params, rng)`. The dVAE's temperature depends
on the step, which `loss_fn` does not see: the batch carries it
(`gumbel_temperature` [B], every entry the same), computed on the host from
the step the batch is for (see `with_gumbel_temperature`).
"""

from __future__ import annotations

from collections.abc import Iterator
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from slotformer_jax import steve_inference
from slotformer_jax.frames import frames_to_model
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.steve import STEVE

Batch = dict[str, jax.Array]
Metrics = dict[str, jax.Array]


def cosine_anneal(step: int, start_value: float, final_value: float,
                  num_steps: int) -> float:
  """start_value at step 0 -> final_value at `num_steps` along half a cosine;
  final_value from then on."""
  if step >= num_steps:
    return final_value
  progress = step / num_steps
  return final_value + 0.5 * (start_value - final_value) * (
      1.0 + math.cos(math.pi * progress))


def gumbel_temperature(step: int, num_train_steps: int, *,
                       start: float = 1.0, final: float = 0.1,
                       anneal_fraction: float = 0.15) -> float:
  """The dVAE's temperature at `step`: 1.0 -> 0.1 over the first 15% of the
  steps (the official Physion dVAE), then constant."""
  anneal_steps = max(1, int(anneal_fraction * num_train_steps))
  return cosine_anneal(step, start, final, anneal_steps)


def with_gumbel_temperature(batches: Iterator[dict[str, np.ndarray]],
                            start_step: int, num_train_steps: int,
                            **schedule) -> Iterator[dict[str, np.ndarray]]:
  """Adds `gumbel_temperature` float32 [B] of each batch's step."""
  step = start_step
  for batch in batches:
    size = len(next(iter(batch.values())))
    temperature = gumbel_temperature(step, num_train_steps, **schedule)
    yield dict(batch, gumbel_temperature=np.full(size, temperature,
                                                 np.float32))
    step += 1


def dvae_loss(params: Any, batch: Batch, frozen_params: Any, rng: jax.Array,
              *, model: DVAE) -> tuple[jax.Array, Metrics]:
  """Pixel MSE of the relaxed-code reconstruction.

  batch['video']: uint8 [B, T, H, W, 3] (single frames: T = 1);
  batch['gumbel_temperature']: float32 [B].
  """
  del frozen_params
  video = frames_to_model(batch['video'])
  images = video.reshape(-1, *video.shape[2:])
  temperature = jnp.mean(batch['gumbel_temperature'])
  recon, log_probs = model.apply({'params': params}, images, temperature,
                                 rngs={'gumbel': rng})
  loss = jnp.mean(jnp.square(recon - images))
  # How many codes the encoder uses: exp(entropy of the mean code
  # distribution), a quick check for codebook collapse.
  mean_probs = jnp.mean(jnp.exp(log_probs), axis=(0, 1, 2))
  perplexity = jnp.exp(-jnp.sum(mean_probs * jnp.log(mean_probs + 1e-10)))
  return loss, {'recon_loss': loss, 'gumbel_temperature': temperature,
                'code_perplexity': perplexity}


def steve_loss(params: Any, batch: Batch, frozen_params: Any, rng: jax.Array,
               *, model: STEVE) -> tuple[jax.Array, Metrics]:
  """Cross-entropy of the decoder's token logits against the frozen dVAE's
  tokens, averaged over batch, frames and tokens.

  batch['video']: uint8 [B, T, H, W, 3]; batch['tokens']: int [B, T, L]
  (precomputed argmax codes of the same frames).
  """
  del frozen_params
  video = frames_to_model(batch['video'])
  tokens = batch['tokens'].astype(jnp.int32)
  logits, _, _ = model.apply({'params': params}, video, tokens,
                             deterministic=False, rngs={'dropout': rng})
  loss = jnp.mean(optax.softmax_cross_entropy_with_integer_labels(
      logits, tokens))
  accuracy = jnp.mean(jnp.argmax(logits, -1) == tokens)
  return loss, {'token_loss': loss, 'token_accuracy': accuracy}


# Kept under its old name; the implementation lives with inference.
steve_encode = steve_inference.steve_encode
