"""The whole pipeline on a tiny embedded dataset, then a resumed re-run."""

import importlib.util
import json
import os

import jax
import numpy as np
import pytest

from slotformer_jax import inference
from slotformer_jax import stages
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import visualize
from slotformer_jax.train import sharding

CONFIGS = os.path.join(os.path.dirname(__file__), '..', 'configs')


def load_config(name, variant=''):
  spec = importlib.util.spec_from_file_location(
      name, os.path.join(CONFIGS, f'{name}.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant) if variant else module.get_config()


def _micro_config(data_dir):
  config = load_config('synthetic', 'tiny')
  config.data.data_dir = str(data_dir)
  config.data.resolution = (16, 16)
  config.data.num_frames = 8
  config.data.num_train, config.data.num_val, config.data.num_test = 8, 4, 4
  config.data.num_workers = 1
  config.savi.decoder.features = (8, 8)
  config.savi.encoder.features = (8, 8)
  config.savi.encoder.strides = (1, 1)
  config.savi.num_train_steps = 4
  config.savi.log_every = config.savi.checkpoint_every = 2
  config.slotformer.burn_in, config.slotformer.rollout = 2, 2
  config.slotformer.num_train_steps = 4
  config.slotformer.log_every = config.slotformer.checkpoint_every = 2
  config.slot_lstm.train = True  # the baseline runs through every stage too
  config.slot_lstm.num_train_steps = 2
  config.extraction.chunk_length = 4  # two chunks per video carry the state
  config.evaluation.rollout_steps = 6
  config.evaluation.batch_size = 4
  config.evaluation.chunk_length = 4
  config.render.num_videos = 1
  return config


def _run_all(config, workdir, mesh):
  stages.train_savi(config, workdir, mesh)
  stages.extract_slots(config, workdir, mesh)
  stages.train_slotformer(config, workdir, mesh)
  stages.train_slot_lstm(config, workdir, mesh)
  results = evaluate.evaluate(config, workdir, mesh)
  pictures = visualize.render(config, workdir, mesh)
  return results, pictures


def test_pipeline_runs_end_to_end_and_resumes(tmp_path):
  config = _micro_config(tmp_path / 'data')
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()  # 4 fake devices: every stage runs sharded
  results, pictures = _run_all(config, workdir, mesh)

  for stage in ('savi', 'slotformer', 'slot_lstm'):
    assert os.listdir(os.path.join(workdir, stage, 'checkpoints'))
  for split in ('train', 'val', 'test'):
    meta = json.load(open(os.path.join(workdir, 'slots', split,
                                       'meta.json')))
    assert meta['complete'] and meta['savi_step'] == 4
  source = workdir_lib.slot_source_for(config, workdir, 'test', ('video',))
  assert source[0]['slots'].shape == (8, config.savi.num_slots,
                                      config.savi.slot_size)
  saved = json.load(open(os.path.join(workdir, 'eval', 'metrics.json')))
  assert saved['checkpoints'] == {'savi_step': 4, 'slotformer_step': 4,
                                  'slot_lstm_step': 2}
  assert list(saved['rollout']) == ['slotformer', 'slot_lstm', 'copy_last',
                                    'savi_reconstruction']
  for method in saved['rollout']:
    per_step = saved['rollout'][method]['psnr']['per_step']
    assert len(per_step) == 6 and all(v is not None for v in per_step)
  assert 0.0 <= saved['rollout']['slotformer']['ssim']['mean'] <= 1.0
  assert saved['savi']['num_videos'] == 4
  assert os.path.exists(os.path.join(workdir, 'eval', 'per_step.csv'))
  assert any(p.endswith('.gif') for p in pictures)
  assert any(os.path.basename(p).startswith('attention_') for p in pictures)
  assert os.path.join(workdir, 'render', 'per_step.png') in pictures
  assert all(os.path.getsize(p) > 0 for p in pictures)

  # Re-running resumes: nothing is retrained or re-extracted.
  slots_file = os.path.join(workdir, 'slots', 'train', 'slots.f32')
  before = os.path.getmtime(slots_file)
  results_again, _ = _run_all(config, workdir, mesh)
  assert os.path.getmtime(slots_file) == before
  assert results_again['rollout'] == results['rollout']

  # Datasets without instance masks (e.g. OBJ3D) evaluate frame metrics only.
  config.evaluation.metrics = ('psnr',)
  frame_only = evaluate.evaluate(config, workdir, mesh)
  assert set(frame_only['savi']) == {'psnr', 'num_videos', 'num_frames'}
  # Another compiled program: equal up to float32 rounding.
  np.testing.assert_allclose(
      frame_only['rollout']['slotformer']['psnr']['per_step'],
      results['rollout']['slotformer']['psnr']['per_step'], rtol=1e-5)


def test_stage_two_explains_a_missing_stage_one(tmp_path):
  config = _micro_config(tmp_path / 'data')
  with pytest.raises(UserError, match='--mode=train_savi'):
    stages.train_slotformer(config, str(tmp_path / 'run'),
                            sharding.make_mesh())


def test_stage_two_rejects_a_checkpoint_of_another_model(tmp_path):
  config = _micro_config(tmp_path / 'data')
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  stages.train_savi(config, workdir, mesh)
  config.savi.slot_size = 24
  with pytest.raises(UserError, match='slot_size'):
    inference.load_savi_params(config, workdir, mesh)


def test_real_dataset_configs_name_the_missing_data(tmp_path):
  for name in ('obj3d', 'clevrer', 'phyre'):
    config = load_config(name)
    config.data.data_dir = str(tmp_path)
    with pytest.raises(FileNotFoundError, match=str(tmp_path / name)):
      stages.train_savi(config, str(tmp_path / 'run'), sharding.make_mesh())
