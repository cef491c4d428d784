"""The whole pipeline of every slot model on tiny embedded data.

One run per slot model (SAVi; dVAE + STEVE) through every stage of
`--mode=all`, on 4 fake devices, is shared by the tests of this module:
artifacts, resuming, run identities, staleness, a read-only stage 1, the
evaluation conventions. Tests that change a workdir work on a copy.
"""

import json
import os
import shutil

import numpy as np
import pytest

from pipeline_helpers import SLOT_MODELS
from pipeline_helpers import load_config
from pipeline_helpers import micro_config
from pipeline_helpers import run_stage
from pipeline_helpers import run_stages
from pipeline_helpers import slots_of
from slotformer_jax import slot_models
from slotformer_jax.run import Run
from slotformer_jax.data import slots as tokens_lib
from slotformer_jax.data.slots import read_meta
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import metrics as metrics_lib
from slotformer_jax.runtime import sharding
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir import identity as identity_lib


@pytest.fixture(scope='module', params=SLOT_MODELS)
def trained(request, tmp_path_factory):
  """(config, workdir, mesh, {stage: result}) of a finished run."""
  root = tmp_path_factory.mktemp(request.param)
  config = micro_config(request.param, root / 'data')
  workdir = str(root / 'run')
  mesh = sharding.make_mesh()  # 4 fake devices: every stage runs sharded
  return config, workdir, mesh, run_stages(config, workdir, mesh)


def _copy(trained, tmp_path):
  config, workdir, mesh, results = trained
  copy = str(tmp_path / 'copy')
  shutil.copytree(workdir, copy)
  return config.copy_and_resolve_references(), copy, mesh, results


def test_every_stage_writes_its_artifacts(trained):
  config, workdir, _, results = trained
  slot_model = slot_models.get(config)
  dynamics_names = ['slotformer'] + (['slot_lstm']
                                     if config.slot_lstm.train else [])
  for stage in [*slot_model.stage_labels, *dynamics_names]:
    assert os.listdir(os.path.join(workdir, stage, 'checkpoints')), stage
  # One seed: no per-seed folders, no seeds file (docs/seeds.md).
  assert not [n for n in os.listdir(workdir) if n.startswith('seed_')]
  assert not os.path.exists(os.path.join(workdir, 'slotformer', 'seeds.json'))
  num_slots, slot_size = slot_model.slot_shape
  for split in config.extraction.splits:
    meta = read_meta(Paths.of(workdir).slots(split))
    assert meta['complete'] and meta['num_slots'] == num_slots
  source = slots_of(config, workdir, 'test', ('video',))
  assert source[0]['slots'].shape == (config.data.num_frames, num_slots,
                                      slot_size)

  with open(os.path.join(workdir, 'eval', 'metrics.json')) as f:
    saved = json.load(f)
  steps = {f'{key}_step': 4 for key in slot_model.stage_labels}
  steps.update({f'{name}_step': getattr(config, name).num_train_steps
                for name in dynamics_names})
  assert saved['checkpoints'] == steps
  assert saved['slot_model'] == slot_model.name
  assert list(saved['rollout']) == [*dynamics_names, 'copy_last',
                                    slot_model.reference_method]
  for method, per_metric in saved['rollout'].items():
    per_step = per_metric['psnr']['per_step']
    assert len(per_step) == config.evaluation.rollout_steps, method
    assert all(v is not None and np.isfinite(v) for v in per_step), method
  assert 0.0 <= saved['rollout']['slotformer']['ssim']['mean'] <= 1.0
  quality = saved[slot_model.name]
  assert quality['num_videos'] == config.data.num_test
  assert 0.0 <= quality['fg_miou_per_frame'] <= 1.0
  assert ('psnr' in quality) == (slot_model.name == 'savi')
  assert os.path.exists(os.path.join(workdir, 'eval', 'per_step.csv'))

  pictures = results['render']
  assert os.path.join(workdir, 'render', 'rollout_000.gif') in pictures
  assert os.path.join(workdir, 'render', 'per_step.png') in pictures
  # The attention figure needs per-slot reconstructions (SAVi's decoder).
  assert any(os.path.basename(p).startswith('attention_')
             for p in pictures) == (slot_model.name == 'savi')
  assert all(os.path.getsize(p) > 0 for p in pictures)
  # The run explorer (its page is tested in tests/evaluation/test_explore*).
  assert results['explore'] == os.path.join(workdir, 'explore', 'index.html')
  with open(os.path.join(workdir, 'explore', 'identity.json')) as f:
    assert json.load(f)['identity'] == saved['identity']


def test_rerun_resumes_without_recomputing(trained):
  config, workdir, mesh, results = trained
  files = [os.path.join(workdir, 'slots', 'train', 'slots.f32')]
  if config.slot_model == 'steve':
    files.append(os.path.join(Paths.of(workdir).derived('tokens', 'train'),
                              tokens_lib.TOKENS_FILE))
  before = [os.path.getmtime(f) for f in files]
  again = run_stages(config, workdir, mesh)
  assert [os.path.getmtime(f) for f in files] == before
  assert again['evaluate']['rollout'] == results['evaluate']['rollout']


def test_artifacts_record_what_they_were_made_from(trained):
  config, workdir, mesh, results = trained
  slot_model = slot_models.get(config)
  encoder = identity_lib.read_identity(os.path.join(workdir, slot_model.name))
  slots_parent = {f'{slot_model.name}_run_id': encoder['run_id'],
                  f'{slot_model.name}_step': 4}
  assert Run.create(config, workdir, mesh).stage1.slots_parent == slots_parent
  for split in config.extraction.splits:
    assert read_meta(Paths.of(workdir).slots(split))['parent'] == (
        slots_parent)
  slotformer = identity_lib.read_identity(
      Paths.of(workdir).dynamics('slotformer'))
  assert slotformer['parent'] == slots_parent
  identity = results['evaluate']['identity']
  assert identity['slots'] == slots_parent
  assert identity['slotformer']['parent'] == slots_parent
  assert identity[slot_model.name]['run_id'] == encoder['run_id']
  if config.slot_model == 'steve':
    dvae = identity_lib.read_identity(Paths.of(workdir).model('dvae'))
    dvae_parent = {'dvae_run_id': dvae['run_id'], 'dvae_step': 4}
    tokens = tokens_lib.read_meta(Paths.of(workdir).derived('tokens', 'train'))
    assert tokens['complete'] and tokens['num_tokens'] == 16
    assert tokens['parent'] == dvae_parent == encoder['parent']


def test_a_retrained_slot_model_makes_slots_stale_and_refuses_mixing(
    trained, tmp_path):
  config, workdir, mesh, _ = _copy(trained, tmp_path)
  directory = os.path.join(workdir, config.slot_model)
  old = identity_lib.read_identity(directory)
  identity_lib.write_identity(  # as retraining stamps a new run id
      directory, identity_lib.new_identity(old['fields'], old['parent']))
  with pytest.raises(UserError, match='stale'):
    run_stage(config, workdir, mesh, 'evaluate')
  run_stages(config, workdir, mesh, ['extract_slots'])
  with pytest.raises(UserError, match='would mix them'):
    run_stage(config, workdir, mesh, 'evaluate')


def test_stage_two_on_a_read_only_stage_one(trained, tmp_path):
  config, workdir, mesh, _ = trained
  config = config.copy_and_resolve_references()
  slot_model = slot_models.get(config)
  other = str(tmp_path / 'ablation')
  config.stage1_workdir = workdir
  listing = sorted(os.listdir(workdir))
  run_stages(config, other, mesh,
             [*slot_model.stage1_modes, 'extract_slots', 'train_slotformer'])
  assert sorted(os.listdir(workdir)) == listing  # only read there
  assert sorted(os.listdir(other)) == ['slotformer']
  current = read_meta(Paths.of(workdir).slots('train'))['parent']
  assert identity_lib.read_identity(
      Paths.of(other).dynamics('slotformer'))['parent'] == current
  config.slot_lstm.train = False
  assert run_stage(config, other, mesh, 'evaluate')['identity'][
      'slots'] == current


def test_evaluation_conventions_apply_to_every_slot_model(
    trained, tmp_path, monkeypatch):
  config, workdir, mesh, _ = _copy(trained, tmp_path)
  config.evaluation.metrics = ('fg_miou', 'ar')
  config.evaluation.miou_absent_ids = 'zero'
  config.evaluation.ar_gt_boxes = 'object_masks'
  absent_ids, box_calls = [], []
  hungarian = metrics_lib.hungarian_mean_iou
  from_normalized = metrics_lib.boxes_from_normalized

  def spy_hungarian(*args, **kwargs):
    absent_ids.append(kwargs.get('absent_ids', 'skip'))
    return hungarian(*args, **kwargs)

  def spy_boxes(*args, **kwargs):
    box_calls.append(1)
    return from_normalized(*args, **kwargs)

  monkeypatch.setattr(metrics_lib, 'hungarian_mean_iou', spy_hungarian)
  monkeypatch.setattr(metrics_lib, 'boxes_from_normalized', spy_boxes)
  results = run_stage(config, workdir, mesh, 'evaluate')
  assert absent_ids and set(absent_ids) == {'zero'}
  assert box_calls  # AR read the dataset's per-object boxes
  assert results['protocol']['miou_absent_ids'] == 'zero'
  assert results['protocol']['ar_gt_boxes'] == 'object_masks'


def test_frame_metrics_only_for_datasets_without_masks(trained, tmp_path):
  # E.g. OBJ3D has no instance masks: frame metrics only, same values.
  config, workdir, mesh, results = _copy(trained, tmp_path)
  config.evaluation.metrics = ('psnr',)
  frame_only = run_stage(config, workdir, mesh, 'evaluate')
  name = config.slot_model
  expected = {'num_videos', 'num_frames'} | ({'psnr'} if name == 'savi'
                                              else set())
  assert set(frame_only[name]) == expected
  # Another compiled program: equal up to float32 rounding.
  np.testing.assert_allclose(
      frame_only['rollout']['slotformer']['psnr']['per_step'],
      results['evaluate']['rollout']['slotformer']['psnr']['per_step'],
      rtol=1e-5)


def test_evaluation_refuses_videos_too_short_for_the_rollout(trained,
                                                             tmp_path):
  config, workdir, mesh, _ = _copy(trained, tmp_path)
  config.evaluation.rollout_steps = config.data.num_frames
  with pytest.raises(UserError, match='lower evaluation.rollout_steps'):
    run_stage(config, workdir, mesh, 'evaluate')


def test_stage_two_explains_a_missing_stage_one(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  with pytest.raises(UserError, match='--mode=train_savi'):
    run_stage(config, str(tmp_path / 'run'), sharding.make_mesh(),
              'train_slotformer')


def test_stage_two_rejects_a_checkpoint_of_another_model(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  run_stage(config, workdir, mesh, 'train_savi')
  config.savi.slot_size = 24
  with pytest.raises(UserError, match='slot_size'):
    Run.create(config, workdir, mesh).stage1  # pylint: disable=expression-not-assigned


def test_real_dataset_configs_name_the_missing_data(tmp_path):
  for name in ('obj3d', 'clevrer', 'phyre'):
    config = load_config(name)
    config.data.data_dir = str(tmp_path)
    with pytest.raises(FileNotFoundError, match=str(tmp_path / name)):
      run_stage(config, str(tmp_path / 'run'), sharding.make_mesh(),
                'train_savi')
