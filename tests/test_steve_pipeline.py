"""The whole STEVE pipeline on a tiny embedded dataset (slow: ~minutes)."""

import json
import os

import numpy as np
import pytest

from slotformer_jax import main as main_lib
from slotformer_jax import steve_stages
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import tokens as tokens_lib
from slotformer_jax.data.slots import read_meta
from slotformer_jax.errors import UserError
from slotformer_jax.train import sharding
from test_end_to_end import load_config


def _micro_config(data_dir):
  config = load_config('synthetic', 'steve_tiny')
  config.data.data_dir = str(data_dir)
  config.data.resolution = (16, 16)  # 4x4 tokens, 8x8 Slot Attention inputs
  config.data.num_workers = 1
  return config


@pytest.mark.slow
def test_steve_pipeline_runs_and_resumes(tmp_path):
  config = _micro_config(tmp_path / 'data')
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  stages = main_lib.stage_table(config)
  for mode in ('train_dvae', 'tokenize_frames', 'train_steve',
               'extract_slots', 'train_slotformer'):
    stages[mode](config, workdir, mesh)
  tokens = tokens_lib.read_meta(steve_stages.tokens_dir(workdir, 'train'))
  assert tokens['complete'] and tokens['dvae_step'] == 4
  assert tokens['num_tokens'] == 16
  results = stages['evaluate'](config, workdir, mesh)
  for method in ('slotformer', 'copy_last', 'steve_reconstruction'):
    for name in ('psnr', 'ssim', 'fg_ari', 'fg_miou'):
      value = results['rollout'][method][name]['mean']
      assert value is None or np.isfinite(value), (method, name)
    assert np.isfinite(results['rollout'][method]['psnr']['mean'])
  assert 0.0 <= results['steve']['fg_miou_per_frame'] <= 1.0
  assert results['checkpoints']['steve_step'] == 4
  with open(os.path.join(workdir, 'eval', 'metrics.json')) as f:
    assert json.load(f)['slot_model'] == 'steve'
  pictures = stages['render'](config, workdir, mesh)
  assert any(p.endswith('steve_rollout_000.gif') for p in pictures)
  # Re-running stage 1 resumes: nothing is retrained or re-tokenized.
  before = os.path.getmtime(os.path.join(
      steve_stages.tokens_dir(workdir, 'train'), tokens_lib.TOKENS_FILE))
  stages['train_dvae'](config, workdir, mesh)
  stages['tokenize_frames'](config, workdir, mesh)
  stages['train_steve'](config, workdir, mesh)
  after = os.path.getmtime(os.path.join(
      steve_stages.tokens_dir(workdir, 'train'), tokens_lib.TOKENS_FILE))
  assert before == after
  # Run identities: each artifact records the one it was made from.
  dvae = workdir_lib.read_identity(steve_stages.dvae_dir(workdir))
  steve = workdir_lib.read_identity(steve_stages.steve_dir(workdir))
  slotformer = workdir_lib.read_identity(
      workdir_lib.dynamics_dir(workdir, 'slotformer'))
  dvae_parent = {'dvae_run_id': dvae['run_id'], 'dvae_step': 4}
  assert tokens['parent'] == dvae_parent and steve['parent'] == dvae_parent
  slots_parent = {'steve_run_id': steve['run_id'], 'steve_step': 4}
  for split in config.extraction.splits:
    meta = read_meta(workdir_lib.slots_dir(workdir, split))
    assert meta['parent'] == slots_parent
  assert slotformer['parent'] == slots_parent
  assert results['identity']['slotformer']['parent'] == slots_parent
  # A retrained STEVE (new run id) makes the slots stale: re-extracted, and
  # SlotFormer on the old slots is refused by evaluation.
  workdir_lib.write_identity(
      steve_stages.steve_dir(workdir),
      workdir_lib.new_identity(steve['fields'], steve['parent']))
  with pytest.raises(UserError, match='stale'):
    stages['evaluate'](config, workdir, mesh)
  stages['extract_slots'](config, workdir, mesh)
  with pytest.raises(UserError, match='would mix them'):
    stages['evaluate'](config, workdir, mesh)
  # Stage 2 in another workdir on this stage 1 (read-only there): the stage-1
  # modes only check it, SlotFormer trains in the new workdir on its slots.
  other = str(tmp_path / 'ablation')
  config.stage1_workdir = workdir
  listing = sorted(os.listdir(workdir))
  for mode in ('train_dvae', 'tokenize_frames', 'train_steve',
               'extract_slots', 'train_slotformer'):
    stages[mode](config, other, mesh)
  assert sorted(os.listdir(workdir)) == listing
  assert sorted(os.listdir(other)) == ['slotformer']
  current = read_meta(workdir_lib.slots_dir(workdir, 'train'))['parent']
  assert workdir_lib.read_identity(
      workdir_lib.dynamics_dir(other, 'slotformer'))['parent'] == current
  assert stages['evaluate'](config, other, mesh)['identity']['slots'] == (
      current)
