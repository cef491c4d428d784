"""Paths of the STEVE stages and what each of their artifacts was made from.

The STEVE counterpart of the SAVi parts of `workdir.py` (whose generic
helpers it uses). Layout, inside the stage-1 workdir::

    dvae/checkpoints/   dvae/identity.json (parent: null)
    tokens/train/       the frozen dVAE's tokens; meta 'parent' = dVAE run+step
    steve/checkpoints/  steve/identity.json (parent: dVAE run+step)
    slots/<split>/      STEVE's slots; meta 'parent' = STEVE run+step
    slotformer/ ...     identity parent = the STEVE run+step of its slots

Only paths and checks live here (no training code), so evaluation can use it.
"""

from __future__ import annotations

import json
import os
from typing import Any

import ml_collections

from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import tokens as tokens_lib
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError

DVAE = 'dvae'
STEVE = 'steve'


def check_float32(config: ml_collections.ConfigDict) -> None:
  """The STEVE stages compute in float32 only (`compute_dtype` wraps the
  SAVi / SlotFormer losses and evaluator, not STEVE's); refuse rather than
  ignore another setting."""
  if config.get('compute_dtype', 'float32') != 'float32':
    raise ConfigError(
        f'compute_dtype={config.compute_dtype!r} is not implemented for '
        "slot_model='steve'; use --config.compute_dtype=float32")


def dvae_dir(workdir: str) -> str:
  return os.path.join(workdir, DVAE)


def steve_dir(workdir: str) -> str:
  return os.path.join(workdir, STEVE)


def tokens_dir(workdir: str, split: str) -> str:
  return os.path.join(workdir, 'tokens', split)


def _jsonable(fields: dict[str, Any]) -> dict[str, Any]:
  return json.loads(json.dumps(fields))  # tuples -> lists, for comparison


def dvae_model_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """The config values that determine the dVAE's parameters."""
  return _jsonable({'vocab_size': config.dvae.vocab_size,
                    'hidden_size': config.dvae.hidden_size})


def steve_model_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """The config values that determine STEVE's parameters (incl. its dVAE)."""
  steve = config.steve.to_dict()
  fields = {key: steve[key] for key in (
      'num_slots', 'slot_size', 'encoder', 'slot_attention', 'predictor',
      'decoder', 'layer_norm_epsilon')}
  fields['resolution'] = list(config.data.resolution)
  fields['vocab_size'] = config.dvae.vocab_size
  return _jsonable(fields)


def dvae_identity_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """Everything that shapes the dVAE: data, the dvae section, the seed."""
  return workdir_lib.stage_identity_fields(config, 'dvae')


def steve_identity_fields(config: ml_collections.ConfigDict
                          ) -> dict[str, Any]:
  """Everything that shapes STEVE besides its dVAE (recorded as parent)."""
  return workdir_lib.stage_identity_fields(config, 'steve')


def dvae_identity(config: ml_collections.ConfigDict, workdir: str
                  ) -> dict[str, Any]:
  root = workdir_lib.stage1_workdir(config, workdir)
  return workdir_lib.checked_identity(dvae_dir(root),
                                      dvae_identity_fields(config), 'dVAE',
                                      root, 'train_dvae')


def steve_identity(config: ml_collections.ConfigDict, workdir: str
                   ) -> dict[str, Any]:
  root = workdir_lib.stage1_workdir(config, workdir)
  return workdir_lib.checked_identity(steve_dir(root),
                                      steve_identity_fields(config), 'STEVE',
                                      root, 'train_steve')


def dvae_parent(identity: dict[str, Any], step: int) -> dict[str, Any]:
  """What tokens and STEVE descend from: the dVAE run id and step."""
  return {'dvae_run_id': identity['run_id'], 'dvae_step': int(step)}


def check_tokens_current(config: ml_collections.ConfigDict, workdir: str,
                         split: str, parent: dict[str, Any]) -> None:
  """The tokens of `split` must come from the dVAE `parent`.

  Raises:
    UserError: missing or stale tokens, with the command that rebuilds them.
  """
  root = workdir_lib.stage1_workdir(config, workdir)
  directory = tokens_dir(root, split)
  meta = tokens_lib.read_meta(directory)
  rebuild = ('python -m slotformer_jax.main --config=<config> '
             f'--workdir={root} --mode=tokenize_frames')
  if not (meta and meta.get('complete')):
    raise MissingInputError(f'no complete dVAE tokens in {directory}; '
                            f'compute them: {rebuild}')
  if meta.get('parent') != parent:
    raise UserError(
        f'the tokens in {directory} are stale: made by dVAE '
        f'{meta.get("parent")}, the current dVAE is {parent}. Recompute '
        f'them: {rebuild}')


def check_steve_current(config: ml_collections.ConfigDict, workdir: str,
                        dvae_step: int) -> dict[str, Any]:
  """STEVE's identity, checked to descend from the current dVAE at
  `dvae_step`.

  Raises:
    UserError: STEVE was trained with another dVAE (retrain it).
  """
  parent = dvae_parent(dvae_identity(config, workdir), dvae_step)
  identity = steve_identity(config, workdir)
  if identity.get('parent') != parent:
    raise UserError(
        f'STEVE in {steve_dir(workdir_lib.stage1_workdir(config, workdir))} '
        f'was trained with dVAE {identity.get("parent")}, the current dVAE '
        f'is {parent}; using both would mix them. Retrain STEVE (it is set '
        'aside and retrained): python -m slotformer_jax.main '
        f'--config=<config> --workdir={workdir} --mode=train_steve')
  return identity


def evaluation_identity(config: ml_collections.ConfigDict, workdir: str,
                        split: str, dvae_step: int, steve_step: int,
                        dynamics_steps: dict[str, int]) -> dict[str, Any]:
  """What a STEVE evaluation (metrics, pictures) is made from; checks that
  the dVAE, STEVE, the slots of `split` and every dynamics model descend from
  each other.

  Raises:
    UserError: something is stale; the message names the stage to rerun.
  """
  dvae = dvae_identity(config, workdir)
  steve = check_steve_current(config, workdir, dvae_step)
  parent = workdir_lib.check_slots_current(config, workdir, split, steve,
                                           steve_step, 'steve')
  out = {'dvae': {'run_id': dvae['run_id'], 'step': int(dvae_step),
                  'fingerprint': dvae['fingerprint']},
         'steve': {'run_id': steve['run_id'], 'step': int(steve_step),
                   'fingerprint': steve['fingerprint'],
                   'parent': steve['parent']},
         'slots': parent}
  for name, step in dynamics_steps.items():
    directory = workdir_lib.dynamics_dir(workdir, name)
    identity = workdir_lib.read_identity(directory)
    retrain = ('python -m slotformer_jax.main --config=<config> '
               f'--workdir={workdir} --mode=train_{name}')
    if identity is None:
      raise UserError(f'{directory} has no identity.json: it is from an '
                      f'older version or incomplete; retrain it: {retrain}')
    workdir_lib.check_identity_fields(
        identity, workdir_lib.dynamics_identity_fields(config, name), name,
        directory)
    if identity.get('parent') != parent:
      raise UserError(
          f'{name} in {directory} was trained on the slots of STEVE '
          f'{identity.get("parent")}, but stage 1 is now {parent}; '
          f'evaluating would mix them. Retrain it (it is set aside and '
          f'retrained): {retrain}')
    out[name] = {'run_id': identity['run_id'], 'step': int(step),
                 'fingerprint': identity['fingerprint'], 'parent': parent}
  return out
