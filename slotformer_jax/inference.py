"""Inference, one implementation for evaluation, rendering and extraction.

encode (SAVi over chunks) / decode (frozen SAVi decoder) / rollout (the
dynamics model or the copy-last baseline) / rollout-and-decode / predicted
segmentation, plus reading trained parameters from a workdir without
building an optimizer. Pure functions of params; the caller jits them.

Shapes at this boundary: video uint8 [B, T, H, W, 3]; slots [B, T, N, D];
decoded recon / rgb float [..., H, W, 3] in [0, 1], alpha_masks [..., N, H,
W, 1].
"""

from __future__ import annotations

import logging
from typing import Any

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections

from slotformer_jax import models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.evaluation.metrics import segmentation_from_alpha_masks
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.slot_lstm import SlotLSTM
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.train import sharding
from slotformer_jax.train.checkpoint import restore_params

logger = logging.getLogger(__name__)


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


def rollouts(dynamics_params: dict[str, Any], dynamics: dict[str, Any],
             burn_in_slots: jax.Array, num_steps: int, *,
             copy_last: bool = True) -> dict[str, jax.Array]:
  """Every method's predicted slots: {name: [B, num_steps, N, D]} for each
  dynamics model in `dynamics` ({name: module}, params in
  `dynamics_params`), plus 'copy_last' (the baseline) when asked."""
  out = {name: rollout_slots(dynamics_params[name], burn_in_slots,
                             model=model, num_steps=num_steps)
         for name, model in dynamics.items()}
  if copy_last:
    out['copy_last'] = copy_last_rollout(burn_in_slots, num_steps)
  return out


def predicted_segmentation(decoded, bg_threshold: float | None = None
                           ) -> jax.Array:
  """DecodedSlots (alpha_masks [..., N, H, W, 1]) -> int32 [..., H, W]: the
  slot with the largest alpha per pixel (`bg_threshold`: the official
  post-processing, see `metrics.segmentation_from_alpha_masks`)."""
  return segmentation_from_alpha_masks(decoded.alpha_masks[..., 0],
                                       bg_threshold=bg_threshold)


# --------------------------------------------------------------------------
# Trained parameters of a workdir (no optimizer is built)
# --------------------------------------------------------------------------


def _param_shapes(module, *args, **kwargs) -> Any:
  rngs = {name: jax.random.key(0) for name in ('params', 'sample', 'dropout')}
  return jax.eval_shape(
      lambda: module.init(rngs, *args, **kwargs)['params'])


def savi_param_shapes(config: ml_collections.ConfigDict) -> Any:
  clip_shape = (1, config.savi.clip_length, *config.data.resolution, 3)
  return _param_shapes(models.build_savi(config),
                       jnp.zeros(clip_shape, jnp.float32))


def dynamics_param_shapes(config: ml_collections.ConfigDict,
                          name: str = models.SLOTFORMER) -> Any:
  stage_config = models.dynamics_config(config, name)
  history_shape = (1, stage_config.burn_in, config.savi.num_slots,
                   config.savi.slot_size)
  return _param_shapes(models.build_dynamics(config, name),
                       jnp.zeros(history_shape, jnp.float32),
                       stage_config.rollout)


def load_savi_params(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh) -> tuple[Any, int]:
  """SAVi's trained parameters (replicated) and the step they are from."""
  directory = workdir_lib.savi_dir(workdir_lib.stage1_workdir(config, workdir))
  workdir_lib.check_model_config(directory, workdir_lib.savi_model_fields(
      config), 'SAVi')
  params, step = restore_params(
      directory, savi_param_shapes(config),
      sharding.replicated_sharding(mesh), what='SAVi',
      train_command=_train_command(workdir, 'train_savi'))
  if step < config.savi.num_train_steps:
    logger.warning('SAVi was trained for %d of %d steps only', step,
                   config.savi.num_train_steps)
  return params, step


def load_dynamics_params(config: ml_collections.ConfigDict, workdir: str,
                         mesh: Mesh, name: str = models.SLOTFORMER
                         ) -> tuple[Any, int]:
  """The newest parameters of stage-2 model `name` and their step."""
  directory = workdir_lib.dynamics_dir(workdir, name)
  workdir_lib.check_model_config(
      directory, workdir_lib.dynamics_model_fields(config, name), name)
  return restore_params(
      directory, dynamics_param_shapes(config, name),
      sharding.replicated_sharding(mesh), what=name,
      train_command=_train_command(workdir, f'train_{name}'))


def _train_command(workdir: str, mode: str) -> str:
  return ('python -m slotformer_jax.main --config=<config> '
          f'--workdir={workdir} --mode={mode}')
