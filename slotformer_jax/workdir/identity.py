"""Run identity: what each artifact of a workdir was made from.

Every trained stage folder (savi/, dvae/, steve/, slotformer/, slot_lstm/)
holds identity.json:
  run_id       random, stamped when the stage starts training from scratch
  fields       the config values that shaped it (`stage_fields`)
  parent       the identity of what it was trained on (dynamics: the slot
               model's run_id + step whose slots it read; STEVE: the dVAE's),
               or null
and model_config.json, the fields that shape its parameters (checked before a
checkpoint is restored). Extracted slots and tokens record their parent in
their meta.json, the metrics and pictures record every identity they used. A
child whose parent changed is rebuilt (slots, tokens) or refused (dynamics,
evaluation): nothing mixes.
"""

from __future__ import annotations

from collections.abc import Sequence
import hashlib
import json
import logging
import os
import time
from typing import Any
import uuid

import jax

from slotformer_jax import targets
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic

logger = logging.getLogger(__name__)

IDENTITY_FILE = 'identity.json'
MODEL_CONFIG_FILE = 'model_config.json'

# Settings that change how a run is observed, not what it computes.
NOT_SHAPING = ('log_every', 'checkpoint_every', 'stop_check_every',
               'num_workers', 'data_dir', 'reader_workers')

# Fields added after workdirs were made, and the value their absence stands
# for (what the code did before they existed): a workdir whose settings lack
# one is read as having that value, so it stays usable; any other value is a
# change like every other. A whole section added later is listed by its name
# with None (its absence stands for its defaults, whatever they are).
ADDED_FIELDS: dict[str, Any] = {
    'vqa.layer_norm_epsilon': 1e-6,
    'vqa.min_lr_fraction': 0.0,
    # Training fields every section has since their defaults were set
    # (before, only some sections had them; the code read their absence as
    # these values).
    'dvae.min_lr_fraction': 0.0,
    'steve.min_lr_fraction': 0.0,
    'savi.group_learning_rates': {},
    'dvae.group_learning_rates': {},
    'slotformer.group_learning_rates': {},
    'slot_lstm.group_learning_rates': {},
    'vqa.group_learning_rates': {},
    'vqa.choice_type_weights': {},
    'readout.layer_norm_epsilon': 1e-6,
    'readout.dropout_rate': 0.0,
    'evaluation.skip_first_frame': False,
    'data.reader_workers': 0,
    # Several seeds in one program (config.seeds): None is the one seed.
    'seeds': None,
    'seed_data_order': 'shared',
    'on_seed_divergence': 'stop',
    'seed_axis': True,
    'seed_loop': 'auto',
    # The task was told by a `vqa` section before `task` was set for VQA.
    'task': None,
    # Planning readouts before every readout field had a default: the
    # values the code used when they were absent (config/defaults.py).
    'readout.candidates': 'rendered',
    'readout.fold': 0,
    'readout.splits': {'train': 'train', 'test': 'val'},
    'readout.negatives_per_task': 40,
    'readout.num_pictures': 0,
    'readout.rollout_steps': 10,
    # SAVi's targets and encoder choices (issue 51): RGB frames, the CNN,
    # its position MLP as wide as its output, no Transformer after it.
    'savi.targets': list(targets.DEFAULT),
    'savi.encoder.kind': 'cnn',
    'savi.encoder.mlp_size': None,
    'savi.encoder.transformer': {'num_layers': 0, 'num_heads': 4,
                                 'qkv_size': 64, 'mlp_size': 1024},
    # SAVi++'s qkv width of the corrector and predictor; None: the slot size.
    'savi.slot_attention.qkv_size': None,
    'savi.predictor.qkv_size': None,
    # SAVi++'s random resized crop, off (issue 51): the clips as read.
    'savi.random_resized_crop': {
        'enabled': False, 'min_object_covered': 0.75,
        'aspect_ratio_range': [3 / 4, 4 / 3], 'area_range': [0.08, 1.0],
        'max_attempts': 100},
}


def plain(value: Any) -> Any:
  """Tuples -> lists (as JSON stores them), for comparisons."""
  return json.loads(json.dumps(value))


def shaping(section: dict[str, Any]) -> dict[str, Any]:
  """A config section without the fields that only change how it is
  observed (`NOT_SHAPING`)."""
  return {key: value for key, value in section.items()
          if key not in NOT_SHAPING}


def stage_fields(seed: int, data: dict[str, Any], name: str,
                 section: dict[str, Any]) -> dict[str, Any]:
  """Everything that shapes a model trained from the videos of `data` with
  the settings `section` (the config section `name`: 'savi', 'dvae',
  'steve', ...) and `seed`."""
  return plain({'seed': seed, 'data': shaping(data), name: shaping(section)})


def slots_fields(seed: int, extraction: dict[str, Any]) -> dict[str, Any]:
  """What shapes extracted slots besides the slot model that made them: the
  extraction settings (all but which splits) and the seed (stochastic SAVi
  samples with it)."""
  extraction = dict(extraction)
  extraction.pop('splits', None)
  return plain({'seed': seed, 'extraction': extraction})


def seeds_entry(seeds: Sequence[int], data_order: str) -> dict[str, Any]:
  """The `seeds` field a stage trained with several seeds in one program
  adds to its identity fields (the seeds it stacks and their data order;
  stages/fit.py stamps it, the readers of a stacked stage expect it)."""
  return {'seeds': [int(s) for s in seeds], 'data_order': data_order}


def fingerprint(fields: dict[str, Any]) -> str:
  return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()
                        ).hexdigest()[:16]


# Added fields whose absence from an old workdir matches any new value (the
# seed count and the task were told by other fields then); for every other
# field the absence stands for its ADDED_FIELDS value, None included.
_ABSENT_MATCHES_ANY = frozenset({'seeds', 'task'})
# A dynamics loss term's weight (`losses.register_loss`: its config entry
# `<term>_loss_weight`) absent from an old workdir stands for 0: the term was
# not in its loss. A new term needs no ADDED_FIELDS line.
LOSS_WEIGHT_SUFFIX = '_loss_weight'


def absent_value(name: str) -> tuple[bool, Any]:
  """(whether the dotted field `name` was added after workdirs were made,
  the value its absence stands for)."""
  if name in ADDED_FIELDS:
    return True, ADDED_FIELDS[name]
  if name.endswith(LOSS_WEIGHT_SUFFIX):
    return True, 0.0
  return False, None


def flat_differences(old: Any, new: Any, prefix: str = '') -> list[str]:
  """['savi.learning_rate: 0.0002 -> 0.001', ...] between nested dicts (a
  field of `ADDED_FIELDS` absent from `old` at its old value is none)."""
  if isinstance(old, dict) and isinstance(new, dict):
    out = []
    for key in sorted(set(old) | set(new)):
      name = f'{prefix}.{key}' if prefix else key
      if key not in old:
        added, value = absent_value(name)
        if added and (name in _ABSENT_MATCHES_ANY
                      or plain(new[key]) == value):
          continue
        out.append(f'{name}: (absent) -> {new[key]!r}')
      elif key not in new:
        out.append(f'{name}: {old[key]!r} -> (absent)')
      else:
        out += flat_differences(old[key], new[key], name)
    return out
  return [] if old == new else [f'{prefix}: {old!r} -> {new!r}']


# --------------------------------------------------------------------------
# identity.json
# --------------------------------------------------------------------------


def read_identity(stage_directory: str) -> dict[str, Any] | None:
  path = os.path.join(stage_directory, IDENTITY_FILE)
  if not os.path.exists(path):
    return None
  return read_json(path, fix=f'Delete {os.path.dirname(path)} to retrain '
                   'that stage.')


def new_identity(fields: dict[str, Any],
                 parent: dict[str, Any] | None = None) -> dict[str, Any]:
  return {'run_id': uuid.uuid4().hex[:12], 'fingerprint': fingerprint(fields),
          'fields': fields, 'parent': parent,
          'created': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}


def write_identity(stage_directory: str, identity: dict[str, Any]) -> None:
  if jax.process_index() == 0:
    write_json_atomic(os.path.join(stage_directory, IDENTITY_FILE), identity)


def check_identity_fields(identity: dict[str, Any], fields: dict[str, Any],
                          what: str, directory: str) -> None:
  changes = flat_differences(identity['fields'], fields)
  if changes:
    raise UserError(
        f'the {what} in {directory} was made with other settings '
        f'({"; ".join(changes[:8])}'
        f'{f"; and {len(changes) - 8} more" if len(changes) > 8 else ""}). '
        'Use the settings it was made with, or another --workdir.')


def checked_identity(directory: str, fields: dict[str, Any], what: str,
                     train_command: str) -> dict[str, Any]:
  """The identity of the stage in `directory`, made with `fields`.

  Raises:
    MissingInputError: the stage has no identity (never trained); the
      message names `train_command`.
    UserError: it was trained with other settings (the fields are listed).
  """
  identity = read_identity(directory)
  if identity is None:
    raise MissingInputError(
        f'no trained {what} in {directory}. Train it first: {train_command}')
  check_identity_fields(identity, fields, what, directory)
  return identity


def lost_steps(made_from: Any, current: dict[str, Any]
               ) -> tuple[str, int, int] | None:
  """(model name, its current step, the newer step `made_from` records)
  when something was made from a newer step of the same training run of a
  model than the one restored now (`parent_of` records both): that model's
  newer checkpoints were lost (damaged, set aside); retraining them
  reproduces them, so what was made from them is good. None otherwise."""
  if not isinstance(made_from, dict):
    return None
  for key, step in current.items():
    name = key[:-len('_step')] if key.endswith('_step') else None
    recorded = made_from.get(key)
    if (name and made_from.get(f'{name}_run_id') is not None
        and made_from.get(f'{name}_run_id') == current.get(f'{name}_run_id')
        and isinstance(recorded, int) and isinstance(step, int)
        and recorded > step):
      return name, step, recorded
  return None


def lost_steps_advice(what: str, made: str, lost: tuple[str, int, int],
                      train_command: str) -> str:
  """The line for `lost_steps`: retrain the lost steps (never remake what
  `made` names from the older step)."""
  _, step, newer = lost
  return (f'{made} were made by {what} step {newer}, but its newest intact '
          f'checkpoint is step {step} (the newer ones are damaged or '
          f'missing). Retrain the lost steps: {train_command} (it resumes '
          f'from step {step} and reproduces step {newer} bit for bit); '
          f'{made} then match again, keep them')


def parent_of(identity: dict[str, Any], step: int,
              name: str) -> dict[str, Any]:
  """What is made from the model `name` ('savi', 'dvae', 'steve') of
  `identity` at `step` records as its parent: {name_run_id, name_step}."""
  return {f'{name}_run_id': identity['run_id'], f'{name}_step': int(step)}


def start_stage(directory: str, fields: dict[str, Any],
                parent: dict[str, Any] | None, what: str) -> dict[str, Any]:
  """The stage's identity, stamped before training starts. A stage made with
  other settings or from another parent is stale: set aside, then retrained
  from scratch (so nothing mixes)."""
  identity = read_identity(directory)
  has_checkpoints = os.path.isdir(os.path.join(directory, 'checkpoints')) and (
      os.listdir(os.path.join(directory, 'checkpoints')))
  if identity is None and has_checkpoints:
    # A workdir from before identities: its checkpoints are the ones it was
    # trained with under config.json (which the settings check accepted).
    logger.warning('%s in %s has no identity.json (older version); '
                   'stamping one for the current settings', what, directory)
  elif identity is not None:
    changes = flat_differences(identity['fields'], fields)
    if identity.get('parent') != parent:
      changes.append(f'trained on {identity.get("parent")}, its parent is '
                     f'now {parent}')
    if not changes:
      return identity
    moved = set_aside(directory, identity)
    logger.warning('%s in %s is stale (%s): set aside as %s and retrained',
                   what, directory, '; '.join(changes), moved)
  identity = new_identity(fields, parent)
  write_identity(directory, identity)
  return identity


def set_aside(stage_directory: str, identity: dict[str, Any] | None) -> str:
  """Renames a stale stage folder out of the way (never deletes results)."""
  tag = identity['run_id'] if identity else uuid.uuid4().hex[:12]
  target = f'{stage_directory}.stale-{tag}'
  if jax.process_index() == 0:
    os.replace(stage_directory, target)
  return target


# --------------------------------------------------------------------------
# model_config.json: the fields that shape a checkpoint's parameters
# --------------------------------------------------------------------------


def write_model_config(directory: str, fields: dict[str, Any]) -> None:
  if jax.process_index() == 0:
    write_json_atomic(os.path.join(directory, MODEL_CONFIG_FILE), fields)


def check_model_config(directory: str, fields: dict[str, Any],
                       what: str) -> None:
  """Fails clearly when a checkpoint was trained with another architecture."""
  path = os.path.join(directory, MODEL_CONFIG_FILE)
  if not os.path.exists(path):
    return
  saved = read_json(path)
  differences = [
      f'{key}: checkpoint {saved.get(key)!r} vs config {fields.get(key)!r}'
      for key in sorted(set(saved) | set(fields))
      if saved.get(key) != fields.get(key)]
  if differences:
    raise ConfigError(
        f'the {what} checkpoint in {directory} was trained with a different '
        'model configuration: ' + '; '.join(differences) +
        '. Use the config it was trained with, or another --workdir.')
