"""Paths of a run and what each artifact was made from.

Workdir layout (shared by all stages; each stage resumes from it)::

    config.json                 the settings this workdir was trained with
    config_history.jsonl        every accepted settings change
    <stage-1 model>/            e.g. savi/, or dvae/ + tokens/ + steve/
                                (slot_models/): checkpoints/<step>/,
                                model_config.json, identity.json,
                                train_log.jsonl
    slots/<split>/              extracted slots (see data/slots.py)
    slotformer/checkpoints/     slotformer/train_log.jsonl (also slot_lstm/)
    eval/metrics.json           eval/per_step.csv
    render/*.gif, *.png

Only paths and checks live here (no training code), so evaluation can use it.
What is particular to one slot model (its folders, the fields that shape it)
lives with it in `slot_models/`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from typing import Any
import uuid

import jax
import ml_collections

from slotformer_jax import models
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.slots import read_meta
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.files import append_line_atomic
from slotformer_jax.lock import FileLock
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic

logger = logging.getLogger(__name__)

MODEL_CONFIG_FILE = 'model_config.json'


def stage1_workdir(config: ml_collections.ConfigDict, workdir: str) -> str:
  """Where SAVi and the extracted slots live: `config.stage1_workdir` when
  set (stage-2 ablations reuse one stage 1, read-only), else the run's own
  workdir."""
  return config.get('stage1_workdir') or workdir


def uses_foreign_stage1(config: ml_collections.ConfigDict,
                        workdir: str) -> bool:
  """True when stage 1 is read from another workdir (never written there)."""
  other = config.get('stage1_workdir')
  return bool(other) and (os.path.realpath(other)
                          != os.path.realpath(workdir))


def slots_dir(workdir: str, split: str) -> str:
  return os.path.join(workdir, 'slots', split)


def dynamics_dir(workdir: str, name: str = models.SLOTFORMER) -> str:
  """Where stage-2 model `name` keeps checkpoints and logs."""
  return os.path.join(workdir, name)


def eval_dir(workdir: str) -> str:
  return os.path.join(workdir, 'eval')


def render_dir(workdir: str) -> str:
  return os.path.join(workdir, 'render')


def dynamics_model_fields(config: ml_collections.ConfigDict,
                          name: str = models.SLOTFORMER) -> dict[str, Any]:
  """The config values that determine a stage-2 model's parameters."""
  dynamics = models.dynamics_config(config, name).to_dict()
  keys = ['burn_in', 'embed_dim', 'num_layers', 'num_heads', 'mlp_ratio',
          'residual']
  if name == models.SLOTFORMER:
    keys += ['positional_encoding', 'max_context', 'layer_norm_epsilon']
  return json.loads(json.dumps({key: dynamics[key] for key in keys}))


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


def slot_source_for(config: ml_collections.ConfigDict, workdir: str,
                    split: str, video_fields: tuple[str, ...]) -> SlotSource:
  """Extracted slots of `split` served together with `video_fields`."""
  video_source = get_video_source(config.data, split) if video_fields else None
  return SlotSource(slots_dir(stage1_workdir(config, workdir), split),
                    video_source, video_fields)


# --------------------------------------------------------------------------
# Run identity: what each artifact was made from
# --------------------------------------------------------------------------
#
# Every stage folder (savi/, slotformer/, slot_lstm/) holds identity.json:
#   run_id       random, stamped when the stage starts training from scratch
#   fields       the config values that shaped it (`*_identity_fields`)
#   parent       the identity of what it was trained on (dynamics: the SAVi
#                run_id + step whose slots it read), or null
# The slots record the SAVi run_id + step they were extracted with, the
# metrics and pictures record every identity they used. A child whose parent
# changed is rebuilt (slots) or refused (dynamics, evaluation): nothing mixes.

IDENTITY_FILE = 'identity.json'
LOCK_FILE = '.lock'
CONFIG_FILE = 'config.json'
CONFIG_HISTORY_FILE = 'config_history.jsonl'

# Settings that change how a run is observed, not what it computes.
_NOT_SHAPING = ('log_every', 'checkpoint_every', 'stop_check_every',
                'num_workers', 'data_dir')
# Settings that pick a variant with its own folder (vqa/<inputs>_s<seed>/):
# one workdir holds every Aloe input and seed of a comparison.
_VARIANT_SELECTORS = ('vqa.inputs', 'vqa.seed', 'vqa.eval_split')


def _plain(value: Any) -> Any:
  """Tuples -> lists (as JSON stores them), for comparisons."""
  return json.loads(json.dumps(value))


def _shaping(section: dict[str, Any]) -> dict[str, Any]:
  return {key: value for key, value in section.items()
          if key not in _NOT_SHAPING}


def stage_identity_fields(config: ml_collections.ConfigDict,
                          section: str) -> dict[str, Any]:
  """Everything that shapes a stage-1 model trained from the videos with the
  settings of `config[section]` (e.g. 'savi', 'dvae', 'steve'): data, that
  section, the seed."""
  return _plain({'seed': config.seed, 'data': _shaping(config.data.to_dict()),
                 section: _shaping(config[section].to_dict())})


def slots_identity_fields(config: ml_collections.ConfigDict
                          ) -> dict[str, Any]:
  """Besides the slot model that made them: extraction settings and the
  seed (stochastic SAVi samples with it)."""
  extraction = config.extraction.to_dict()
  extraction.pop('splits', None)
  return _plain({'seed': config.seed, 'extraction': extraction})


def dynamics_identity_fields(config: ml_collections.ConfigDict,
                             name: str = models.SLOTFORMER
                             ) -> dict[str, Any]:
  return _plain({'seed': config.seed, name: _shaping(
      models.dynamics_config(config, name).to_dict())})


def fingerprint(fields: dict[str, Any]) -> str:
  return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()
                        ).hexdigest()[:16]


# Fields added after workdirs were made, and the value their absence stands
# for (what the code did before they existed): a workdir whose settings lack
# one is read as having that value, so it stays usable; any other value is a
# change like every other.
ADDED_FIELDS: dict[str, Any] = {
    'vqa.layer_norm_epsilon': 1e-6,
    'vqa.min_lr_fraction': 0.0,
    'readout.layer_norm_epsilon': 1e-6,
    'readout.dropout_rate': 0.0,
    'evaluation.skip_first_frame': False,
}


def flat_differences(old: Any, new: Any, prefix: str = '') -> list[str]:
  """['savi.learning_rate: 0.0002 -> 0.001', ...] between nested dicts (a
  field of `ADDED_FIELDS` absent from `old` at its old value is none)."""
  if isinstance(old, dict) and isinstance(new, dict):
    out = []
    for key in sorted(set(old) | set(new)):
      name = f'{prefix}.{key}' if prefix else key
      if key not in old:
        if name in ADDED_FIELDS and _plain(new[key]) == ADDED_FIELDS[name]:
          continue
        out.append(f'{name}: (absent) -> {new[key]!r}')
      elif key not in new:
        out.append(f'{name}: {old[key]!r} -> (absent)')
      else:
        out += flat_differences(old[key], new[key], name)
    return out
  return [] if old == new else [f'{prefix}: {old!r} -> {new!r}']


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


def checked_identity(directory: str, fields: dict[str, Any], what: str,
                     workdir: str, train_mode: str) -> dict[str, Any]:
  """The identity of the stage in `directory`, made with `fields`.

  Raises:
    MissingInputError: the stage has no identity (never trained).
    UserError: it was trained with other settings (the fields are listed).
  """
  identity = read_identity(directory)
  if identity is None:
    raise MissingInputError(
        f'no trained {what} in {directory}. Train it first: python -m '
        f'slotformer_jax.main --config=<config> --workdir={workdir} '
        f'--mode={train_mode}')
  check_identity_fields(identity, fields, what, directory)
  return identity


def slots_parent(identity: dict[str, Any], step: int,
                 stage: str) -> dict[str, Any]:
  """What slots (and the dynamics trained on them) descend from: the run id
  and step of the stage-1 model `stage` ('savi', 'steve') that made them."""
  return {f'{stage}_run_id': identity['run_id'], f'{stage}_step': int(step)}


def check_slots_current(config: ml_collections.ConfigDict, workdir: str,
                        split: str, expected: dict[str, Any], what: str
                        ) -> dict[str, Any]:
  """The slots of `split` must descend from `expected` (the slot model's
  `Loaded.slots_parent`; `what` names that model); returns their parent.

  Raises:
    UserError: missing or stale slots, with the command that rebuilds them.
  """
  directory = slots_dir(stage1_workdir(config, workdir), split)
  meta = read_meta(directory)
  rebuild = ('python -m slotformer_jax.main --config=<config> '
             f'--workdir={stage1_workdir(config, workdir)} '
             '--mode=extract_slots')
  if not (meta and meta.get('complete')):
    raise MissingInputError(f'no complete slots in {directory}; extract them: '
                    f'{rebuild}')
  if (meta.get('parent') != expected
      or meta.get('fields') != slots_identity_fields(config)):
    raise UserError(
        f'the slots in {directory} are stale: made by {what} '
        f'{meta.get("parent")}, the current {what} is {expected}. Re-extract '
        f'them: {rebuild}')
  return expected


def check_identity_fields(identity: dict[str, Any], fields: dict[str, Any],
                          what: str, directory: str) -> None:
  changes = flat_differences(identity['fields'], fields)
  if changes:
    raise UserError(
        f'the {what} in {directory} was made with other settings '
        f'({"; ".join(changes[:8])}'
        f'{f"; and {len(changes) - 8} more" if len(changes) > 8 else ""}). '
        'Use the settings it was made with, or another --workdir.')


# --------------------------------------------------------------------------
# The settings of a workdir
# --------------------------------------------------------------------------


def accept_config(config: ml_collections.ConfigDict, workdir: str, *,
                  allow_change: bool = False) -> list[str]:
  """Checks `config` against the settings the workdir was run with; records
  them in config.json (the old ones go to config_history.jsonl).

  Returns the changed fields (empty for a new workdir or the same settings).

  Raises:
    UserError: settings changed and `allow_change` is False.
  """
  path = os.path.join(workdir, CONFIG_FILE)
  current = _plain(config.to_dict())
  changes = []
  if os.path.exists(path):
    saved = read_json(path, fix=f'Restore it from {CONFIG_HISTORY_FILE} or '
                      'delete it to accept the current settings.')
    changes = [c for c in flat_differences(saved, current)
               if not _only_observation(c)]
    if changes and not allow_change:
      raise UserError(
          f'{workdir} was run with other settings: {"; ".join(changes)}. '
          'Use a new --workdir for new settings, or pass '
          '--allow_config_change to accept them here (stages they affect '
          'are then retrained or re-extracted; old checkpoints are kept as '
          '<stage>.stale-<run id>).')
  if jax.process_index() == 0 and (changes or not os.path.exists(path)):
    if changes:
      append_line_atomic(
          os.path.join(workdir, CONFIG_HISTORY_FILE), json.dumps(
              {'replaced': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
               'changes': changes, 'config': saved}))
    write_json_atomic(path, current)
  return changes


def _only_observation(change: str) -> bool:
  name = change.split(':', 1)[0]
  last = name.rsplit('.', 1)[-1]
  # The pictures', the explorer's and the logging settings (a whole section
  # too: a workdir from before the explorer has no `explore` section).
  return (last in _NOT_SHAPING or name in ('render', 'explore', 'logging')
          or name.startswith(('render.', 'explore.', 'logging.'))
          or name in _VARIANT_SELECTORS)


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
    # trained with under config.json (which accept_config checked).
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
# The workdir lock: one writer at a time (see lock.py)
# --------------------------------------------------------------------------


def workdir_lock(workdir: str) -> FileLock:
  return FileLock(os.path.join(workdir, LOCK_FILE),
                  what=f'the workdir {workdir}',
                  fix='give a --workdir you can write')


def evaluation_identity(config: ml_collections.ConfigDict, workdir: str,
                        split: str, stage1: dict[str, Any],
                        slots_parent: dict[str, Any], what: str,
                        dynamics_steps: dict[str, int]) -> dict[str, Any]:
  """What an evaluation (metrics, pictures) is made from; checks that the
  slot model, the slots of `split` and every dynamics model descend from
  each other.

  Args:
    stage1: the slot model's own identity entries (`Loaded.identity`).
    slots_parent: what its slots descend from (`Loaded.slots_parent`).
    what: the slot model's name in messages ('SAVi').
    dynamics_steps: {dynamics model name: step} of the loaded checkpoints.

  Raises:
    UserError: something is stale; the message names the stage to rerun.
  """
  parent = check_slots_current(config, workdir, split, slots_parent, what)
  out = {**stage1, 'slots': parent}
  for name, step in dynamics_steps.items():
    directory = dynamics_dir(workdir, name)
    identity = read_identity(directory)
    retrain = ('python -m slotformer_jax.main --config=<config> '
               f'--workdir={workdir} --mode=train_{name}')
    if identity is None:
      raise UserError(f'{directory} has no identity.json: it is from an '
                      f'older version or incomplete; retrain it: {retrain}')
    check_identity_fields(identity, dynamics_identity_fields(config, name),
                          name, directory)
    if identity.get('parent') != parent:
      raise UserError(
          f'{name} in {directory} was trained on the slots of {what} '
          f'{identity.get("parent")}, but stage 1 is now {parent}; '
          f'evaluating would mix them. Retrain it (it is set aside and '
          f'retrained): {retrain}')
    out[name] = {'run_id': identity['run_id'], 'step': int(step),
                 'fingerprint': identity['fingerprint'], 'parent': parent}
  return out
