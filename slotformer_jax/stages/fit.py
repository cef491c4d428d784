"""Training a stage of the pipeline: its identity stamped, its architecture
checked, then the trainer's loop (train/trainer.py), which knows nothing of
workdirs."""

from __future__ import annotations

from typing import Any

from jax.sharding import Mesh

from slotformer_jax.train.state import TrainState
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit
from slotformer_jax.workdir import identity as identity_lib


def fit_stage(stage: Stage, *, mesh: Mesh, seed: int, what: str,
              identity_fields: dict[str, Any], parent: dict[str, Any] | None,
              model_fields: dict[str, Any]) -> TrainState:
  """`fit` after stamping the stage's run identity (a stage made with other
  settings or from another parent is set aside and retrained; see
  `identity.start_stage`) and checking that its checkpoints have the
  architecture of `model_fields`."""
  identity_lib.start_stage(stage.directory, identity_fields, parent, what)
  identity_lib.check_model_config(stage.directory, model_fields, what)
  identity_lib.write_model_config(stage.directory, model_fields)
  return fit(stage, mesh=mesh, seed=seed)
