"""STEVE inference: frames -> tokens, slots -> tokens -> frames.

Pure functions over parameters (jit them at the call site). Generation is
greedy, all h*w tokens of a frame in raster order, batched over every frame
given; `generate_tokens` keeps a key/value cache inside `lax.scan` (one
token's worth of work per step), `generate_tokens_recomputed` re-runs the
decoder over the whole sequence every step as the official code does (kept
as the reference the cache is tested and timed against).

Frames arrive as uint8 and are mapped to [-1, 1] on device (frames.py).
Reading the trained dVAE / STEVE / dynamics parameters of a STEVE workdir is
here too (no optimizer is built, no training code is imported).
"""

from __future__ import annotations

import logging
from typing import Any

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections

from slotformer_jax import inference
from slotformer_jax import models
from slotformer_jax import steve_workdir
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.modules.token_decoder import TokenDecoder
from slotformer_jax.train import sharding
from slotformer_jax.train.checkpoint import restore_params

logger = logging.getLogger(__name__)


def steve_encode(params: Any, video: jax.Array, carry: Any, *,
                 model: STEVE):
  """uint8 video [B, T, H, W, 3] -> (slots [B, T, N, D], masks [B, T, N, h',
  w'], carry); `carry` continues the state of the previous chunk."""
  return model.apply({'params': params}, frames_to_model(video), carry,
                     method=STEVE.encode)


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


# --------------------------------------------------------------------------
# Trained parameters of a STEVE workdir (no optimizer is built)
# --------------------------------------------------------------------------


def _frame_shape(config: ml_collections.ConfigDict) -> tuple[int, int, int]:
  return (*config.data.resolution, 3)


def dvae_param_shapes(config: ml_collections.ConfigDict) -> Any:
  return inference._param_shapes(  # pylint: disable=protected-access
      models.build_dvae(config), jnp.zeros((1, *_frame_shape(config))), 1.0)


def steve_param_shapes(config: ml_collections.ConfigDict) -> Any:
  model = models.build_steve(config)
  height, width = model.token_grid
  clip = (1, config.steve.clip_length, *_frame_shape(config))
  tokens = jnp.zeros((1, config.steve.clip_length, height * width), jnp.int32)
  return inference._param_shapes(model, jnp.zeros(clip), tokens)  # pylint: disable=protected-access


def dynamics_param_shapes(config: ml_collections.ConfigDict,
                          name: str = models.SLOTFORMER) -> Any:
  """As `inference.dynamics_param_shapes`, with STEVE's slot sizes."""
  stage_config = models.dynamics_config(config, name)
  history = jnp.zeros((1, stage_config.burn_in, config.steve.num_slots,
                       config.steve.slot_size))
  return inference._param_shapes(  # pylint: disable=protected-access
      models.build_dynamics(config, name), history, stage_config.rollout)


def _restore(directory: str, shapes: Any, mesh: Mesh, what: str,
             workdir: str, mode: str, num_train_steps: int
             ) -> tuple[Any, int]:
  params, step = restore_params(
      directory, shapes, sharding.replicated_sharding(mesh), what=what,
      train_command=inference._train_command(workdir, mode))  # pylint: disable=protected-access
  if step < num_train_steps:
    logger.warning('%s was trained for %d of %d steps only', what, step,
                   num_train_steps)
  return params, step


def load_dvae_params(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh) -> tuple[Any, int]:
  """The dVAE's trained parameters (replicated) and their step."""
  root = workdir_lib.stage1_workdir(config, workdir)
  directory = steve_workdir.dvae_dir(root)
  workdir_lib.check_model_config(
      directory, steve_workdir.dvae_model_fields(config), 'dVAE')
  return _restore(directory, dvae_param_shapes(config), mesh, 'dVAE', root,
                  'train_dvae', config.dvae.num_train_steps)


def load_steve_params(config: ml_collections.ConfigDict, workdir: str,
                      mesh: Mesh) -> tuple[Any, int]:
  """STEVE's trained parameters (replicated) and their step."""
  root = workdir_lib.stage1_workdir(config, workdir)
  directory = steve_workdir.steve_dir(root)
  workdir_lib.check_model_config(
      directory, steve_workdir.steve_model_fields(config), 'STEVE')
  return _restore(directory, steve_param_shapes(config), mesh, 'STEVE', root,
                  'train_steve', config.steve.num_train_steps)


def load_dynamics_params(config: ml_collections.ConfigDict, workdir: str,
                         mesh: Mesh, name: str = models.SLOTFORMER
                         ) -> tuple[Any, int]:
  """Stage-2 model `name` trained on STEVE's slots, and its step."""
  directory = workdir_lib.dynamics_dir(workdir, name)
  workdir_lib.check_model_config(
      directory, workdir_lib.dynamics_model_fields(config, name), name)
  return _restore(directory, dynamics_param_shapes(config, name), mesh, name,
                  workdir, f'train_{name}',
                  models.dynamics_config(config, name).num_train_steps)
