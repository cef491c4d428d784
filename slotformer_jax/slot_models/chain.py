"""A slot model's stage 1 as one checked chain, for any slot model.

From the parts a slot model declares (`base.Part`), this finds each part's
folder, checks its identity against the config and against the part it was
trained on, restores its parameters, and checks that the extracted slots
descend from the part that encodes. SAVi is a chain of one; STEVE of two
(dVAE -> STEVE, the dVAE's tokens in between).
"""

from __future__ import annotations

import logging
from typing import Any

from jax.sharding import Mesh

from slotformer_jax import inference
from slotformer_jax.inference import StackedSeed
from slotformer_jax.data.slots import read_meta
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.slot_models.base import Loaded
from slotformer_jax.slot_models.base import Part
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir.paths import command

logger = logging.getLogger(__name__)


def part_identity(part: Part, paths: Paths,
                  stacked: StackedSeed | None = None) -> dict[str, Any]:
  """The identity of `part` in the stage-1 workdir, made with this config
  (`stacked`: a seed view's share of a K-seed run's stacked checkpoint).

  Raises:
    MissingInputError: never trained (the message names its stage).
    UserError: trained with other settings.
  """
  fields = dict(part.identity_fields)
  if stacked is not None:
    fields.update(stacked.identity_fields())
  return identity_lib.checked_identity(
      paths.model(part.name), fields, part.label,
      command(paths.stage1, part.mode))


def check_identities(slot_model: SlotModel, paths: Paths,
                     stacked: StackedSeed | None = None
                     ) -> dict[str, dict[str, Any]]:
  """{part name: identity} of every part, checked against this config
  (`stacked`: of a seed view of a K-seed run) without reading
  parameters (e.g. a read-only stage 1 before any work)."""
  return {part.name: part_identity(part, paths, stacked)
          for part in slot_model.parts}


def parent_of(slot_model: SlotModel, part: Part, identities: dict[str, Any],
              steps: dict[str, int]) -> dict[str, Any] | None:
  """What `part` is (to be) trained on: its parent part's run id and step."""
  if part.parent is None:
    return None
  return identity_lib.parent_of(identities[part.parent], steps[part.parent],
                                part.parent)


def chain(slot_model: SlotModel, paths: Paths, steps: dict[str, int],
          stacked: StackedSeed | None = None
          ) -> tuple[dict[str, Any], dict[str, Any]]:
  """(identity entries, slots parent) of the parts at `steps` (the
  `Loaded.identity` and `Loaded.slots_parent` of checkpoints at those
  steps), checked to descend from each other; `stacked`: of one seed of
  parts trained with several (each entry names the seed).

  Raises:
    UserError: a part was never trained, trained with other settings, or
      trained on another parent (the message names the stage to rerun).
  """
  identities, entries = {}, {}
  for part in slot_model.parts:
    identity = part_identity(part, paths, stacked)
    expected = parent_of(slot_model, part, identities, steps)
    if part.parent is not None and identity.get('parent') != expected:
      parent_label = slot_model.stage_labels[part.parent]
      lost = identity_lib.lost_steps(identity.get('parent'), expected)
      if lost is not None:
        raise UserError(identity_lib.lost_steps_advice(
            parent_label, f'{part.label} in {paths.model(part.name)}',
            lost, command(paths.stage1, f'train_{lost[0]}')) + '.')
      raise UserError(
          f'{part.label} in {paths.model(part.name)} was trained with '
          f'{parent_label} {identity.get("parent")}, the current '
          f'{parent_label} is {expected}; using both would mix them. Retrain '
          f'{part.label} (it is set aside and retrained): '
          f'{command(paths.root, part.mode)}')
    identities[part.name] = identity
    entries[part.name] = {'run_id': identity['run_id'],
                          'step': int(steps[part.name]),
                          'fingerprint': identity['fingerprint']}
    if part.parent is not None:
      entries[part.name]['parent'] = identity['parent']
    if stacked is not None:
      entries[part.name]['seed'] = stacked.seed
  last = slot_model.parts[-1]
  return entries, identity_lib.parent_of(identities[last.name],
                                         steps[last.name], last.name)


def param_shapes(part: Part) -> Any:
  """The parameter shapes of `part` (no compute)."""
  return inference.param_shapes(part.module, *part.example,
                                **part.example_kwargs)


def load_part(part: Part, paths: Paths, mesh: Mesh,
              stacked: StackedSeed | None = None) -> tuple[Any, int]:
  """The newest parameters of `part` (replicated) and their step;
  `stacked`: a seed view's share of a K-seed run's stacked part.

  Raises:
    UserError: no checkpoint, or one of another architecture.
  """
  params, step, _ = _restore_part(part, paths, mesh, stacked)
  return params, step


def _restore_part(part: Part, paths: Paths, mesh: Mesh,
                  stacked: StackedSeed | None) -> tuple[Any, int, int]:
  """`load_part`, or with `stacked` that seed's share of the stacked
  checkpoint; and the update in which the seed diverged (0: none)."""
  directory = paths.model(part.name)
  identity_lib.check_model_config(directory, dict(part.model_fields),
                                  part.label)
  train_command = command(paths.stage1, part.mode)
  if stacked is None:
    params, step = inference.restore(
        directory, param_shapes(part), mesh, what=part.label,
        train_command=train_command,
        num_train_steps=part.section.num_train_steps)
    return params, step, 0
  return inference.restore_seed(
      directory, param_shapes(part), mesh, stacked, what=part.label,
      train_command=train_command,
      num_train_steps=part.section.num_train_steps)


def load(slot_model: SlotModel, paths: Paths, mesh: Mesh,
         stacked: StackedSeed | None = None) -> Loaded:
  """The trained stage 1 of the run `paths` (its `stage1` folder), checked;
  `stacked`: a seed view's share of a K-seed run's stacked checkpoints
  (`Loaded.diverged_at`).

  Raises:
    UserError: missing, trained with another architecture or settings, or
      its parts do not descend from each other.
  """
  params, steps, diverged_at = {}, {}, {}
  for part in reversed(slot_model.parts):  # the one that encodes first
    params[part.name], steps[part.name], update = _restore_part(
        part, paths, mesh, stacked)
    if update:
      diverged_at[part.name] = update
  steps = {part.name: steps[part.name] for part in slot_model.parts}
  identity, slots_parent = chain(slot_model, paths, steps, stacked)
  last = slot_model.parts[-1].name
  return Loaded(params={p.name: params[p.name] for p in slot_model.parts},
                steps=steps, identity=identity, step=steps[last],
                slots_parent=slots_parent, diverged_at=diverged_at)


def check_slots_current(paths: Paths, split: str, expected: dict[str, Any],
                        fields: dict[str, Any], what: str) -> dict[str, Any]:
  """The slots of `split` must descend from `expected` (the slot model's
  `Loaded.slots_parent`; `what` names that model) and have been extracted
  with `fields` (`identity.slots_fields`); returns their parent.

  Raises:
    UserError: missing or stale slots, with the command that rebuilds them.
  """
  directory = paths.slots(split)
  meta = read_meta(directory)
  rebuild = command(paths.stage1, 'extract_slots')
  if not (meta and meta.get('complete')):
    raise MissingInputError(f'no complete slots in {directory}; extract them: '
                            f'{rebuild}')
  lost = identity_lib.lost_steps(meta.get('parent'), expected)
  if lost is not None and meta.get('fields') == fields:
    raise UserError(identity_lib.lost_steps_advice(
        what, f'the slots in {directory}', lost,
        command(paths.stage1, f'train_{lost[0]}')) + '.')
  if meta.get('parent') != expected or meta.get('fields') != fields:
    raise UserError(
        f'the slots in {directory} are stale: made by {what} '
        f'{meta.get("parent")}, the current {what} is {expected}. Re-extract '
        f'them: {rebuild}')
  return expected


def check_foreign_stage1(slot_model: SlotModel, paths: Paths, mesh: Mesh,
                         splits: tuple[str, ...],
                         slots_fields: dict[str, Any],
                         stacked: StackedSeed | None = None) -> Loaded:
  """A stage 1 read from another workdir (`config.stage1_workdir`) is
  read-only: its parts must be trained to their full length with this
  config's settings, the slots of `splits` complete and made by it.
  `stacked` (with `paths` of that seed view): its share of a K-seed run's
  stage 1, and its slots.

  Raises:
    UserError: what is missing or different, and where to fix it.
  """
  loaded = load(slot_model, paths, mesh, stacked)
  for key, step in loaded.steps.items():
    total = slot_model.num_train_steps[key]
    if step < total:
      raise UserError(
          f'stage 1 in stage1_workdir={paths.stage1} is incomplete '
          f'({slot_model.stage_labels[key]} step {step} of {total}); this '
          'run never trains there. Finish it with its own run: '
          f'python -m slotformer_jax.main --config=<its config> '
          f'--workdir={paths.stage1}')
  missing = [split for split in splits
             if not (read_meta(paths.slots(split)) or {}).get('complete')]
  if missing:
    # That run's own extract_slots would not make them (its config's
    # extraction.splits lacks them): name what this run can read instead.
    kept = tuple(split for split in splits if split not in missing)
    raise MissingInputError(
        f'stage1_workdir={paths.stage1} has no complete slots of '
        f'{", ".join(missing)}; this run reads extraction.splits='
        f'{tuple(splits)} and never extracts there. '
        + (f'Read the splits it has: --config.extraction.splits="{kept}", '
           'or e' if kept else 'E')
        + f'xtract {", ".join(missing)} with that run\'s own config: '
        f'{command(paths.stage1, "extract_slots")} --config.extraction.'
        f'splits="{tuple(splits)}" --allow_config_change')
  for split in splits:
    check_slots_current(paths, split, loaded.slots_parent, slots_fields,
                        slot_model.label)
  return loaded
