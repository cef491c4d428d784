"""Both downstream tasks through every stage on micro configs (slow)."""

from __future__ import annotations

import json
import os

import pytest

from configs import synthetic_contact
from configs import synthetic_phyre
from pipeline_helpers import prepare_data
from slotformer_jax import stages
from slotformer_jax.runtime import sharding
from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.stages import extract
from slotformer_jax.stages import dynamics


def _micro_models(config):
  config.savi.encoder.features = (8, 8)
  config.savi.encoder.strides = (2, 1)
  config.savi.decoder.features = (8, 8)
  config.savi.num_train_steps = 2
  config.savi.log_every = config.savi.checkpoint_every = 2
  config.slotformer.num_train_steps = 2
  config.slotformer.log_every = config.slotformer.checkpoint_every = 2
  config.readout.epochs = 1


def _run(config, workdir, stage_names):
  mesh = sharding.make_mesh()
  prepare_data(config)
  savi_slots.train_savi(config, workdir, mesh)
  extract.extract_slots(config, workdir, mesh)
  dynamics.train_slotformer(config, workdir, mesh)
  run = stages.stage_table(config)
  return [run[name](config, workdir, mesh) for name in stage_names]


@pytest.mark.slow
def test_contact_task_end_to_end(tmp_path):
  config = synthetic_contact.get_config('tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.resolution = (16, 16)
  config.data.supersample = 1
  _micro_models(config)
  workdir = str(tmp_path / 'run')
  _, results = _run(config, workdir, ('train_readout', 'evaluate_readout'))
  for condition in config.readout.conditions:
    assert len(results[condition]['test_accuracy']) == len(config.readout.seeds)
    assert 0.0 <= results[condition]['mean'] <= 1.0
  assert results['chance']['mean'] == 0.5  # balanced labels
  with open(os.path.join(workdir, 'readout', 'results.json')) as f:
    assert json.load(f)['num_test_videos'] == config.data.num_readout_test


@pytest.mark.slow
def test_planning_task_end_to_end(tmp_path):
  config = synthetic_phyre.get_config('tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.num_candidates = 12
  _micro_models(config)
  workdir = str(tmp_path / 'run')
  _, summary = _run(config, workdir, ('train_readout', 'plan'))
  assert summary['oracle']['mean'] == pytest.approx(
      summary['solvable_test_tasks'] / summary['num_test_tasks'])
  for name in ('random', 'first_frame', 'rollout'):
    assert 0.0 <= summary[name]['mean'] <= summary['oracle']['mean'] + 1e-9
