r"""Imports the authors' released PyTorch checkpoints into a workdir.

  python -m slotformer_jax.official.convert --config=configs/obj3d.py \
      --workdir=runs/obj3d_official \
      --checkpoint=pretrained/savi_obj3d_params/model_40.pth \
      --checkpoint=pretrained/slotformer_obj3d_params/model_200.pth

Each checkpoint's family (SAVi / stochastic SAVi, SlotFormer, dVAE, STEVE,
SlotFormer on STEVE slots, Aloe, the Physion and PHYRE readouts) is
recognised from its keys, and its parameters go where the pipeline reads
them, so ``extract_slots``, ``evaluate``, ``render``, ``evaluate_vqa``,
``evaluate_readout`` and ``plan`` run on them unchanged. The frozen copies a
later checkpoint carries must equal what the workdir already holds; the
optimizer state is not converted. Every family, command and check:
docs/official_weights.md.
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

from slotformer_jax import datasets
from slotformer_jax import dynamics
from slotformer_jax.config import checks as config_checks
from slotformer_jax.errors import UserError
from slotformer_jax.errors import printable
from slotformer_jax.files import write_json_atomic
from slotformer_jax.official import aloe as official_aloe
from slotformer_jax.official import common
from slotformer_jax.official import families
from slotformer_jax.official import readouts as official_readouts
from slotformer_jax.official import pth_reader
from slotformer_jax.run import Run
from slotformer_jax.slot_models import chain
from slotformer_jax.train import optim
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.trainer import checkpointer_for
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.lock import workdir_lock
from slotformer_jax.workdir.settings import accept_config

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
  """The official models of a dataset saw the frames of its spec's
  `official_channel_order` (CLEVRER's BGR, read with OpenCV; OBJ3D's,
  PHYRE's and Physion's RGB): refuse the other order."""
  channel_order = config.data.channel_order
  dataset = datasets.DATASETS.get(config.data.name)
  official = dataset.official_channel_order if dataset else None
  if official == 'bgr' and channel_order != 'bgr':
    raise common.ConversionError(
        f'the official {config.data.name} models were trained on BGR frames '
        "(OpenCV); add --config.data.channel_order=bgr here and to every "
        'later command on this workdir (the SAVi model config records it)')
  if official == 'rgb' and channel_order != 'rgb':
    raise common.ConversionError(
        f'the official {config.data.name} models were trained on RGB frames '
        f'(read with PIL), not {channel_order!r}; drop '
        '--config.data.channel_order (or set it to rgb)')


def _part(run: Run, stage: str):
  """The slot model's part `stage`, or a ConversionError naming the config
  that has it."""
  try:
    return run.slot_model.part(stage)
  except KeyError:
    raise common.ConversionError(
        f'an official {stage} checkpoint belongs to a slot model with a '
        f'{stage!r} part; this config trains {run.slot_model.label} '
        f'(slot_model={run.slot_model.name!r})') from None


def _stage_target(run: Run, stage: str) -> tuple[str, dict[str, Any],
                                                 ml_collections.ConfigDict]:
  """(directory, model-config fields, stage config) of `stage`."""
  config = run.config
  if stage in (common.DVAE_STAGE, common.STEVE_STAGE, common.SAVI_STAGE):
    part = _part(run, stage)
    return run.paths.model(stage), dict(part.model_fields), part.section
  if stage == official_aloe.ALOE_STAGE:  # vqa/<inputs>_s<seed>/
    return (run.paths.aloe(config.vqa.inputs, config.vqa.seed),
            official_aloe.model_fields(config,
                                       official_aloe.vocabulary(config)),
            config.vqa)
  section = run.dynamics_section(stage)
  return (run.paths.dynamics(stage), dynamics.model_fields(section, stage),
          section)


def write_converted(run: Run, stage: str, params: Any,
                    provenance: dict[str, Any]) -> str:
  """Writes `params` as stage `stage`'s checkpoint; returns its directory.

  The one place that writes into a workdir: a TrainState at step
  `num_train_steps` of the stage (so training counts it as finished and
  evaluation does not warn), a fresh Adam state, the stage's
  model_config.json, and `converted_from.json` naming the source file.

  Raises:
    FileExistsError: the stage already has a checkpoint (never overwritten).
  """
  directory, fields, stage_config = _stage_target(run, stage)
  checkpointer = checkpointer_for(directory)
  try:
    if checkpointer.latest_step() is not None:
      raise FileExistsError(
          f'{directory} already holds a {stage} checkpoint (step '
          f'{checkpointer.latest_step()}); convert into a fresh --workdir')
    identity_lib.check_model_config(directory, fields, stage)
    identity_lib.write_model_config(directory, fields)
    identity_lib.write_identity(directory, _identity(run, stage))
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


def _identity(run: Run, stage: str) -> dict[str, Any]:
  """The run identity the pipeline checks, as training would stamp it: a
  converted SAVi or dVAE is a new run without parent; STEVE descends from
  the workdir's dVAE at its last step, a SlotFormer from the workdir's SAVi
  or STEVE at its last step (the slots extracted later name the same
  parent)."""
  config = run.config
  if stage in (common.DVAE_STAGE, common.STEVE_STAGE, common.SAVI_STAGE):
    part = _part(run, stage)
    parent = None
    if part.parent is not None:
      parent_part = run.slot_model.part(part.parent)
      parent = identity_lib.parent_of(
          chain.part_identity(parent_part, run.paths),
          int(parent_part.section.num_train_steps), parent_part.name)
    return identity_lib.new_identity(dict(part.identity_fields), parent)
  if stage == official_aloe.ALOE_STAGE:
    return identity_lib.new_identity(
        _section_fields(config, 'vqa'), _slots_parent_if_any(run))
  if stage in official_readouts.READOUT_STAGES:
    return identity_lib.new_identity(
        _section_fields(config, 'readout'), _slots_parent_if_any(run))
  last = run.slot_model.parts[-1]
  parent = identity_lib.parent_of(
      chain.part_identity(last, run.paths),
      int(last.section.num_train_steps), last.name)
  return identity_lib.new_identity(
      dynamics.identity_fields(config.seed, run.dynamics_section(stage),
                               stage), parent)


def _section_fields(config: ml_collections.ConfigDict,
                    section: str) -> dict[str, Any]:
  return json.loads(json.dumps({'seed': config.seed,
                                section: config[section].to_dict()}))


def _slots_parent_if_any(run: Run) -> dict[str, Any] | None:
  """What a converted Aloe or readout reads the slots of: the workdir's
  SlotFormer (its rollouts) at its last step, else its stage-1 model, else
  None (the workdir holds neither yet; the official model was trained on
  the authors' slots)."""
  last = run.slot_model.parts[-1]
  for directory, name, step in (
      (run.paths.dynamics(common.SLOTFORMER_STAGE), common.SLOTFORMER_STAGE,
       run.config.slotformer.num_train_steps),
      (run.paths.model(last.name), last.name, last.section.num_train_steps)):
    identity = identity_lib.read_identity(directory)
    if identity is not None:
      return identity_lib.parent_of(identity, int(step), name)
  return None


def _sha256(path: str) -> str:
  digest = hashlib.sha256()
  with open(path, 'rb') as f:
    for block in iter(lambda: f.read(1 << 20), b''):
      digest.update(block)
  return digest.hexdigest()


def check_frozen_decoder(run: Run, decoder: Any) -> None:
  """SlotFormer's frozen decoder copy must be the workdir's SAVi decoder."""
  directory = run.paths.model(common.SAVI_STAGE)
  try:
    savi_params, _ = chain.load_part(_part(run, common.SAVI_STAGE),
                                     run.paths, run.mesh)
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


# extras key -> (what it is a copy of, the checkpoint to convert first, the
# part holding it, its sub-tree there or None).
_FROZEN_COPIES = {
    'dvae': ('dVAE', 'dvae_physion_params/model_20.pth', common.DVAE_STAGE,
             None),
    'steve_decoder': ("STEVE's token decoder",
                      'steve_physion_params/model_10.pth',
                      common.STEVE_STAGE, 'decoder'),
}


def check_frozen_copy(run: Run, key: str, copy: Any, family: str) -> None:
  """A frozen module copy inside a STEVE / STEVESlotFormer checkpoint must
  equal, bit for bit, the one the workdir already holds (the same official
  run), since the pipeline uses the workdir's."""
  what, source, stage, subtree = _FROZEN_COPIES[key]
  try:
    held, _ = chain.load_part(_part(run, stage), run.paths, run.mesh)
  except FileNotFoundError as error:
    raise common.ConversionError(
        f'the official {family} checkpoint carries a frozen copy of the '
        f'{what}, but {run.paths.root} has no {what} checkpoint yet: convert '
        f'{source} first (or in the same command)') from error
  if subtree is not None:
    held = held[subtree]
  worst = common.max_difference(held, copy)
  if worst > 0:
    raise common.ConversionError(
        f'the official {family} checkpoint\'s frozen copy of the {what} '
        f'differs from the {what} in {run.paths.root} (max |diff| '
        f'{worst:.3g}): it was trained with another {what} checkpoint than '
        f'{source}')


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
  run = Run.create(config, workdir, mesh=jax.sharding.Mesh(
      np.array(jax.devices()[:1]), ('data',)))
  with workdir_lock(run.paths):
    # Later pipeline commands on this workdir must use the same settings.
    accept_config(config.to_dict(), run.paths)
    return [_write(run, path, result, readout_threshold)
            for path, result in converted]


def _write(run: Run, path: str, result: Any,
           readout_threshold: float = DEFAULT_READOUT_THRESHOLD) -> str:
  if 'decoder' in result.extras:
    check_frozen_decoder(run, result.extras['decoder'])
  for key in ('dvae', 'steve_decoder'):
    if key in result.extras:
      check_frozen_copy(run, key, result.extras[key], result.family)
  provenance = {
      'file': os.path.abspath(path), 'sha256': _sha256(path),
      'family': result.family,
      'converted_at': datetime.datetime.now(datetime.timezone.utc)
                      .isoformat(timespec='seconds'),
  }
  if result.stage in official_readouts.READOUT_STAGES:
    directory = official_readouts.write_readout(
        run.config, run.paths, result.stage, result.params, provenance,
        _identity(run, result.stage), readout_threshold)
  else:
    directory = write_converted(run, result.stage, result.params, provenance)
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
