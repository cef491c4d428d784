"""Stage 2: SlotFormer (or the Slot-LSTM baseline) on the extracted slots.

The same stage for every slot model: L = L_S + lambda * L_I, where L_I
decodes the predicted slots through the slot model's frozen pixel decoder
(SAVi); a slot model without one (STEVE) trains with L_S alone, as the
paper does on Physion. A model trained on other slots (or with other
settings) is set aside and retrained from scratch.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import inference
from slotformer_jax import losses
from slotformer_jax import models
from slotformer_jax import slot_models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import pipeline
from slotformer_jax.errors import ConfigError
from slotformer_jax.modules import initializers
from slotformer_jax.runtime import precision
from slotformer_jax.runtime import sharding
from slotformer_jax.train import steps
from slotformer_jax.train import summaries
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit_stage


def image_loss_decoder(config: ml_collections.ConfigDict, name: str,
                       slot_model: slot_models.SlotModel, slot_params: Any
                       ) -> tuple[Any, Any]:
  """(decoder, its frozen params) of L_I, or (None, None) without L_I.

  Raises:
    ConfigError: L_I is on but the slot model has no pixel decoder.
  """
  weight = models.dynamics_config(config, name).image_loss_weight
  if weight <= 0:
    return None, None
  image_decoder = slot_model.image_decoder(slot_params)
  if image_decoder is None:
    raise ConfigError(
        f'L_I needs a differentiable pixel decoder, which '
        f'{slot_model.label} does not have (the paper trains SlotFormer on '
        f'{slot_model.label} slots without it); set --config.{name}.'
        f'image_loss_weight=0 (got {weight})')
  return image_decoder


def dynamics_stage(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh, name: str, slot_model: slot_models.SlotModel,
                   slot_params: Any, source: Any) -> Stage:
  """Dynamics model `name`'s training stage on `source` (the slots of the
  'train' split, with their videos when L_I is on; only its `batches` read
  it). `slot_params`: the slot model's, for the frozen decoder of L_I."""
  stage_config = models.dynamics_config(config, name)
  rollout = stage_config.rollout
  decoder, decoder_params = image_loss_decoder(config, name, slot_model,
                                               slot_params)
  video_fields = ('video',) if decoder is not None else ()
  model = models.build_dynamics(config, name)
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  example = inference.dynamics_example(config, name, slot_model.slot_shape)
  return Stage(
      name=name,
      directory=workdir_lib.dynamics_dir(workdir, name),
      config=stage_config,
      loss_fn=precision.with_compute_dtype(functools.partial(
          losses.slotformer_loss, model=model, decoder=decoder,
          rollout=rollout,
          image_loss_weight=stage_config.image_loss_weight if decoder else 0.0,
          teacher_forcing=stage_config.teacher_forcing), config.compute_dtype),
      init_params=lambda rng: initializers.initialize(
          steps.init_params(model, rng, *example),
          jax.random.fold_in(rng, 1), stage_config.get('init', 'flax')),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=stage_config.burn_in + rollout, seed=config.seed + 1,
          start_step=start_step, fields=('slots',) + video_fields,
          frame_stride=stage_config.frame_stride,
          process_index=jax.process_index(),
          process_count=jax.process_count()),
      frozen_params=decoder_params,
      logging=config.get('logging'),
      images=(_rollout_images(slot_model, slot_params, model,
                              stage_config.burn_in, rollout, name)
              if slot_model.image_decoder(slot_params) is not None
              else None),
  )


def train_dynamics(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh, name: str) -> None:
  """Trains dynamics model `name` on the current slots of the 'train' split."""
  slot_model = slot_models.get(config)
  slot_model.check_compute_dtype()
  loaded = slot_model.load(workdir, mesh)
  parent = workdir_lib.check_slots_current(config, workdir, 'train',
                                           loaded.slots_parent,
                                           slot_model.label)
  decoder, _ = image_loss_decoder(config, name, slot_model, loaded.params)
  video_fields = ('video',) if decoder is not None else ()
  source = workdir_lib.slot_source_for(config, workdir, 'train', video_fields)
  stage = dynamics_stage(config, workdir, mesh, name, slot_model,
                         loaded.params, source)
  fit_stage(stage, mesh=mesh, seed=config.seed + 1, what=name,
            identity_fields=workdir_lib.dynamics_identity_fields(config, name),
            parent=parent,
            model_fields=workdir_lib.dynamics_model_fields(config, name))


def _rollout_images(slot_model, slot_params, model, burn_in: int,
                    rollout: int, name: str):
  """TensorBoard rollout strip of the first clip of a training batch: its
  frames (when the batch has them), its extracted slots decoded, and the
  burn-in slots followed by the model's rollout, decoded (slot models with
  a pixel decoder only)."""

  @jax.jit
  def run(params, slots):
    predicted = inference.rollout_slots(params, slots[:, :burn_in],
                                        model=model, num_steps=rollout)
    both = jnp.concatenate([slots, jnp.concatenate(
        [slots[:, :burn_in], predicted], axis=1)])
    return slot_model.decode(slot_params, both).recon

  def images(params, batch):
    recon = np.asarray(jax.device_get(run(params, batch['slots'][:1])))
    rows = {}
    if 'video' in batch:
      rows['real frames'] = batch['video'][0]
    rows['slots decoded'] = summaries.to_uint8(recon[0])
    rows[f'burn-in {burn_in} + {name}'] = summaries.to_uint8(recon[1])
    return {'rollout': summaries.labelled_grid(rows)}

  return images


def train_slotformer(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh) -> None:
  train_dynamics(config, workdir, mesh, models.SLOTFORMER)


def train_slot_lstm(config: ml_collections.ConfigDict, workdir: str,
                    mesh: Mesh) -> None:
  """The Slot-LSTM baseline, with SlotFormer's data, losses and schedule."""
  train_dynamics(config, workdir, mesh, models.SLOT_LSTM)


def load_dynamics(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh, slot_shape: tuple[int, int],
                  names: tuple[str, ...] = (models.SLOTFORMER,)
                  ) -> dict[str, tuple]:
  """{name: (params, step)} of the trained dynamics models `names`."""
  return {name: inference.load_dynamics_params(config, workdir, mesh, name,
                                               slot_shape)
          for name in names}
