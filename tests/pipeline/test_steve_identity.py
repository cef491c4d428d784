"""Run identities of the STEVE stages (fast: identity files only, no model).

The chain dVAE -> tokens -> STEVE -> slots -> SlotFormer -> evaluation is
checked link by link: each test builds a consistent chain, then breaks one
link (as retraining that stage would) and expects the stage below it to be
refused. `test_pipeline_end_to_end` checks the same chain as the real stages
write it.
"""

import os

import pytest

from slotformer_jax.run import Run
from slotformer_jax.slot_models import chain as chain_lib
from slotformer_jax.slot_models import steve as steve_slots
from slotformer_jax.stages import stage1
from slotformer_jax.stages import video_prediction
from slotformer_jax.data import slots as tokens_lib
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from pipeline_helpers import load_config
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.config.sections import dynamics_section
from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax.workdir import identity as identity_lib

SLOTFORMER = 'slotformer'  # the dynamics model's registered name

DVAE_STEP, STEVE_STEP = 4, 6


def _stamp(directory, fields, parent):
  identity = identity_lib.new_identity(fields, parent)
  identity_lib.write_identity(directory, identity)
  return identity


def _fields(config, part):
  return dict(steve_slots.Steve(config).part(part).identity_fields)


def _run(config, workdir):
  return Run.create(config, workdir)


def _check_tokens(config, workdir, split, parent):
  run = _run(config, workdir)
  stage1.check_derived_current(run, run.slot_model.derived[0], split, parent)


def _chain(config, workdir):
  """A consistent dVAE -> tokens -> STEVE -> slots -> SlotFormer chain."""
  dvae = _stamp(Paths.of(workdir).model('dvae'), _fields(config, 'dvae'),
                None)
  dvae_parent = identity_lib.parent_of(dvae, DVAE_STEP, 'dvae')
  writer = tokens_lib.TokenWriter(Paths.of(workdir).derived('tokens', 'train'),
                                  0, 4, DVAE_STEP, parent=dvae_parent)
  writer.close()
  steve = _stamp(Paths.of(workdir).model('steve'), _fields(config, 'steve'),
                 dvae_parent)
  slots_parent = identity_lib.parent_of(steve, STEVE_STEP, 'steve')
  for split in ('train', config.evaluation.split):
    SlotWriter(Paths.of(workdir).slots(split), 0, 2, 3, STEVE_STEP,
               parent=slots_parent,
               fields=identity_lib.slots_fields(config.seed, config.extraction.to_dict())).close()
  _stamp(Paths.of(workdir).dynamics(SLOTFORMER),
         dynamics_lib.identity_fields(config.seed, dynamics_section(config, SLOTFORMER), SLOTFORMER),
         slots_parent)
  return dvae_parent, slots_parent


def _evaluation_identity(config, workdir):
  run = _run(config, workdir)
  identity, slots_parent = chain_lib.chain(
      run.slot_model, run.paths, {'dvae': DVAE_STEP, 'steve': STEVE_STEP})
  return video_prediction.evaluation_identity(run, identity, slots_parent,
                                              {SLOTFORMER: 3})


@pytest.fixture
def chain(tmp_path):
  config = load_config('synthetic', 'steve_tiny')
  workdir = str(tmp_path / 'run')
  return (config, workdir, *_chain(config, workdir))


def test_consistent_chain_is_accepted_and_recorded(chain):
  config, workdir, dvae_parent, slots_parent = chain
  _check_tokens(config, workdir, 'train', dvae_parent)
  identity = _evaluation_identity(config, workdir)
  assert identity['steve']['parent'] == dvae_parent
  assert identity['slots'] == slots_parent
  assert identity[SLOTFORMER]['parent'] == slots_parent
  assert set(slots_parent) == {'steve_run_id', 'steve_step'}


def test_retrained_dvae_makes_tokens_and_steve_stale(chain):
  config, workdir, _, _ = chain
  new = _stamp(Paths.of(workdir).model('dvae'), _fields(config, 'dvae'),
               None)
  parent = identity_lib.parent_of(new, DVAE_STEP, 'dvae')
  with pytest.raises(UserError, match='tokens .* are stale'):
    _check_tokens(config, workdir, 'train', parent)
  with pytest.raises(UserError, match='STEVE .* was trained with dVAE'):
    _evaluation_identity(config, workdir)


def test_another_dvae_step_makes_steve_stale(chain):
  config, workdir, _, _ = chain
  run = _run(config, workdir)
  with pytest.raises(UserError, match='trained with dVAE'):
    chain_lib.chain(run.slot_model, run.paths,
                    {'dvae': DVAE_STEP + 1, 'steve': STEVE_STEP})


def test_retrained_steve_makes_slots_stale(chain):
  config, workdir, dvae_parent, _ = chain
  _stamp(Paths.of(workdir).model('steve'), _fields(config, 'steve'),
         dvae_parent)
  with pytest.raises(UserError, match='made by STEVE'):
    _evaluation_identity(config, workdir)


def test_dynamics_on_other_slots_are_refused(chain):
  config, workdir, _, slots_parent = chain
  _stamp(Paths.of(workdir).dynamics(SLOTFORMER),
         dynamics_lib.identity_fields(config.seed, dynamics_section(config, SLOTFORMER), SLOTFORMER),
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
  run = _run(config, str(tmp_path))
  with pytest.raises(MissingInputError, match='--mode=train_dvae'):
    chain_lib.part_identity(run.slot_model.part('dvae'), run.paths)
  with pytest.raises(MissingInputError, match='--mode=tokenize_frames'):
    _check_tokens(config, str(tmp_path), 'train', {})


def test_steve_stage_set_aside_when_its_dvae_changes(chain):
  config, workdir, dvae_parent, _ = chain
  directory = Paths.of(workdir).model('steve')
  old = identity_lib.read_identity(directory)
  fields = _fields(config, 'steve')
  assert identity_lib.start_stage(directory, fields, dvae_parent,
                                 'STEVE') == old
  other = dict(dvae_parent, dvae_step=DVAE_STEP + 1)
  new = identity_lib.start_stage(directory, fields, other, 'STEVE')
  assert new['run_id'] != old['run_id'] and new['parent'] == other
  assert os.path.isdir(f'{directory}.stale-{old["run_id"]}')


def test_other_compute_dtype_is_refused_not_ignored(tmp_path):
  config = load_config('synthetic', 'steve_tiny')
  Run.create(config, str(tmp_path))
  config.compute_dtype = 'bfloat16'
  with pytest.raises(ConfigError, match='not implemented'):
    Run.create(config, str(tmp_path))
