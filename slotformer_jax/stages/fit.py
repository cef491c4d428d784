"""Training a stage of the pipeline: its identity stamped, its architecture
checked, then the trainer's loop (train/trainer.py), which knows nothing of
workdirs."""

from __future__ import annotations

from typing import Any

from jax.sharding import Mesh
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
