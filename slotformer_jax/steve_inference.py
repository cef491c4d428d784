"""STEVE inference: frames -> tokens, slots -> tokens -> frames.

Pure functions over parameters (jit them at the call site). Generation is
greedy, all h*w tokens of a frame in raster order, batched over every frame
given; `generate_tokens` keeps a key/value cache inside `lax.scan` (one
token's worth of work per step), `generate_tokens_recomputed` re-runs the
decoder over the whole sequence every step as the official code does (kept
as the reference the cache is tested and timed against).

Frames arrive as uint8 and are mapped to [-1, 1] on device.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.token_decoder import TokenDecoder


def frames_to_model(frames: jax.Array) -> jax.Array:
  """uint8 [..., 3] in [0, 255] -> float32 in [-1, 1]."""
  return frames.astype(jnp.float32) / 127.5 - 1.0


def model_to_unit(frames: jax.Array) -> jax.Array:
  """Model output in [-1, 1] -> [0, 1], clipped."""
  return jnp.clip((frames + 1.0) * 0.5, 0.0, 1.0)


def tokenize(dvae_params: Any, frames: jax.Array, *, dvae: DVAE) -> jax.Array:
  """uint8 frames [..., H, W, 3] -> int32 tokens [..., h * w] (raster order)."""
  lead = frames.shape[:-3]
  images = frames_to_model(frames.reshape(-1, *frames.shape[-3:]))
  tokens = dvae.apply({'params': dvae_params}, images, method=DVAE.tokenize)
  return tokens.reshape(*lead, -1)


def decode_tokens(dvae_params: Any, tokens: jax.Array, *, dvae: DVAE,
                  token_grid: tuple[int, int]) -> jax.Array:
  """int tokens [..., h * w] -> frames [..., H, W, 3] in [0, 1]."""
  lead = tokens.shape[:-1]
  images = dvae.apply({'params': dvae_params},
                      tokens.reshape(-1, *token_grid),
                      method=DVAE.decode_tokens)
  return model_to_unit(images.reshape(*lead, *images.shape[1:]))


def generate_tokens(decoder_params: Any, slots: jax.Array, *,
                    decoder: TokenDecoder) -> tuple[jax.Array, jax.Array]:
  """Greedy decoding with a key/value cache.

  slots [B, N, D] -> (tokens int32 [B, L], cross-attention of the last
  layer over the slots [B, L, N], each row summing to 1).
  """
  variables = {'params': decoder_params}
  cache = decoder.apply(variables, slots, method=TokenDecoder.init_cache)
  batch = slots.shape[0]

  def step(carry, position):
    previous, cache = carry
    token = jnp.where(position == 0, decoder.vocab_size, previous)
    logits, weights, cache = decoder.apply(
        variables, token, position, cache, method=TokenDecoder.decode_step)
    chosen = jnp.argmax(logits, axis=-1).astype(jnp.int32)
    return (chosen, cache), (chosen, weights)

  initial = (jnp.zeros((batch,), jnp.int32), cache)
  _, (tokens, weights) = jax.lax.scan(
      step, initial, jnp.arange(decoder.num_tokens))
  return tokens.T, weights.transpose(1, 0, 2)


def generate_tokens_recomputed(decoder_params: Any, slots: jax.Array, *,
                               decoder: TokenDecoder) -> jax.Array:
  """Greedy decoding by re-running the decoder over all L positions at every
  step (causal, so the not-yet-generated positions do not matter).

  slots [B, N, D] -> tokens int32 [B, L].
  """
  variables = {'params': decoder_params}
  length = decoder.num_tokens

  def step(tokens, position):
    logits = decoder.apply(variables, slots, tokens)
    chosen = jnp.argmax(logits[:, position], axis=-1).astype(jnp.int32)
    return tokens.at[:, position].set(chosen), None

  tokens = jnp.zeros((slots.shape[0], length), jnp.int32)
  tokens, _ = jax.lax.scan(step, tokens, jnp.arange(length))
  return tokens


def generate_frames(decoder_params: Any, dvae_params: Any, slots: jax.Array,
                    *, decoder: TokenDecoder, dvae: DVAE,
                    token_grid: tuple[int, int]
                    ) -> tuple[jax.Array, jax.Array]:
  """slots [..., N, D] -> (frames [..., H, W, 3] in [0, 1], masks
  [..., N, h, w]: the decoder's last-layer cross-attention of each token
  over the slots, the segmentation of a generated frame)."""
  lead = slots.shape[:-2]
  tokens, weights = generate_tokens(
      decoder_params, slots.reshape(-1, *slots.shape[-2:]), decoder=decoder)
  frames = decode_tokens(dvae_params, tokens, dvae=dvae,
                         token_grid=token_grid)
  masks = weights.transpose(0, 2, 1).reshape(-1, slots.shape[-2], *token_grid)
  return (frames.reshape(*lead, *frames.shape[1:]),
          masks.reshape(*lead, *masks.shape[1:]))
