"""Runs you can trust: one test (or more) per reproduced defect.

1. a foreign `stage1_workdir` is read-only;
2. artifacts record what they were made from, nothing mixes; workdir lock;
3. changed settings on an existing workdir are refused (or recorded);
4. config problems are found before any work, unknown fields in one line;
5. atomic files, verified dataset caches, checkpoint fallback, slot checksums;
6. the NaN guard checks the updated state;
7. failed saves stop at once (SIGTERM and worker cleanup: the slow tests in
   test_reliability_slow.py);
8. anticipated errors are one line on stderr.

The trained micro workdir is built once per module (~1 min on 2 cores) and
copied by the tests that change it.
"""

import dataclasses
import errno
import itertools
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys

import jax
from jax.sharding import Mesh
import ml_collections
import numpy as np
import pytest

from slotformer_jax import datasets

from slotformer_jax.config import checks as config_checks
from slotformer_jax import files
from slotformer_jax.data import integrity
from slotformer_jax.data import sources
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.errors import UserError
from slotformer_jax.workdir.lock import FileLock
from slotformer_jax.runtime import checkpoint as checkpoint_lib
from slotformer_jax.runtime import sharding
from slotformer_jax.train import trainer
from slotformer_jax.train.trainer import Diverged
from slotformer_jax.runtime.preemption import Preempted
from slotformer_jax.train.trainer import fit
from slotformer_jax.data.slots import read_meta
from slotformer_jax.slot_models.savi import Savi

import pipeline_helpers
from pipeline_helpers import check
from slotformer_jax.workdir.lock import workdir_lock
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir import identity as identity_lib
from pipeline_helpers import accept
from linear_stage import linear_stage
from pipeline_helpers import run_stage
from slotformer_jax.slot_models import chain as chain_lib
from slotformer_jax.run import Run

ROOT = os.path.join(os.path.dirname(__file__), '..', '..')


def _config(data_dir):
  config = pipeline_helpers.micro_config('savi', data_dir)
  config.slot_lstm.train = False
  config.evaluation.metrics = ('psnr', 'ari')
  config.evaluation.savi_metrics = False
  return config


def _snapshot(directory):
  """{relative path: (size, mtime_ns)} of every file below `directory`."""
  out = {}
  for root, _, names in os.walk(directory):
    for name in names:
      path = os.path.join(root, name)
      stat = os.stat(path)
      out[os.path.relpath(path, directory)] = (stat.st_size,
                                               stat.st_mtime_ns)
  return out


@pytest.fixture(scope='module')
def trained(tmp_path_factory):
  """(config, workdir) with SAVi, slots and SlotFormer trained."""
  base = tmp_path_factory.mktemp('reliability')
  config = _config(base / 'data')
  workdir = str(base / 'run')
  mesh = sharding.make_mesh()
  run_stage(config, workdir, mesh, 'train_savi')
  run_stage(config, workdir, mesh, 'extract_slots')
  run_stage(config, workdir, mesh, 'train_slotformer')
  return config, workdir


@pytest.fixture
def copied(trained, tmp_path):
  config, workdir = trained
  copy = str(tmp_path / 'copy')
  shutil.copytree(workdir, copy)
  return _config(config.data.data_dir), copy


# --------------------------------------------------------------------------
# 1. stage1_workdir is read-only
# --------------------------------------------------------------------------


def test_foreign_stage1_with_other_settings_is_refused_untouched(
    trained, tmp_path):
  _, other = trained
  before = _snapshot(other)
  config = _config(trained[0].data.data_dir)
  config.stage1_workdir = other
  config.savi.num_train_steps = 6  # OTHER was trained for 4
  mesh = sharding.make_mesh()
  workdir = str(tmp_path / 'ablation')
  for stage in ('train_savi', 'extract_slots'):
    with pytest.raises(UserError, match='num_train_steps: 4 -> 6'):
      run_stage(config, workdir, mesh, stage)
  # main checks this before any data is generated.
  run = Run.create(config, workdir, mesh)
  with pytest.raises(UserError, match='num_train_steps'):
    chain_lib.check_identities(run.slot_model, run.paths)
  assert _snapshot(other) == before


def test_a_foreign_stage1_without_a_split_names_the_splits_it_has(
    trained, tmp_path):
  """Issue 61, case 9: a run reading a Physion contact run's stage 1 was
  told `no complete slots in <contact run>/slots/val; extract them: ...
  --mode=extract_slots`, which with the contact config extracts no val
  (rc 0). What works, reading the splits it has, is named now."""
  config, other = trained
  copy = str(tmp_path / 'contact')
  shutil.copytree(other, copy)
  splits = tuple(config.extraction.splits)
  lacking = splits[-1]
  shutil.rmtree(Paths.of(copy).slots(lacking))
  config = _config(config.data.data_dir)
  config.stage1_workdir = copy
  with pytest.raises(UserError) as error:
    run_stage(config, str(tmp_path / 'prediction'), sharding.make_mesh(),
              'train_savi')
  message = str(error.value)
  assert '\n' not in message
  assert f'has no complete slots of {lacking}' in message, message
  assert (f'--config.extraction.splits="{splits[:-1]}"') in message
  assert '--allow_config_change' in message


@pytest.mark.slow  # trains SlotFormer (~35 s on 2 busy cores)
def test_foreign_stage1_is_used_without_writing_there(trained, tmp_path):
  _, other = trained
  before = _snapshot(other)
  config = _config(trained[0].data.data_dir)
  config.stage1_workdir = other
  config.slotformer.num_train_steps = 2
  workdir = str(tmp_path / 'ablation')
  mesh = sharding.make_mesh()
  run_stage(config, workdir, mesh, 'train_savi')  # checks, trains nothing
  run_stage(config, workdir, mesh, 'extract_slots')
  run_stage(config, workdir, mesh, 'train_slotformer')
  assert _snapshot(other) == before
  assert not os.path.exists(os.path.join(workdir, 'savi'))
  assert os.listdir(os.path.join(workdir, 'slotformer', 'checkpoints'))


# --------------------------------------------------------------------------
# 2. run identity: nothing mixes; the workdir lock
# --------------------------------------------------------------------------


def test_slots_and_dynamics_of_another_savi_are_refused(copied):
  """SAVi retrained to the same step count (here: a new run id stamped on
  it) must not be combined with the slots or SlotFormer of the old one."""
  config, workdir = copied
  mesh = sharding.make_mesh()
  savi = os.path.join(workdir, 'savi')
  identity = identity_lib.read_identity(savi)
  identity_lib.write_identity(savi, dict(identity, run_id='retrained'))
  with pytest.raises(UserError, match='stale'):
    run_stage(config, workdir, mesh, 'train_slotformer')
  with pytest.raises(UserError, match='stale'):
    run_stage(config, workdir, mesh, 'evaluate')
  # Fresh slots of the new SAVi, but the SlotFormer of the old one.
  meta_path = os.path.join(Paths.of(workdir).slots('test'), 'meta.json')
  meta = files.read_json(meta_path)
  meta['parent']['savi_run_id'] = 'retrained'
  files.write_json_atomic(meta_path, meta)
  with pytest.raises(UserError, match='would mix'):
    run_stage(config, workdir, mesh, 'evaluate')


@pytest.mark.slow  # retrains SAVi and SlotFormer (~60 s on 2 busy cores)
def test_retrained_savi_rebuilds_slots_and_refuses_stale_dynamics(copied):
  config, workdir = copied
  mesh = sharding.make_mesh()
  old_parent = read_meta(
      Paths.of(workdir).slots('train'))['parent']
  # Retrain SAVi to the same step count (another learning rate).
  shutil.rmtree(os.path.join(workdir, 'savi'))
  config.savi.learning_rate = 5e-4
  run_stage(config, workdir, mesh, 'train_savi')
  step = Run.create(config, workdir, mesh).stage1.step
  assert step == 4
  # The slots of the old SAVi are not used for anything.
  with pytest.raises(UserError, match='stale'):
    run_stage(config, workdir, mesh, 'train_slotformer')
  run_stage(config, workdir, mesh, 'extract_slots')  # re-extracts: new parent
  new_parent = read_meta(
      Paths.of(workdir).slots('train'))['parent']
  assert new_parent != old_parent and new_parent['savi_step'] == 4
  # SlotFormer trained on the old slots must not be evaluated with them.
  with pytest.raises(UserError, match='would mix'):
    run_stage(config, workdir, mesh, 'evaluate')
  run_stage(config, workdir, mesh, 'train_slotformer')  # set aside and retrained
  assert any('.stale-' in name for name in os.listdir(workdir))
  results = run_stage(config, workdir, mesh, 'evaluate')
  assert results['identity']['slotformer']['parent'] == new_parent
  saved = files.read_json(os.path.join(workdir, 'eval', 'metrics.json'))
  assert saved['identity']['savi']['run_id'] == new_parent['savi_run_id']


def test_a_second_writer_is_refused_and_a_dead_ones_lock_taken_over(
    tmp_path):
  workdir = str(tmp_path / 'run')
  holder = subprocess.Popen(
      [sys.executable, '-c', 'import time; time.sleep(60)'])
  try:
    os.makedirs(workdir)
    with open(os.path.join(workdir, '.lock'), 'w') as f:
      json.dump({'pid': holder.pid, 'host': os.uname().nodename,
                 'started': 'then'}, f)
    with pytest.raises(UserError, match=f'in use by process {holder.pid}'):
      workdir_lock(Paths.of(workdir)).acquire()
  finally:
    holder.kill()
    holder.wait()
  lock = workdir_lock(Paths.of(workdir))
  lock.acquire()  # the holder is dead now
  assert lock.took_over
  assert json.load(open(lock.path))['pid'] == os.getpid()
  with pytest.raises(UserError, match=f'in use by process {os.getpid()}'):
    FileLock(lock.path, what=workdir).acquire()
  lock.release()
  assert not os.path.exists(lock.path)


# --------------------------------------------------------------------------
# 3. changed settings on an existing workdir
# --------------------------------------------------------------------------


def test_changed_settings_are_refused_and_config_json_kept(tmp_path):
  config = _config(tmp_path / 'data')
  workdir = str(tmp_path / 'run')
  assert accept(config, workdir) == []
  saved = open(os.path.join(workdir, 'config.json')).read()
  config.seed = 1
  config.slotformer.learning_rate = 1e-3
  with pytest.raises(UserError) as error:
    accept(config, workdir)
  message = str(error.value)
  assert 'seed: 0 -> 1' in message and 'slotformer.learning_rate' in message
  assert '--allow_config_change' in message and '\n' not in message
  assert open(os.path.join(workdir, 'config.json')).read() == saved
  # Observation-only settings are not changes.
  config.seed, config.slotformer.learning_rate = 0, 5e-4
  config.savi.log_every = 1
  assert accept(config, workdir) == []
  # The override records the new settings and keeps the old ones.
  config.seed = 1
  assert accept(config, workdir, allow_change=True) == [
      'seed: 0 -> 1']
  assert files.read_json(os.path.join(workdir, 'config.json'))['seed'] == 1
  history = open(os.path.join(workdir, 'config_history.jsonl')).readlines()
  assert json.loads(history[-1])['config'] == json.loads(saved)


def test_a_workdir_from_before_an_added_field_stays_usable(tmp_path):
  config = pipeline_helpers.load_config('synthetic_vqa', 'tiny')
  workdir = str(tmp_path / 'run')
  accept(config, workdir)
  path = os.path.join(workdir, 'config.json')
  saved = files.read_json(path)
  # As written before these existed (where the config has the value their
  # absence stands for; synthetic_vqa sets its own choice_type_weights).
  for name, old in identity_lib.ADDED_FIELDS.items():
    *section, field = name.split('.')
    holder = saved.get(section[0], {}) if section else saved
    if field in holder and (old is None or holder[field] == old):
      del holder[field]
  files.write_json_atomic(path, saved)
  assert accept(config, workdir) == []
  # Another value than the one the old code used is a change.
  config.vqa.layer_norm_epsilon = 1e-5
  with pytest.raises(UserError, match=r'vqa.layer_norm_epsilon: \(absent\)'):
    accept(config, workdir)


def test_an_added_field_whose_old_value_is_none_is_still_compared():
  """A workdir from before `qkv_size` existed had the slot size (None):
  another width set now is a change, not a match."""
  old = {'savi': {'slot_attention': {'num_iterations': 1}}}
  same = {'savi': {'slot_attention': {'num_iterations': 1, 'qkv_size': None}}}
  wider = {'savi': {'slot_attention': {'num_iterations': 1, 'qkv_size': 256}}}
  assert identity_lib.flat_differences(old, same) == []
  assert identity_lib.flat_differences(old, wider) == [
      'savi.slot_attention.qkv_size: (absent) -> 256']
  # The task was told by another field then: any value matches.
  assert identity_lib.flat_differences({}, {'task': 'vqa'}) == []


def test_run_open_reads_an_added_field_as_its_old_value(tmp_path):
  """`Run.open` of a workdir whose config.json predates fields gives them
  the values their absence stands for, so code reading them works."""
  from slotformer_jax.train import optim
  config = pipeline_helpers.load_config('synthetic_vqa', 'tiny')
  workdir = str(tmp_path / 'run')
  accept(config, workdir)
  path = os.path.join(workdir, 'config.json')
  saved = files.read_json(path)
  for section in ('savi', 'dvae', 'vqa'):
    del saved[section]['group_learning_rates']
  del saved['dvae']['min_lr_fraction'], saved['vqa']['choice_type_weights']
  files.write_json_atomic(path, saved)
  opened = Run.open(workdir).config
  assert opened.dvae.min_lr_fraction == 0.0
  assert dict(opened.vqa.choice_type_weights) == {}
  for section in ('savi', 'dvae', 'vqa'):
    assert dict(opened[section].group_learning_rates) == {}
    optim.make_optimizer(opened[section])
  # Values the workdir has are kept.
  assert opened.vqa.learning_rate == config.vqa.learning_rate


def test_a_stage_made_with_other_settings_is_set_aside(copied):
  config, workdir = copied
  config.seed = 1  # accepted with --allow_config_change
  savi = os.path.join(workdir, 'savi')
  old = identity_lib.read_identity(savi)
  identity = identity_lib.start_stage(
      savi, dict(Savi(config).part('savi').identity_fields), None, 'SAVi')
  assert identity['run_id'] != old['run_id']
  assert os.path.isdir(f'{savi}.stale-{old["run_id"]}')
  assert not os.path.exists(os.path.join(savi, 'checkpoints'))


# --------------------------------------------------------------------------
# 4. every check before any work
# --------------------------------------------------------------------------


def test_shipped_config_fails_before_work_on_four_devices():
  config = pipeline_helpers.load_config('synthetic')
  with pytest.raises(UserError, match='evaluation.batch_size=50'):
    check(config, ('train_savi', 'evaluate'),
                           num_devices=4)
  # Only the stages that run are checked.
  check(config, ('train_savi',), num_devices=4)


@pytest.mark.parametrize('field, value, expected', [
    ('evaluation.rollout_steps', 30, 'lower evaluation.rollout_steps to at '
     'most 6'),
    ('evaluation.metrics', ('psnr', 'fg_aru'), "evaluation.metrics=('psnr', "
     "'fg_aru'): each must be one of 'psnr', 'ssim', 'lpips', 'ari', "),
    ('savi.checkpoint_every', 0, 'savi.checkpoint_every must be an integer'),
    ('slotformer.log_every', -1, 'slotformer.log_every must be an integer'),
    ('savi.clip_length', 20, 'savi.clip_length=20 is longer'),
])
def test_config_problems_are_found_before_work(tmp_path, field, value,
                                               expected):
  config = _config(tmp_path / 'data')
  section, name = field.split('.')
  config[section][name] = value
  with pytest.raises(UserError, match=re.escape(expected)):
    check(config, ('train_savi', 'train_slotformer',
                                    'evaluate'), num_devices=4)
  assert not os.path.exists(tmp_path / 'data')  # no data was generated


def test_unknown_field_is_one_line_with_the_nearest_names():
  spec = os.path.join(ROOT, 'configs', 'synthetic.py') + ':tiny'
  problem = config_checks.check_overrides(
      [f'--config={spec}', '--config.savi.num_slot=3'])
  assert 'savi.num_slot' in problem and 'savi.num_slots' in problem
  problem = config_checks.check_overrides(
      [f'--config={spec}', '--config.savi.foo=1'])
  assert "'savi.foo'" in problem and '\n' not in problem
  assert config_checks.check_overrides(
      [f'--config={spec}', '--config.savi.num_slots=3']) is None


# --------------------------------------------------------------------------
# 5. atomic files, verified caches, checkpoint fallback, slot checksums
# --------------------------------------------------------------------------


def test_a_failed_write_leaves_the_old_file(tmp_path, monkeypatch):
  path = tmp_path / 'metrics.json'
  files.write_json_atomic(path, {'psnr': 30})

  def disk_full(fd):
    raise OSError(errno.ENOSPC, 'No space left on device')
  monkeypatch.setattr(os, 'fsync', disk_full)
  with pytest.raises(OSError):
    files.write_json_atomic(path, {'psnr': 31})
  monkeypatch.undo()
  assert files.read_json(path) == {'psnr': 30}
  assert os.listdir(tmp_path) == ['metrics.json']  # no temporary left


def test_a_torn_file_is_named_with_the_fix(tmp_path):
  path = tmp_path / 'meta.json'
  path.write_text('')
  with pytest.raises(UserError, match=f'{path} is empty.*re-run'):
    files.read_json(path)
  path.write_text('{"complete": tr')
  with pytest.raises(UserError, match='not valid JSON'):
    files.read_json(path)


def _record_file(dataset_dir, split='train'):
  [path] = [p for p in os.listdir(dataset_dir)
            if f'-{split}.array_record' in p]
  return os.path.join(dataset_dir, path)


@pytest.mark.parametrize('damage', ['truncate', 'garble'])
def test_damaged_synthetic_cache_is_regenerated(trained, tmp_path, damage,
                                                caplog):
  config = _config(tmp_path / 'data')
  pipeline_helpers.prepare_data(config)
  source = datasets.get_video_source(config.data, 'train')
  expected = source[3]['video']
  record = _record_file(source.dataset_dir)
  data = bytearray(open(record, 'rb').read())
  if damage == 'truncate':
    data = data[:len(data) // 2]
  else:  # same size, other bytes (inverted: records are stored
    # uncompressed, so the middle of the file may already be zeros)
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(b ^ 0xFF for b in data[middle:middle + 64])
  open(record, 'wb').write(bytes(data))
  # The reader refuses it (reading never writes); the data stage, which
  # every --mode runs first, regenerates it.
  with pytest.raises(UserError, match='damaged.*--mode=prepare_data'):
    datasets.get_video_source(config.data, 'train')
  with caplog.at_level(logging.WARNING):
    pipeline_helpers.prepare_data(config)
  assert 'cache is damaged' in caplog.text and 'regenerating' in caplog.text
  regenerated = datasets.get_video_source(config.data, 'train')
  np.testing.assert_array_equal(regenerated[3]['video'], expected)


def test_an_older_cache_gets_its_checksums_from_the_data_stage(trained):
  config, _ = trained
  dataset_dir = datasets.get_video_source(config.data, 'train').dataset_dir
  checksums = dataset_dir / integrity.CHECKSUMS_FILE
  recorded = files.read_json(checksums)
  os.remove(checksums)  # as a cache made before checksums were recorded
  assert len(datasets.get_video_source(config.data, 'val')) == 4
  assert not checksums.exists()  # the reader writes nothing
  pipeline_helpers.prepare_data(config)
  assert files.read_json(checksums) == recorded


def test_damaged_real_dataset_names_the_conversion_command(trained, tmp_path):
  synthetic_dir = datasets.get_video_source(trained[0].data, 'train'
                                           ).dataset_dir
  real = tmp_path / 'data' / 'obj3d' / 'cfg' / '1.0.0'
  shutil.copytree(synthetic_dir, real)
  config = _config(tmp_path / 'data')
  config.data.name = 'obj3d'
  assert len(datasets.get_video_source(config.data, 'train')) == 8
  record = _record_file(real)
  with open(record, 'r+b') as f:
    f.truncate(os.path.getsize(record) - 100)
  for read in (lambda: datasets.get_video_source(config.data, 'train'),
               lambda: pipeline_helpers.prepare_data(config)):
    with pytest.raises(UserError, match=r'damaged.*slotformer_jax\.data\.'
                       'prepare --dataset=obj3d'):
      read()
  # Without checksums the reader's own error still names the folder.
  os.remove(real / integrity.CHECKSUMS_FILE)
  source = sources.TfdsVideoSource(real, 'train')
  with pytest.raises(UserError, match=f'{real}: reading video'):
    for index in range(len(source)):
      source[index]


def test_damaged_newest_checkpoint_falls_back_with_a_warning(copied, caplog):
  config, workdir = copied
  mesh = sharding.make_mesh()
  newest = os.path.join(workdir, 'slotformer', 'checkpoints', '4')
  for root, _, names in os.walk(os.path.join(newest, 'default')):
    for name in names:  # a disk fault: every file of step 4 cut short
      path = os.path.join(root, name)
      with open(path, 'r+b') as f:
        f.truncate(os.path.getsize(path) // 3)
  with caplog.at_level(logging.WARNING):
    step = Run.create(config, workdir, mesh).dynamics('slotformer').step
  assert step == 2
  assert 'newest intact checkpoint, step 2' in caplog.text


def test_garbled_slots_are_detected(copied):
  config, workdir = copied
  path = os.path.join(Paths.of(workdir).slots('train'), 'slots.f32')
  slots = np.fromfile(path, np.float32)
  slots[100:110] += 0.5  # plausible values, wrong ones
  slots.tofile(path)
  with pytest.raises(UserError, match='slots.f32 is damaged'):
    SlotSource(Paths.of(workdir).slots('train'), None, ())


# --------------------------------------------------------------------------
# 6. the NaN guard checks the updated state; 7. a failed save stops at once
# --------------------------------------------------------------------------


def test_diverged_parameters_are_never_saved(tmp_path):
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  # The loss before the first update is finite; the updated state is not.
  stage = linear_stage(tmp_path / 'linear', learning_rate=1e39,
                       checkpoint_every=1)
  with pytest.raises(Diverged, match='there is no checkpoint yet') as error:
    fit(stage, mesh=mesh, seed=0)
  assert 'non-finite in update 1' in str(error.value)
  checkpointer = checkpoint_lib.Checkpointer(
      str(tmp_path / 'linear' / 'checkpoints'), read_only=True)
  assert checkpointer.all_steps() == []
  # With a good checkpoint first, the message names it.
  stage = linear_stage(tmp_path / 'late', checkpoint_every=1,
                       num_train_steps=2)
  fit(stage, mesh=mesh, seed=0)
  stage = linear_stage(tmp_path / 'late', learning_rate=1e39,
                       num_train_steps=4, checkpoint_every=1)
  with pytest.raises(Diverged, match='last good checkpoint is step 2'):
    fit(stage, mesh=mesh, seed=0)
  assert checkpoint_lib.Checkpointer(
      str(tmp_path / 'late' / 'checkpoints'), read_only=True
  ).all_steps() == [1, 2]


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_a_signal_in_training_saves_that_step(tmp_path, signum):
  """Ctrl-C (SIGINT) is treated as SIGTERM: the step is saved, `Preempted`
  carries the signal (main exits 128 + it), the handlers are restored."""
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  stage = linear_stage(tmp_path / 'linear', num_train_steps=50,
                       checkpoint_every=1000)
  plain = stage.batches
  # The trainer takes the batch of step k while step k - DEVICE_PREFETCH + 1
  # runs (it puts batches on the devices ahead): a signal sent then is acted
  # on after that update, update 4 here.
  signal_at = 3 + trainer.DEVICE_PREFETCH - 1

  def batches(start_step):
    for step, batch in zip(itertools.count(start_step), plain(start_step)):
      if step == signal_at:
        os.kill(os.getpid(), signum)
      yield batch
  stage = dataclasses.replace(stage, batches=batches)
  # Whatever pytest was started with (`nohup ... &` ignores SIGINT), the
  # handlers before training are known ones, and must be the ones after.
  with _handlers({signal.SIGINT: _before_int, signal.SIGTERM: _before_term}):
    with pytest.raises(Preempted, match=f'stopped by {signum.name} after '
                       'step 4;') as error:
      fit(stage, mesh=mesh, seed=0)
    assert signal.getsignal(signal.SIGINT) is _before_int
    assert signal.getsignal(signal.SIGTERM) is _before_term
  assert error.value.signal == signum
  assert checkpoint_lib.Checkpointer(
      str(tmp_path / 'linear' / 'checkpoints'), read_only=True
  ).all_steps() == [4]


def test_a_signal_during_the_last_save_stops_the_run_once_it_is_saved(
    tmp_path, monkeypatch):
  """Issue 61, case 5: a SIGTERM after a stage's last stop check (during
  its final save or log) was forgotten when the handlers were put back,
  and the run went on through the next stages."""
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  directory = tmp_path / 'linear'
  save = checkpoint_lib.Checkpointer.save

  def save_then_signal(self, step, state, **kwargs):
    save(self, step, state, **kwargs)
    if step == 4:  # the last one: its stop check is behind
      os.kill(os.getpid(), signal.SIGTERM)
  monkeypatch.setattr(checkpoint_lib.Checkpointer, 'save', save_then_signal)
  with _handlers({signal.SIGINT: _before_int, signal.SIGTERM: _before_term}):
    with pytest.raises(Preempted, match='stopped by SIGTERM after its last '
                       'step, 4; its checkpoint is saved') as error:
      fit(linear_stage(directory, num_train_steps=4, checkpoint_every=2),
          mesh=mesh, seed=0)
    assert signal.getsignal(signal.SIGTERM) is _before_term
  assert error.value.signal == signal.SIGTERM
  assert checkpoint_lib.Checkpointer(
      str(directory / 'checkpoints'), read_only=True).all_steps() == [2, 4]
  # The rerun finds the stage trained.
  monkeypatch.setattr(checkpoint_lib.Checkpointer, 'save', save)
  assert int(fit(linear_stage(directory, num_train_steps=4,
                              checkpoint_every=2), mesh=mesh,
                 seed=0).step) == 4


def test_a_signal_between_host_syncs_leaves_few_updates_to_compute(tmp_path):
  """Issue 61, case 5: with no host sync between logs, the host queued
  update after update; a SIGTERM near step 20 stopped after step 51, ~40 s
  late. Now at most MAX_STEPS_AHEAD updates are queued beyond the finished
  ones when the signal is noted, and the stop is after that very step."""
  from slotformer_jax.runtime import in_flight  # pylint: disable=g-import-not-at-top
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  outputs = {}
  queued_at_signal = []

  def after_update(done, params, metrics):
    del params
    outputs[done] = metrics
    if done == 12:
      queued_at_signal.append(sum(not m['loss'].is_ready()
                                  for m in outputs.values()))
      os.kill(os.getpid(), signal.SIGTERM)
  stage = dataclasses.replace(
      linear_stage(tmp_path / 'linear', num_train_steps=40, log_every=1000,
                   checkpoint_every=1000, device_work=60),
      after_update=after_update)
  with _handlers({signal.SIGINT: _before_int, signal.SIGTERM: _before_term}):
    # Sent after step 12's stop check: acted on after the next update.
    with pytest.raises(Preempted, match='after step 13;'):
      fit(stage, mesh=mesh, seed=0)
  assert queued_at_signal[0] <= in_flight.MAX_STEPS_AHEAD, queued_at_signal
  assert checkpoint_lib.Checkpointer(
      str(tmp_path / 'linear' / 'checkpoints'), read_only=True
  ).all_steps() == [13]


def _before_int(signum, frame):
  raise AssertionError('the handler from before training was called')


def _before_term(signum, frame):
  raise AssertionError('the handler from before training was called')


class _handlers:
  """Installs signal handlers for a block and puts back the ones before."""

  def __init__(self, handlers):
    self.handlers = handlers
    self.saved = {}

  def __enter__(self):
    for signum, handler in self.handlers.items():
      self.saved[signum] = signal.signal(signum, handler)

  def __exit__(self, *exc):
    for signum, handler in self.saved.items():
      signal.signal(signum, handler)


def test_a_signal_ignored_before_training_stays_ignored(tmp_path):
  """A run started with SIGINT ignored (a background job of a script,
  `nohup ... &`) is not stopped by a SIGINT, as Python itself ignores it
  then; SIGTERM still saves and stops. Before, the trainer caught the
  ignored SIGINT and stopped."""
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  stage = linear_stage(tmp_path / 'linear', num_train_steps=6,
                       checkpoint_every=1000)
  plain = stage.batches

  def batches(start_step):
    for step, batch in zip(itertools.count(start_step), plain(start_step)):
      if step == 3:
        os.kill(os.getpid(), signal.SIGINT)
      yield batch
  stage = dataclasses.replace(stage, batches=batches)
  with _handlers({signal.SIGINT: signal.SIG_IGN,
                  signal.SIGTERM: _before_term}):
    fit(stage, mesh=mesh, seed=0)  # runs to the end
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    assert signal.getsignal(signal.SIGTERM) is _before_term
  assert checkpoint_lib.Checkpointer(
      str(tmp_path / 'linear' / 'checkpoints'), read_only=True
  ).all_steps() == [6]


def test_a_failed_save_stops_training_with_one_line(tmp_path, monkeypatch):
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  saved = []

  def failing_save(self, step, state, force=False):
    saved.append(step)
    raise checkpoint_lib.CheckpointSaveError(
        f'saving the checkpoint of step {step} failed (OSError: [Errno 28] '
        'No space left on device); training stopped.')
  monkeypatch.setattr(checkpoint_lib.Checkpointer, 'save', failing_save)
  stage = linear_stage(tmp_path / 'linear', checkpoint_every=1)
  with pytest.raises(checkpoint_lib.CheckpointSaveError) as error:
    fit(stage, mesh=mesh, seed=0)
  assert saved == [1]  # stopped at the first failure
  assert '\n' not in str(error.value)


def test_an_orbax_save_error_becomes_one_line(tmp_path, monkeypatch):
  checkpointer = checkpoint_lib.Checkpointer(str(tmp_path / 'checkpoints'))

  def disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, 'No space left on device\n' + 'detail\n' * 50)
  monkeypatch.setattr(checkpointer._manager, 'save', disk_full)
  with pytest.raises(checkpoint_lib.CheckpointSaveError) as error:
    checkpointer.save(3, {'x': np.zeros(2)})
  message = str(error.value)
  assert '\n' not in message and 'by step 3' in message
  assert 'last saved step (none)' in message


# --------------------------------------------------------------------------
# 8. anticipated errors: one line on stderr, no traceback
# --------------------------------------------------------------------------


def _main(*args, cwd):
  env = dict(os.environ, PYTHONPATH=os.path.abspath(ROOT),
             JAX_PLATFORMS='cpu',
             SLOTFORMER_DATA_DIR=os.path.join(cwd, '.test_cache'))
  env.pop('XLA_FLAGS', None)
  return subprocess.run(
      [sys.executable, '-m', 'slotformer_jax.main', *args], cwd=cwd, env=env,
      capture_output=True, text=True, timeout=300)


def test_anticipated_errors_are_one_line(tmp_path):
  config = os.path.join(ROOT, 'configs', 'obj3d.py')
  missing_data = _main(f'--config={config}', f'--workdir={tmp_path / "a"}',
                       '--mode=train_savi', cwd=str(tmp_path))
  # Every mode makes its data first (prepare_data): a dataset of 3 videos
  # keeps that short.
  missing_checkpoint = _main(
      f'--config={os.path.join(ROOT, "configs", "synthetic.py")}:tiny',
      f'--workdir={tmp_path / "b"}', '--mode=evaluate',
      '--config.data.num_train=1', '--config.data.num_val=1',
      '--config.data.num_test=1', cwd=str(tmp_path))
  unknown_field = _main(f'--config={config}', f'--workdir={tmp_path / "c"}',
                        '--config.savi.foo=1', cwd=str(tmp_path))
  for result, needle in ((missing_data, 'slotformer_jax.data.prepare'),
                         (missing_checkpoint, '--mode=train_savi'),
                         (unknown_field, "'savi.foo'")):
    lines = [line for line in result.stderr.splitlines()
             if line.startswith('error:')]
    assert result.returncode != 0, result.stderr
    assert 'Traceback' not in result.stderr, result.stderr
    assert len(lines) == 1 and needle in lines[0], result.stderr



def _none_fields(config, prefix=''):
  """(dotted name, its ConfigDict, key) of every field whose value is None."""
  for key in config.keys():
    value = config[key]
    if isinstance(value, ml_collections.ConfigDict):
      yield from _none_fields(value, f'{prefix}{key}.')
    elif value is None:
      yield f'{prefix}{key}', config, key


@pytest.mark.parametrize('name', sorted(
    f[:-3] for f in os.listdir(os.path.join(ROOT, 'configs'))
    if f.endswith('.py') and not f.startswith('_')))
def test_every_unset_field_can_be_set_on_the_command_line(name, monkeypatch):
  """A field left None must be a typed placeholder: absl cannot override a
  plain None (`--config.data.data_dir=...` stopped with a flags error)."""
  from absl import flags
  from ml_collections import config_flags
  samples = {str: '/tmp/x', int: '3', float: '0.5', bool: 'true',
             tuple: '(0, 1)'}
  fields, overrides = [], []
  for field, parent, key in _none_fields(pipeline_helpers.load_config(name)):
    reference = parent._fields[key]  # pylint: disable=protected-access
    assert isinstance(reference, ml_collections.FieldReference), (
        f'configs/{name}.py: {field} is a plain None; use '
        'ml_collections.config_dict.placeholder(<type>)')
    fields.append(field)
    overrides.append(f'--config.{field}={samples[reference.get_type()]}')
  path = os.path.join(ROOT, 'configs', f'{name}.py')
  flag_values = flags.FlagValues()
  config_flags.DEFINE_config_file('config', flag_values=flag_values)
  argv = ['prog', f'--config={path}', *overrides]
  monkeypatch.setattr(sys, 'argv', argv)  # config_flags reads overrides here
  flag_values(argv)
  for field in fields:
    value = flag_values.config
    for part in field.split('.'):
      value = value[part]
    assert value is not None, field


def test_a_stage_says_it_compiles_before_its_first_step(tmp_path, caplog):
  """Issue 61, case 9: the first steps of every training stage compiled
  for 1 to 2 minutes with no line."""
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  with caplog.at_level(logging.INFO, logger='slotformer_jax.train.trainer'):
    fit(linear_stage(tmp_path / 'linear', num_train_steps=2), mesh=mesh,
        seed=0)
  lines = [r.getMessage() for r in caplog.records]
  assert 'linear: compiling the update step (the first step takes longer)' in (
      lines), lines
