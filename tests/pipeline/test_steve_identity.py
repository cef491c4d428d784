"""Run identities of the STEVE stages (fast: identity files only, no model).

The chain dVAE -> tokens -> STEVE -> slots -> SlotFormer -> evaluation is
checked link by link: each test builds a consistent chain, then breaks one
link (as retraining that stage would) and expects the stage below it to be
refused. `test_pipeline_end_to_end` checks the same chain as the real stages
write it.
"""

import os

import pytest

from slotformer_jax import models
from slotformer_jax.slot_models import steve as steve_slots
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import tokens as tokens_lib
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from pipeline_helpers import load_config

DVAE_STEP, STEVE_STEP = 4, 6


def _stamp(directory, fields, parent):
  identity = workdir_lib.new_identity(fields, parent)
  workdir_lib.write_identity(directory, identity)
  return identity


def _chain(config, workdir):
  """A consistent dVAE -> tokens -> STEVE -> slots -> SlotFormer chain."""
  dvae = _stamp(steve_slots.dvae_dir(workdir),
                steve_slots.dvae_identity_fields(config), None)
  dvae_parent = steve_slots.dvae_parent(dvae, DVAE_STEP)
  writer = tokens_lib.TokenWriter(steve_slots.tokens_dir(workdir, 'train'),
                                  0, 4, DVAE_STEP, parent=dvae_parent)
  writer.close()
  steve = _stamp(steve_slots.steve_dir(workdir),
                 steve_slots.steve_identity_fields(config), dvae_parent)
  slots_parent = workdir_lib.slots_parent(steve, STEVE_STEP, 'steve')
  for split in ('train', config.evaluation.split):
    SlotWriter(workdir_lib.slots_dir(workdir, split), 0, 2, 3, STEVE_STEP,
               parent=slots_parent,
               fields=workdir_lib.slots_identity_fields(config)).close()
  _stamp(workdir_lib.dynamics_dir(workdir, models.SLOTFORMER),
         workdir_lib.dynamics_identity_fields(config, models.SLOTFORMER),
         slots_parent)
  return dvae_parent, slots_parent


def _evaluation_identity(config, workdir):
  slot_model = steve_slots.Steve(config)
  stage1, slots_parent = slot_model.chain(
      workdir, {'dvae': DVAE_STEP, 'steve': STEVE_STEP})
  return workdir_lib.evaluation_identity(
      config, workdir, config.evaluation.split, stage1, slots_parent,
      slot_model.label, {models.SLOTFORMER: 3})


@pytest.fixture
def chain(tmp_path):
  config = load_config('synthetic', 'steve_tiny')
  workdir = str(tmp_path / 'run')
  return (config, workdir, *_chain(config, workdir))


def test_consistent_chain_is_accepted_and_recorded(chain):
  config, workdir, dvae_parent, slots_parent = chain
  steve_slots.check_tokens_current(config, workdir, 'train', dvae_parent)
  identity = _evaluation_identity(config, workdir)
  assert identity['steve']['parent'] == dvae_parent
  assert identity['slots'] == slots_parent
  assert identity[models.SLOTFORMER]['parent'] == slots_parent
  assert set(slots_parent) == {'steve_run_id', 'steve_step'}


def test_retrained_dvae_makes_tokens_and_steve_stale(chain):
  config, workdir, _, _ = chain
  new = _stamp(steve_slots.dvae_dir(workdir),
               steve_slots.dvae_identity_fields(config), None)
  parent = steve_slots.dvae_parent(new, DVAE_STEP)
  with pytest.raises(UserError, match='tokens .* are stale'):
    steve_slots.check_tokens_current(config, workdir, 'train', parent)
  with pytest.raises(UserError, match='STEVE .* was trained with dVAE'):
    _evaluation_identity(config, workdir)


def test_another_dvae_step_makes_steve_stale(chain):
  config, workdir, _, _ = chain
  with pytest.raises(UserError, match='trained with dVAE'):
    steve_slots.check_steve_current(config, workdir, DVAE_STEP + 1)


def test_retrained_steve_makes_slots_stale(chain):
  config, workdir, dvae_parent, _ = chain
  _stamp(steve_slots.steve_dir(workdir),
         steve_slots.steve_identity_fields(config), dvae_parent)
  with pytest.raises(UserError, match='made by STEVE'):
    _evaluation_identity(config, workdir)


def test_dynamics_on_other_slots_are_refused(chain):
  config, workdir, _, slots_parent = chain
  _stamp(workdir_lib.dynamics_dir(workdir, models.SLOTFORMER),
         workdir_lib.dynamics_identity_fields(config, models.SLOTFORMER),
         dict(slots_parent, steve_step=STEVE_STEP - 1))
  with pytest.raises(UserError, match='evaluating would mix them'):
    _evaluation_identity(config, workdir)


def test_steve_settings_changed_are_refused(chain):
  config, workdir, _, _ = chain
  config.steve.learning_rate *= 2
  with pytest.raises(UserError, match='steve.learning_rate'):
    _evaluation_identity(config, workdir)


def test_missing_stages_name_the_command(tmp_path):
  config = load_config('synthetic', 'steve_tiny')
  with pytest.raises(MissingInputError, match='--mode=train_dvae'):
    steve_slots.dvae_identity(config, str(tmp_path))
  with pytest.raises(MissingInputError, match='--mode=tokenize_frames'):
    steve_slots.check_tokens_current(config, str(tmp_path), 'train', {})


def test_steve_stage_set_aside_when_its_dvae_changes(chain):
  config, workdir, dvae_parent, _ = chain
  directory = steve_slots.steve_dir(workdir)
  old = workdir_lib.read_identity(directory)
  fields = steve_slots.steve_identity_fields(config)
  assert workdir_lib.start_stage(directory, fields, dvae_parent,
                                 'STEVE') == old
  other = dict(dvae_parent, dvae_step=DVAE_STEP + 1)
  new = workdir_lib.start_stage(directory, fields, other, 'STEVE')
  assert new['run_id'] != old['run_id'] and new['parent'] == other
  assert os.path.isdir(f'{directory}.stale-{old["run_id"]}')


def test_other_compute_dtype_is_refused_not_ignored():
  config = load_config('synthetic', 'steve_tiny')
  steve_slots.Steve(config).check_compute_dtype()
  config.compute_dtype = 'bfloat16'
  with pytest.raises(ConfigError, match='not implemented'):
    steve_slots.Steve(config).check_compute_dtype()
