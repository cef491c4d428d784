"""The video-prediction stages: `evaluate` (metrics), `render` (pictures)
and `explore` (the run explorer page, with counterfactual rollouts).

Each takes the run's trained slot model and dynamics models, checks that
they descend from each other and from the evaluated slots (nothing mixes),
and hands them with the config sections they need to `evaluation/`, which
never loads a model itself.

Several seeds (config.seeds): each stage runs for every seed's view
(`Run.for_seed`: its share of the stacked stage 1 and dynamics models, its
slots) into `seed_<s>/eval/`, `seed_<s>/render/`, `seed_<s>/explore/`, and
`evaluate` folds the seeds' metrics into `eval/metrics.json` (mean +- std,
each seed's value; `evaluation/seeds.py`). A seed that diverged in training
is left out and named.
"""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
import logging
import os
from typing import Any

from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax import targets as targets_lib
from slotformer_jax.dynamics.base import intervened
from slotformer_jax.config.sections import primary_dynamics
from slotformer_jax.config.sections import trained_dynamics
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import evaluate as evaluate_lib
from slotformer_jax.evaluation import explore as explore_lib
from slotformer_jax.evaluation import seeds as seeds_lib
from slotformer_jax.evaluation import visualize
from slotformer_jax.run import Run
from slotformer_jax.slot_models import chain
from slotformer_jax.stages import dynamics as dynamics_stage
from slotformer_jax.stages.fit import stamped_fields
from slotformer_jax.stages.task import Task
from slotformer_jax.stages.task import register
from slotformer_jax.train.seeds import Seeds
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import command

logger = logging.getLogger(__name__)


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
        found, stamped_fields(dynamics_lib.identity_fields(
            run.config.seed, run.dynamics_section(name), name),
            Seeds.of_config(run.config).map(dynamics_stage.dynamics_seed)),
        name, directory)
    if found.get('parent') != parent:
      raise UserError(
          f'{name} in {directory} was trained on the slots of '
          f'{run.slot_model.label} {found.get("parent")}, but stage 1 is now '
          f'{parent}; evaluating would mix them. Retrain it (it is set aside '
          f'and retrained): {retrain}')
    identity[name] = {'run_id': found['run_id'], 'step': int(step),
                      'fingerprint': found['fingerprint'], 'parent': parent}
    if run.stacked is not None:
      identity[name]['seed'] = run.seed
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


def diverged(trained: Evaluated) -> str | None:
  """Why a seed view's models are not evaluated: 'savi diverged in update
  117' when a stage of it diverged in training, else None."""
  updates = dict(trained.stage1.diverged_at)
  updates.update({name: model.diverged_at
                  for name, model in trained.dynamics.items()
                  if model.diverged_at})
  if not updates:
    return None
  return ', '.join(f'{name} diverged in update {update}'
                   for name, update in updates.items())


def _each_seed(run: Run, what: str, stage: Callable[[Run, Evaluated], Any]
               ) -> tuple[dict[int, Any], dict[int, str]]:
  """({seed: `stage(view, its models)`} of every seed view whose models
  trained to the end, {seed: why not} of those that diverged)."""
  done, excluded = {}, {}
  for view in run.seed_views():
    trained = evaluated(view)
    why = diverged(trained)
    if why is None:
      logger.info('%s: seed %d', what, view.seed)
      done[view.seed] = stage(view, trained)
    else:
      excluded[view.seed] = why
      logger.warning('%s: seed %d left out (%s)', what, view.seed, why)
  return done, excluded


def evaluate(run: Run) -> dict[str, Any]:
  """eval/metrics.json and eval/per_step.csv (see evaluation/evaluate.py);
  several seeds: each seed's in seed_<s>/eval/, their summary in
  eval/metrics.json (evaluation/seeds.py)."""
  if run.seeds is None:
    return _evaluate(run, evaluated(run))
  per_seed, excluded = _each_seed(run, 'evaluate', _evaluate)
  summary = seeds_lib.summarise(per_seed, excluded, run.seeds)
  if run.is_lead:
    os.makedirs(run.paths.eval, exist_ok=True)
    seeds_lib.write(run.paths.eval, summary)
    print(seeds_lib.format_table(summary, run.slot_model.label))
  return summary


def _protocol(run: Run) -> Any:
  """The section whose burn-in and frame stride every method is evaluated,
  drawn and explored with: the first trained dynamics model's."""
  return run.dynamics_section(primary_dynamics(run.config))


def _evaluate(run: Run, trained: Evaluated) -> dict[str, Any]:
  """The evaluation of one seed (a one-seed run or a seed view)."""
  split = run.config.evaluation.split
  return evaluate_lib.evaluate(
      run.config.evaluation, _protocol(run), run.mesh,
      slot_model=run.slot_model, slot_params=trained.stage1.params,
      slot_steps=trained.stage1.steps, dynamics=trained.dynamics,
      identity=trained.identity,
      source=run.slots(split, evaluate_lib.video_fields(
          run.config.evaluation)),
      videos=run.videos(split),
      num_true=evaluate_lib.num_true_ids(run.config.data.max_instances),
      compute_dtype=run.config.compute_dtype, output_dir=run.paths.eval)


def render(run: Run) -> list[str]:
  """render/: GIFs, labelled strips, curves (see evaluation/visualize.py);
  several seeds: each seed's in seed_<s>/render/."""
  if run.seeds is None:
    return _render(run, evaluated(run))
  per_seed, _ = _each_seed(run, 'render', _render)
  return [path for paths in per_seed.values() for path in paths]


def _render(run: Run, trained: Evaluated) -> list[str]:
  return visualize.render(
      run.config.render, run.config.evaluation,
      _protocol(run), slot_model=run.slot_model,
      slot_params=trained.stage1.params, dynamics=trained.dynamics,
      identity=trained.identity,
      source=run.slots(run.config.evaluation.split, (
          'video', *(target.field for target
                     in targets_lib.besides_frames(run.slot_model)))),
      metrics_path=os.path.join(run.paths.eval, 'metrics.json'),
      output_dir=run.paths.render)


def explore(run: Run) -> str | list[str | None] | None:
  """explore/index.html (see evaluation/explore.py); several seeds: each
  seed's seed_<s>/explore/index.html, in seed order."""
  if run.seeds is None:
    return _explore(run, evaluated(run))
  per_seed, _ = _each_seed(run, 'explore', _explore)
  return list(per_seed.values())


def _explore(run: Run, trained: Evaluated) -> str | None:
  return explore_lib.explore(
      run.config.explore, run.config.evaluation,
      _protocol(run), slot_model=run.slot_model,
      slot_params=trained.stage1.params, dynamics=trained.dynamics,
      identity=trained.identity,
      open_slots=lambda fields: run.slots(run.config.evaluation.split,
                                          fields),
      num_true=evaluate_lib.num_true_ids(run.config.data.max_instances),
      metrics_path=os.path.join(run.paths.eval, 'metrics.json'),
      output_dir=run.paths.explore,
      title=(f'{run.config.data.name}: {run.slot_model.label} + '
             f'{dynamics_lib.label(intervened(trained.dynamics))}'))


# Video prediction is the task of a config without one (config.task None).
TASK = register(Task(
    name=None, config='configs/synthetic.py',
    stages={'evaluate': evaluate, 'render': render, 'explore': explore},
    seeded=('evaluate', 'render', 'explore'),
    reads=lambda config: (('evaluation.split', config.evaluation.split),)))
