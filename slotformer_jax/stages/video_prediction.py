"""The video-prediction stages: `evaluate` (metrics), `render` (pictures)
and `explore` (the run explorer page, with counterfactual rollouts).

Both load the trained slot model and dynamics models of the workdir, check
that they descend from each other and from the evaluated slots (nothing
mixes), and hand them to `evaluation/`, which never loads a model itself.
"""

from __future__ import annotations

from typing import Any

from jax.sharding import Mesh
import ml_collections

from slotformer_jax import slot_models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.evaluation import evaluate as evaluate_lib
from slotformer_jax.evaluation import explore as explore_lib
from slotformer_jax.evaluation import visualize
from slotformer_jax.stages.dynamics import load_dynamics


def _load(config: ml_collections.ConfigDict, workdir: str, mesh: Mesh):
  """(slot model, its Loaded, {name: (params, step)}, identity)."""
  slot_model = slot_models.get(config)
  slot_model.check_compute_dtype()
  loaded = slot_model.load(workdir, mesh)
  dynamics = load_dynamics(config, workdir, mesh, slot_model.slot_shape,
                           evaluate_lib.dynamics_to_evaluate(config))
  identity = workdir_lib.evaluation_identity(
      config, workdir, config.evaluation.split, loaded.identity,
      loaded.slots_parent, slot_model.label,
      {name: step for name, (_, step) in dynamics.items()})
  return slot_model, loaded, dynamics, identity


def evaluate(config: ml_collections.ConfigDict, workdir: str,
             mesh: Mesh) -> dict[str, Any]:
  """eval/metrics.json and eval/per_step.csv (see evaluation/evaluate.py)."""
  slot_model, loaded, dynamics, identity = _load(config, workdir, mesh)
  return evaluate_lib.evaluate(
      config, workdir, mesh, slot_model=slot_model,
      slot_params=loaded.params, slot_steps=loaded.steps, dynamics=dynamics,
      identity=identity)


def render(config: ml_collections.ConfigDict, workdir: str,
           mesh: Mesh) -> list[str]:
  """render/: GIFs, labelled strips, curves (see evaluation/visualize.py)."""
  slot_model, loaded, dynamics, identity = _load(config, workdir, mesh)
  return visualize.render(config, workdir, mesh, slot_model=slot_model,
                          slot_params=loaded.params, dynamics=dynamics,
                          identity=identity)


def explore(config: ml_collections.ConfigDict, workdir: str,
            mesh: Mesh) -> str | None:
  """explore/index.html (see evaluation/explore.py)."""
  slot_model, loaded, dynamics, identity = _load(config, workdir, mesh)
  return explore_lib.explore(config, workdir, slot_model=slot_model,
                             slot_params=loaded.params, dynamics=dynamics,
                             identity=identity)
