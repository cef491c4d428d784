"""Stage 2: every registered dynamics model (SlotFormer, the Slot-LSTM
baseline, ...: dynamics/) on the extracted slots.

The same stage for every slot model: L = L_S + lambda * L_I, where L_I
decodes the predicted slots through the slot model's frozen pixel decoder
(SAVi); a slot model without one (STEVE) trains with L_S alone, as the
paper does on Physion. A model trained on other slots (or with other
settings) is set aside and retrained from scratch.

Each chain of the run (`Run.chains`) trains its own model on its own slots
(a seed view of a K-seed run: `seed_<s>/slots/train`, L_I through its
share of stage 1's decoder), drawing with its seed + 1 as the one-seed run
of that seed; every chain in one program (`stages/fit.py` `fit_chains`),
one checkpoint in `slotformer/`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
from jax.sharding import Mesh
import ml_collections

from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax import losses
from slotformer_jax.config.sections import dynamics_stages
from slotformer_jax.data import pipeline
from slotformer_jax.errors import ConfigError
from slotformer_jax.modules import initializers
from slotformer_jax.run import Run
from slotformer_jax.runtime import precision
from slotformer_jax.runtime import sharding
from slotformer_jax.slot_models import chain
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.stages.fit import Training
from slotformer_jax.stages.fit import fit_chains
from slotformer_jax.train import steps
from slotformer_jax.train.trainer import Stage


def decoded_terms(weights: dict[str, float]) -> dict[str, float]:
  """The terms of `weights` that are on and decode the predicted slots
  with the slot model's frozen decoder (L_I)."""
  return {name: weight for name, weight in weights.items()
          if weight > 0 and losses.LOSS_TERMS[name].needs_decoder}


def image_loss_decoder(weights: dict[str, float], name: str,
                       slot_model: SlotModel, slot_params: Any
                       ) -> tuple[Any, Any]:
  """(decoder, its frozen params) of the terms that decode (L_I), or
  (None, None) when none is on.

  Raises:
    ConfigError: such a term is on but the slot model has no pixel decoder.
  """
  decoded = decoded_terms(weights)
  if not decoded:
    return None, None
  image_decoder = slot_model.image_decoder(slot_params)
  if image_decoder is None:
    term, weight = next(iter(decoded.items()))
    raise ConfigError(
        f'{losses.LOSS_TERMS[term].label} needs a differentiable pixel '
        f'decoder, which '
        f'{slot_model.label} does not have (the paper trains SlotFormer on '
        f'{slot_model.label} slots without it); set --config.{name}.'
        f'{losses.weight_field(term)}=0 (got {weight})')
  return image_decoder


def dynamics_stage(section: ml_collections.ConfigDict, name: str,
                   directory: str, mesh: Mesh, slot_model: SlotModel,
                   slot_params: Any, source: Any, *, seed: int,
                   compute_dtype: str,
                   logging_config: ml_collections.ConfigDict | None = None,
                   reader_workers: int = 0) -> Stage:
  """Dynamics model `name`'s training stage (settings `section`) on
  `source` (the slots of the 'train' split, with their videos when L_I is
  on; only its `batches` read it). `slot_params`: the slot model's, for the
  frozen decoder of L_I. Its loss: the model's registered terms with their
  weights (`DynamicsModel.loss_terms`; a term at weight <= 0 is off)."""
  rollout = section.rollout
  weights = dynamics_lib.get(name).loss_terms(section)
  decoder, decoder_params = image_loss_decoder(weights, name, slot_model,
                                               slot_params)
  video_fields = slot_model.image_loss_fields if decoder is not None else ()
  model = dynamics_lib.build(section, name)
  example = dynamics_lib.example(section, slot_model.slot_shape)
  images = dynamics_lib.rollout_images(slot_model, slot_params, model,
                                       section.burn_in, rollout, name)
  local_batch_size = sharding.per_host_batch_size(section.batch_size, mesh)

  def batches(start_step):
    return pipeline.train_batches(
        source, batch_size=local_batch_size,
        clip_length=section.burn_in + rollout, seed=seed,
        start_step=start_step, fields=('slots',) + video_fields,
        frame_stride=section.frame_stride,
        process_index=jax.process_index(),
        process_count=jax.process_count(), num_workers=reader_workers)

  return Stage(
      name=name,
      directory=directory,
      config=section,
      loss_fn=precision.with_compute_dtype(functools.partial(
          losses.slotformer_loss, model=model, decoder=decoder,
          rollout=rollout, to_model=slot_model.to_model, weights=weights,
          teacher_forcing=section.teacher_forcing), compute_dtype),
      init_params=lambda rng: initializers.initialize(
          steps.init_params(model, rng, *example),
          jax.random.fold_in(rng, 1), section.init),
      batches=batches,
      frozen_params=decoder_params,
      logging=logging_config,
      images=images,
  )


def train_dynamics(run: Run, name: str) -> None:
  """Trains dynamics model `name` on the current slots of the 'train'
  split, every chain's in one program (the module docstring): each
  chain's stage (`seed_stage`), its parent the stage 1 every chain's slots
  were checked to descend from."""
  section = run.dynamics_section(name)
  training = Training(
      what=name,
      chain_stage=lambda chain, stream: seed_stage(chain, name, stream),
      model_fields=dynamics_lib.model_fields(section, name),
      identity_fields=dynamics_lib.identity_fields(run.config.seed, section,
                                                   name),
      # Its own stream of batches and RNG: seed + 1, apart from stage 1's.
      seed_of=dynamics_seed)
  fit_chains(run, training)


def dynamics_seed(seed: int) -> int:
  """What a dynamics model of the chain of `seed` draws with."""
  return seed + 1


def seed_stage(view: Run, name: str, stream_seed: int
               ) -> tuple[Stage, dict[str, Any]]:
  """The one-seed training stage of dynamics model `name` on the current
  slots of the 'train' split of `view` (a run, or the seed view
  `Run.for_seed` of a several-seed run: what seed `view.seed` trains; the
  stage's directory is `paths.dynamics(name)`, the stacked one then), its
  batches drawn with `stream_seed`; and the slots' parent (stage 1).

  Raises:
    UserError: the view's slots of 'train' are missing or stale.
  """
  section, slot_model, loaded = (view.dynamics_section(name),
                                 view.slot_model, view.stage1)
  parent = chain.check_slots_current(view.paths, 'train', loaded.slots_parent,
                                     view.slots_fields, slot_model.label)
  # L_I (`image_loss_decoder`) reads the videos, and compares the rollout
  # frames only: the burn-in frames are not read.
  decodes = decoded_terms(dynamics_lib.get(name).loss_terms(section))
  source = view.slots('train',
                      slot_model.image_loss_fields if decodes else (),
                      video_from=section.burn_in)
  stage = dynamics_stage(section, name, view.paths.dynamics(name),
                         view.mesh, slot_model, loaded.params, source,
                         seed=stream_seed,
                         compute_dtype=view.config.compute_dtype,
                         logging_config=view.config.logging,
                         reader_workers=view.config.data.reader_workers)
  return stage, parent


def stage_functions(config: ml_collections.ConfigDict
                    ) -> dict[str, Callable[[Run], None]]:
  """{`train_<name>`: its training stage} of every registered dynamics
  model that `config` has a section of, in registration order."""
  return {stage: functools.partial(train_dynamics,
                                   name=stage[len('train_'):])
          for stage in dynamics_stages(config)}
