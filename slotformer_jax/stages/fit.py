"""Training a stage of the pipeline: its identity stamped, its architecture
checked, then the trainer's loop (train/trainer.py), which knows nothing of
workdirs."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections

from slotformer_jax.config.sections import several_seeds
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.trainer import Seeds
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit
from slotformer_jax.workdir import identity as identity_lib


def seeds_of(config: ml_collections.ConfigDict, offset: int = 0
             ) -> Seeds | None:
  """The run's several seeds (config.seeds, each + `offset`: a stage's own
  stream), or None for one seed (config.seed, as before)."""
  values = several_seeds(config)
  if values is None:
    return None
  return Seeds(tuple(v + offset for v in values),
               data_order=config.seed_data_order,
               on_divergence=config.on_seed_divergence,
               seed_axis=config.seed_axis,
               loop=config.seed_loop)


def stream_seeds(config: ml_collections.ConfigDict, offset: int = 0
                 ) -> tuple[int, ...]:
  """Each chain's data-order seed for a stage whose own stream is `offset`
  apart from the run's (the dynamics: 1): one seed, (config.seed +
  offset,); several, config.seed + offset for every seed (the shared
  order), or seed s + offset ('per_seed')."""
  values = several_seeds(config)
  if values is None:
    return (config.seed + offset,)
  if config.seed_data_order == 'per_seed':
    return tuple(seed + offset for seed in values)
  return (config.seed + offset,) * len(values)


def stacked_stage(stages: list[Stage]) -> Stage:
  """One stage of K seeds from their one-seed stages, each on that seed's
  own data: seed k's batches from `stages[k]` (drawn in the order it was
  built for, `stream_seeds`), its frozen parameters (SlotFormer's L_I
  decoder; None: none) `stages[k]`'s, stacked [K, ...]; the loss, schedule,
  pictures (the first seed's) and directory are the first stage's (the
  same for every seed)."""
  frozen = [stage.frozen_params for stage in stages]
  stacked_frozen = (None if frozen[0] is None else
                    jax.tree.map(lambda *xs: jnp.stack(xs), *frozen))
  return dataclasses.replace(
      stages[0],
      seed_batches=lambda index, start_step: stages[index].batches(
          start_step),
      frozen_params=stacked_frozen, seed_frozen_params=True,
      batches_for_seed=None)


def stamped_fields(identity_fields: dict[str, Any], seeds: Seeds | None
                   ) -> dict[str, Any]:
  """The identity fields a stage trained with `seeds` records: with
  several, its `identity_fields` and the seeds with their data order."""
  if seeds is None or not seeds.several:
    return identity_fields
  return dict(identity_fields, seeds=identity_lib.seeds_entry(
      seeds.values, seeds.data_order))


def fit_stage(stage: Stage, *, mesh: Mesh, seed: int, what: str,
              identity_fields: dict[str, Any], parent: dict[str, Any] | None,
              model_fields: dict[str, Any],
              seeds: Seeds | None = None) -> TrainState:
  """`fit` after stamping the stage's run identity (a stage made with other
  settings or from another parent is set aside and retrained; see
  `identity.start_stage`) and checking that its checkpoints have the
  architecture of `model_fields`.

  Several `seeds`: they join the identity (with their data order), so a
  stage trained with other seeds (or one) is set aside; the checkpoints
  hold the one stacked state (train/trainer.py)."""
  identity_fields = stamped_fields(identity_fields, seeds)
  identity_lib.start_stage(stage.directory, identity_fields, parent, what)
  identity_lib.check_model_config(stage.directory, model_fields, what)
  identity_lib.write_model_config(stage.directory, model_fields)
  return fit(stage, mesh=mesh, seed=seed, seeds=seeds)
