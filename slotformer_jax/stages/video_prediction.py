"""The video-prediction stages: `evaluate` (metrics), `render` (pictures)
and `explore` (the run explorer page, with counterfactual rollouts).

Each takes the run's trained slot model and dynamics models, checks that
they descend from each other and from the evaluated slots (nothing mixes),
and hands them with the config sections they need to `evaluation/`, which
never loads a model itself.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax.config.sections import SLOTFORMER
from slotformer_jax.config.sections import trained_dynamics
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import evaluate as evaluate_lib
from slotformer_jax.evaluation import explore as explore_lib
from slotformer_jax.evaluation import visualize
from slotformer_jax.run import Run
from slotformer_jax.slot_models import chain
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import command


@dataclasses.dataclass(frozen=True)
class Evaluated:
  """What an evaluation reads: the trained models and their lineage.

  Attributes:
    stage1: the slot model's `Loaded`.
    dynamics: {name: `dynamics.Loaded`} of every dynamics model compared.
    identity: what all of them descend from, as the results record it.
  """

  stage1: Any
  dynamics: dict[str, Any]
  identity: dict[str, Any]


def evaluation_identity(run: Run, stage1_identity: dict[str, Any],
                        slots_parent: dict[str, Any],
                        dynamics_steps: dict[str, int]) -> dict[str, Any]:
  """What an evaluation (metrics, pictures) is made from, checked: the
  evaluation split's slots descend from the slot model (`stage1_identity`,
  `slots_parent`: `Loaded.identity`, `Loaded.slots_parent`), and every
  dynamics model at its step ({name: step}) was trained on those slots with
  this config. Reads identity files only.

  Raises:
    UserError: something is stale or missing; the message names the stage
      to rerun.
  """
  parent = chain.check_slots_current(
      run.paths, run.config.evaluation.split, slots_parent,
      run.slots_fields, run.slot_model.label)
  identity = {**stage1_identity, 'slots': parent}
  for name, step in dynamics_steps.items():
    directory = run.paths.dynamics(name)
    found = identity_lib.read_identity(directory)
    retrain = command(run.paths.root, f'train_{name}')
    if found is None:
      raise UserError(f'{directory} has no identity.json: it is from an '
                      f'older version or incomplete; retrain it: {retrain}')
    identity_lib.check_identity_fields(
        found, dynamics_lib.identity_fields(
            run.config.seed, run.dynamics_section(name), name),
        name, directory)
    if found.get('parent') != parent:
      raise UserError(
          f'{name} in {directory} was trained on the slots of '
          f'{run.slot_model.label} {found.get("parent")}, but stage 1 is now '
          f'{parent}; evaluating would mix them. Retrain it (it is set aside '
          f'and retrained): {retrain}')
    identity[name] = {'run_id': found['run_id'], 'step': int(step),
                      'fingerprint': found['fingerprint'], 'parent': parent}
  return identity


def evaluated(run: Run) -> Evaluated:
  """The run's trained models for the evaluation split, checked to descend
  from each other and from that split's slots (`evaluation_identity`)."""
  stage1 = run.stage1
  dynamics = {name: run.dynamics(name) for name in trained_dynamics(run.config)}
  identity = evaluation_identity(
      run, stage1.identity, stage1.slots_parent,
      {name: model.step for name, model in dynamics.items()})
  return Evaluated(stage1=stage1, dynamics=dynamics, identity=identity)


def evaluate(run: Run) -> dict[str, Any]:
  """eval/metrics.json and eval/per_step.csv (see evaluation/evaluate.py)."""
  trained = evaluated(run)
  split = run.config.evaluation.split
  return evaluate_lib.evaluate(
      run.config.evaluation, run.dynamics_section(SLOTFORMER), run.mesh,
      slot_model=run.slot_model, slot_params=trained.stage1.params,
      slot_steps=trained.stage1.steps, dynamics=trained.dynamics,
      identity=trained.identity,
      source=run.slots(split, evaluate_lib.video_fields(
          run.config.evaluation)),
      videos=run.videos(split),
      num_true=evaluate_lib.num_true_ids(run.config.data.max_instances),
      compute_dtype=run.config.compute_dtype, output_dir=run.paths.eval)


def render(run: Run) -> list[str]:
  """render/: GIFs, labelled strips, curves (see evaluation/visualize.py)."""
  trained = evaluated(run)
  return visualize.render(
      run.config.render, run.config.evaluation,
      run.dynamics_section(SLOTFORMER), slot_model=run.slot_model,
      slot_params=trained.stage1.params, dynamics=trained.dynamics,
      identity=trained.identity,
      source=run.slots(run.config.evaluation.split, ('video',)),
      metrics_path=os.path.join(run.paths.eval, 'metrics.json'),
      output_dir=run.paths.render)


def explore(run: Run) -> str | None:
  """explore/index.html (see evaluation/explore.py)."""
  trained = evaluated(run)
  return explore_lib.explore(
      run.config.explore, run.config.evaluation,
      run.dynamics_section(SLOTFORMER), slot_model=run.slot_model,
      slot_params=trained.stage1.params, dynamics=trained.dynamics,
      identity=trained.identity,
      open_slots=lambda fields: run.slots(run.config.evaluation.split,
                                          fields),
      num_true=evaluate_lib.num_true_ids(run.config.data.max_instances),
      metrics_path=os.path.join(run.paths.eval, 'metrics.json'),
      output_dir=run.paths.explore,
      title=f'{run.config.data.name}: {run.slot_model.label} + SlotFormer')
