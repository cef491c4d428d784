r"""Imports the authors' released PyTorch checkpoints into a workdir.

  python -m slotformer_jax.official.convert --config=configs/obj3d.py \
      --workdir=runs/obj3d_official \
      --checkpoint=pretrained/savi_obj3d_params/model_40.pth \
      --checkpoint=pretrained/slotformer_obj3d_params/model_200.pth

  python -m slotformer_jax.official.convert --config=configs/physion.py \
      --workdir=runs/physion_official \
      --checkpoint=pretrained/dvae_physion_params/model_20.pth \
      --checkpoint=pretrained/steve_physion_params/model_10.pth \
      --checkpoint=pretrained/slotformer_physion_params/model_25.pth

  python -m slotformer_jax.official.convert --config=configs/clevrer_vqa.py \
      --config.data.channel_order=bgr --workdir=runs/clevrer_official \
      --config.vqa.vocab_file=CLEVRER_vocab.json \
      --checkpoint=pretrained/aloe_clevrer_params-rollout/model_400.pth

Each checkpoint's family (SAVi / stochastic SAVi, SlotFormer, dVAE, STEVE,
SlotFormer on STEVE slots, Aloe, the Physion and PHYRE readouts) is
recognised from its keys; the converted parameters go where the pipeline
reads them (`savi/`, `dvae/`, `steve/`, `slotformer/` checkpoints, each with
its `model_config.json` and run identity; Aloe in the VQA variant folder
`vqa/<inputs>_s<seed>/` the config selects; a readout in
`readout/<condition>/seed_<s>/` or `planning/<condition>/seed_<s>/`), so
`--mode=extract_slots`, `evaluate`, `render`, `evaluate_vqa`,
`evaluate_readout` and `plan` run on them unchanged. Stage-1 checkpoints
are written first (dVAE before STEVE); the frozen copies a later checkpoint
carries (SlotFormer's SAVi decoder, STEVE's dVAE, STEVESlotFormer's dVAE and
token decoder) must equal what the workdir already holds.
Reading `.pth` needs no torch (see official/pth_reader.py). The official
optimizer state is not converted: a converted stage starts a fresh Adam state
at its last step, so training does not resume it.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
import os
import sys
from typing import Any

from absl import app
from absl import flags
from absl import logging as absl_logging
import jax
import jax.numpy as jnp
import ml_collections
from ml_collections import config_flags
import numpy as np

from slotformer_jax import models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.config import checks as config_checks
from slotformer_jax.errors import UserError
from slotformer_jax.errors import printable
from slotformer_jax.files import write_json_atomic
from slotformer_jax.official import aloe as official_aloe
from slotformer_jax.official import common
from slotformer_jax.official import families
from slotformer_jax.official import readouts as official_readouts
from slotformer_jax.official import pth_reader
from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.slot_models import steve as steve_slots
from slotformer_jax.stages import vqa as vqa_stages
from slotformer_jax.train import optim
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.trainer import checkpointer_for

# Not __name__: that is '__main__' under python -m.
logger = logging.getLogger('slotformer_jax.official.convert')


# Provenance of a converted stage, beside its model_config.json.
CONVERTED_FROM_FILE = 'converted_from.json'

# The order in which checkpoints are written: each stage before the ones
# whose frozen copies are checked against it (and whose identity names it as
# parent).
_ORDER = (common.DVAE_STAGE, common.STEVE_STAGE, common.SAVI_STAGE,
          common.SLOTFORMER_STAGE,
          official_aloe.ALOE_STAGE) + official_readouts.READOUT_STAGES

DEFAULT_READOUT_THRESHOLD = official_readouts.DEFAULT_THRESHOLD


def check_channel_order(config: ml_collections.ConfigDict) -> None:
  """The official CLEVRER models saw BGR frames: refuse RGB; the other
  official models (OBJ3D, PHYRE, Physion) saw RGB: refuse BGR."""
  channel_order = config.data.get('channel_order', 'rgb')
  if config.data.name in common.BGR_DATASETS and channel_order != 'bgr':
    raise common.ConversionError(
        f'the official {config.data.name} models were trained on BGR frames '
        "(OpenCV); add --config.data.channel_order=bgr here and to every "
        'later command on this workdir (the SAVi model config records it)')
  if (config.data.name in common.RGB_DATASETS
      and channel_order != 'rgb'):
    raise common.ConversionError(
        f'the official {config.data.name} models were trained on RGB frames '
        f'(read with PIL), not {channel_order!r}; drop '
        '--config.data.channel_order (or set it to rgb)')


def _stage_target(config: ml_collections.ConfigDict, workdir: str,
                  stage: str) -> tuple[str, dict[str, Any],
                                       ml_collections.ConfigDict]:
  """(directory, model-config fields, stage config) of `stage`."""
  root = workdir_lib.stage1_workdir(config, workdir)
  if stage == common.DVAE_STAGE:
    return (steve_slots.dvae_dir(root),
            steve_slots.dvae_model_fields(config), config.dvae)
  if stage == common.STEVE_STAGE:
    return (steve_slots.steve_dir(root),
            steve_slots.steve_model_fields(config), config.steve)
  if stage == common.SAVI_STAGE:
    return (savi_slots.savi_dir(root), savi_slots.model_fields(config),
            config.savi)
  if stage == official_aloe.ALOE_STAGE:  # vqa/<inputs>_s<seed>/
    return (vqa_stages.variant_dir(config, workdir),
            official_aloe.model_fields(config,
                                       official_aloe.vocabulary(config)),
            config.vqa)
  return (workdir_lib.dynamics_dir(workdir, stage),
          workdir_lib.dynamics_model_fields(config, stage),
          models.dynamics_config(config, stage))


def write_converted(config: ml_collections.ConfigDict, workdir: str,
                    stage: str, params: Any, provenance: dict[str, Any]
                    ) -> str:
  """Writes `params` as stage `stage`'s checkpoint; returns its directory.

  The one place that writes into a workdir: a TrainState at step
  `num_train_steps` of the stage (so training counts it as finished and
  evaluation does not warn), a fresh Adam state, the stage's
  model_config.json, and `converted_from.json` naming the source file.

  Raises:
    FileExistsError: the stage already has a checkpoint (never overwritten).
  """
  directory, fields, stage_config = _stage_target(config, workdir, stage)
  checkpointer = checkpointer_for(directory)
  try:
    if checkpointer.latest_step() is not None:
      raise FileExistsError(
          f'{directory} already holds a {stage} checkpoint (step '
          f'{checkpointer.latest_step()}); convert into a fresh --workdir')
    workdir_lib.check_model_config(directory, fields, stage)
    workdir_lib.write_model_config(directory, fields)
    identity = _identity(config, workdir, stage)
    workdir_lib.write_identity(directory, identity)
    optimizer, _ = optim.make_optimizer(stage_config)
    params = jax.tree.map(jnp.asarray, params)
    step = int(stage_config.num_train_steps)
    state = TrainState.create(params, optimizer).replace(
        step=jnp.asarray(step, jnp.int32))
    checkpointer.save(step, state, force=True)
    checkpointer.wait_until_finished()
  finally:
    checkpointer.close()
  if jax.process_index() == 0:
    write_json_atomic(os.path.join(directory, CONVERTED_FROM_FILE),
                      provenance)
  return directory


def _identity(config: ml_collections.ConfigDict, workdir: str,
              stage: str) -> dict[str, Any]:
  """The run identity the pipeline checks, as training would stamp it: a
  converted SAVi or dVAE is a new run without parent; STEVE descends from
  the workdir's dVAE at its last step, a SlotFormer from the workdir's SAVi
  or STEVE at its last step (the slots extracted later name the same
  parent)."""
  if stage == common.DVAE_STAGE:
    return workdir_lib.new_identity(steve_slots.dvae_identity_fields(config))
  if stage == common.STEVE_STAGE:
    return workdir_lib.new_identity(
        steve_slots.steve_identity_fields(config),
        steve_slots.dvae_parent(steve_slots.dvae_identity(config, workdir),
                                int(config.dvae.num_train_steps)))
  if stage == common.SAVI_STAGE:
    return workdir_lib.new_identity(savi_slots.identity_fields(config))
  if stage == official_aloe.ALOE_STAGE:
    return workdir_lib.new_identity(
        _section_fields(config, 'vqa'), _slots_parent_if_any(config, workdir))
  if stage in official_readouts.READOUT_STAGES:
    return workdir_lib.new_identity(
        _section_fields(config, 'readout'),
        _slots_parent_if_any(config, workdir))
  if config.slot_model == steve_slots.NAME:
    parent = workdir_lib.slots_parent(
        steve_slots.steve_identity(config, workdir),
        int(config.steve.num_train_steps), steve_slots.NAME)
  else:
    parent = workdir_lib.slots_parent(
        savi_slots.Savi(config).check_identity(workdir),
        int(config.savi.num_train_steps), savi_slots.NAME)
  return workdir_lib.new_identity(
      workdir_lib.dynamics_identity_fields(config, stage), parent)


def _section_fields(config: ml_collections.ConfigDict,
                    section: str) -> dict[str, Any]:
  return json.loads(json.dumps({'seed': config.seed,
                                section: config[section].to_dict()}))


def _slots_parent_if_any(config: ml_collections.ConfigDict,
                         workdir: str) -> dict[str, Any] | None:
  """What a converted Aloe or readout reads the slots of: the workdir's
  SlotFormer (its rollouts) at its last step, else its stage-1 model, else
  None (the workdir holds neither yet; the official model was trained on
  the authors' slots)."""
  stage1 = workdir_lib.stage1_workdir(config, workdir)
  if config.get('slot_model', 'savi') == steve_slots.NAME:
    slot_model = (steve_slots.steve_dir(stage1), steve_slots.NAME,
                  config.steve.num_train_steps)
  else:
    slot_model = (savi_slots.savi_dir(stage1), savi_slots.NAME,
                  config.savi.num_train_steps)
  for directory, name, step in (
      (workdir_lib.dynamics_dir(workdir), common.SLOTFORMER_STAGE,
       config.slotformer.num_train_steps), slot_model):
    identity = workdir_lib.read_identity(directory)
    if identity is not None:
      return workdir_lib.slots_parent(identity, int(step), name)
  return None


def _sha256(path: str) -> str:
  digest = hashlib.sha256()
  with open(path, 'rb') as f:
    for block in iter(lambda: f.read(1 << 20), b''):
      digest.update(block)
  return digest.hexdigest()


def check_frozen_decoder(config: ml_collections.ConfigDict, workdir: str,
                         decoder: Any) -> None:
  """SlotFormer's frozen decoder copy must be the workdir's SAVi decoder."""
  directory = savi_slots.savi_dir(
      workdir_lib.stage1_workdir(config, workdir))
  mesh = jax.sharding.Mesh(np.array(jax.devices()[:1]), ('data',))
  try:
    savi_params = savi_slots.Savi(config).load(workdir, mesh).params
  except FileNotFoundError as error:
    raise common.ConversionError(
        f'no SAVi checkpoint in {directory}: convert the SAVi checkpoint the '
        'SlotFormer was trained on first (or in the same command, e.g. '
        'savi_obj3d_params/model_40.pth before slotformer_obj3d_params/...)'
    ) from error
  flat_savi = common.flatten(savi_params['decoder'])
  flat_copy = common.flatten(decoder)
  worst = max(float(np.max(np.abs(np.asarray(flat_savi[k]) - flat_copy[k])))
              for k in flat_copy)
  if worst > 0:
    raise common.ConversionError(
        f'the SlotFormer checkpoint\'s frozen decoder differs from the SAVi '
        f'decoder in {directory} (max |diff| {worst:.3g}): it was trained '
        'on another SAVi checkpoint')


# extras key -> (what it is a copy of, the checkpoint to convert first, how
# to read the workdir's own from (config, workdir, mesh)).
_FROZEN_COPIES = {
    'dvae': ('dVAE', 'dvae_physion_params/model_20.pth',
             lambda config, workdir, mesh: steve_slots.Steve(
                 config).load_dvae(workdir, mesh)[0]),
    'steve_decoder': ("STEVE's token decoder",
                      'steve_physion_params/model_10.pth',
                      lambda config, workdir, mesh: steve_slots.Steve(
                          config).load_steve(workdir, mesh)[0]['decoder']),
}


def check_frozen_copy(config: ml_collections.ConfigDict, workdir: str,
                      key: str, copy: Any, family: str) -> None:
  """A frozen module copy inside a STEVE / STEVESlotFormer checkpoint must
  equal, bit for bit, the one the workdir already holds (the same official
  run), since the pipeline uses the workdir's."""
  what, source, load = _FROZEN_COPIES[key]
  mesh = jax.sharding.Mesh(np.array(jax.devices()[:1]), ('data',))
  try:
    held = load(config, workdir, mesh)
  except FileNotFoundError as error:
    raise common.ConversionError(
        f'the official {family} checkpoint carries a frozen copy of the '
        f'{what}, but {workdir} has no {what} checkpoint yet: convert '
        f'{source} first (or in the same command)') from error
  worst = common.max_difference(held, copy)
  if worst > 0:
    raise common.ConversionError(
        f'the official {family} checkpoint\'s frozen copy of the {what} '
        f'differs from the {what} in {workdir} (max |diff| {worst:.3g}): it '
        f'was trained with another {what} checkpoint than {source}')


# extras key -> (the stage holding the original, its part of the params).
_COPY_SOURCES = {
    'decoder': (common.SAVI_STAGE, 'decoder'),
    'dvae': (common.DVAE_STAGE, None),
    'steve_decoder': (common.STEVE_STAGE, 'decoder'),
}


def _check_copies_within(converted: list[tuple[str, Any]]) -> None:
  """Frozen copies against the originals converted in the same command,
  before anything is written (`_write` checks them against the workdir)."""
  by_stage = {result.stage: (path, result) for path, result in converted}
  for path, result in converted:
    for key, copy in result.extras.items():
      stage, part = _COPY_SOURCES[key]
      if stage not in by_stage:
        continue
      source, original = by_stage[stage]
      held = original.params if part is None else original.params[part]
      worst = common.max_difference(held, copy)
      if worst > 0:
        raise common.ConversionError(
            f'{path}: its frozen copy of the {stage} '
            f'{"" if part is None else part + " "}differs from {source} '
            f'(max |diff| {worst:.3g}): they are not from the same official '
            'run')


def convert_files(config: ml_collections.ConfigDict, workdir: str,
                  paths: list[str], reader: str = 'auto',
                  readout_threshold: float = DEFAULT_READOUT_THRESHOLD
                  ) -> list[str]:
  """Converts and writes every checkpoint in `paths`; returns directories.

  Every file is read and converted before anything is written, so a file
  that does not convert leaves the workdir untouched."""
  check_channel_order(config)
  converted = []
  for path in paths:
    state_dict = pth_reader.read_state_dict(path, reader)
    result = families.convert_state_dict(state_dict, config)
    logger.info('%s: official %s, %d tensors', path, result.family,
                len(state_dict))
    converted.append((path, result))
  converted.sort(key=lambda item: _ORDER.index(item[1].stage))
  _check_copies_within(converted)
  with workdir_lib.workdir_lock(workdir):
    # Later pipeline commands on this workdir must use the same settings.
    workdir_lib.accept_config(config, workdir)
    return [_write(config, workdir, path, result, readout_threshold)
            for path, result in converted]


def _write(config: ml_collections.ConfigDict, workdir: str, path: str,
           result: Any,
           readout_threshold: float = DEFAULT_READOUT_THRESHOLD) -> str:
  if 'decoder' in result.extras:
    check_frozen_decoder(config, workdir, result.extras['decoder'])
  for key in ('dvae', 'steve_decoder'):
    if key in result.extras:
      check_frozen_copy(config, workdir, key, result.extras[key],
                        result.family)
  provenance = {
      'file': os.path.abspath(path), 'sha256': _sha256(path),
      'family': result.family,
      'converted_at': datetime.datetime.now(datetime.timezone.utc)
                      .isoformat(timespec='seconds'),
  }
  if result.stage in official_readouts.READOUT_STAGES:
    directory = official_readouts.write_readout(
        config, workdir, result.stage, result.params, provenance,
        _identity(config, workdir, result.stage), readout_threshold)
  else:
    directory = write_converted(config, workdir, result.stage, result.params,
                                provenance)
  logger.info('wrote %s', directory)
  return directory


def _define_flags() -> dict[str, Any]:
  """The command's flags. Defined when the command runs, not on import, so
  that importing this module beside `slotformer_jax.main` (which defines
  --config and --workdir too) does not clash."""
  return dict(
      config=config_flags.DEFINE_config_file(
          'config', None, 'The config of the official model, e.g. '
          'configs/obj3d.py.', lock_config=True),
      workdir=flags.DEFINE_string('workdir', None, 'Where to write.',
                                  required=True),
      checkpoints=flags.DEFINE_multi_string(
          'checkpoint', None,
          'An official .pth file (repeat the flag for several).',
          required=True),
      reader=flags.DEFINE_enum(
          'reader', 'auto', ('auto', 'numpy', 'torch'),
          'How to read .pth: numpy (no torch), torch (pip install -e '
          '.[torch]), auto (numpy for zip files).'),
      readout_threshold=flags.DEFINE_float(
          'readout_threshold', DEFAULT_READOUT_THRESHOLD,
          'A converted Physion readout\'s decision threshold on P(contact) '
          '(the official test script prints the one it picked).'),
  )


def main(argv, flag_holders: dict[str, Any]):
  del argv
  # This package's INFO lines only; orbax logs every save step through absl.
  absl_logging.set_verbosity(absl_logging.ERROR)
  handler = logging.StreamHandler()
  handler.setFormatter(logging.Formatter(
      '%(asctime)s %(levelname).1s %(name)s] %(message)s', '%H:%M:%S'))
  package_logger = logging.getLogger('slotformer_jax')
  package_logger.handlers[:] = [handler]
  package_logger.setLevel(logging.INFO)
  package_logger.propagate = False
  config = flag_holders['config'].value
  if config is None:
    raise app.UsageError('--config is required, e.g. configs/obj3d.py')
  try:
    convert_files(config, flag_holders['workdir'].value,
                  flag_holders['checkpoints'].value,
                  flag_holders['reader'].value,
                  flag_holders['readout_threshold'].value)
  except (common.ConversionError, FileExistsError, NotImplementedError,
          UserError) as error:
    # What to change is in the message; a traceback would only hide it.
    # Names from the file are escaped where they are quoted; `printable`
    # keeps anything else a terminal would act on from reaching it.
    sys.exit(f'error: {printable(error)}')


def _check_config_argument(argv: list[str]) -> None:
  """A --config that cannot be loaded, as one line before absl's traceback
  (status 2 for the argument, 1 for the file's own error)."""
  spec = config_checks.config_spec(argv)
  if spec is None:
    return
  try:
    config_checks.load_config_file(spec)
  except UserError as error:
    print(f'error: {printable(error)}', file=sys.stderr)
    sys.exit(2 if isinstance(error, config_checks.ConfigFileError) else 1)


if __name__ == '__main__':
  _holders = _define_flags()
  _check_config_argument(sys.argv[1:])
  app.run(lambda argv: main(argv, _holders))
