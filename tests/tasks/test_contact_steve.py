"""Contact prediction on STEVE's slots (the paper's Physion pipeline:
STEVE -> SlotFormer -> readout), on the embedded contact family."""

from __future__ import annotations

import json
import os

from flax import serialization
import pytest

from configs import physion_contact
from configs import synthetic_contact
from slotformer_jax import slot_models
from slotformer_jax import stages
from slotformer_jax.data.slots import read_meta
from slotformer_jax.tasks import contact
from slotformer_jax.runtime import sharding


def steve_micro_config(data_dir):
  """configs/synthetic_contact.py:tiny with STEVE as the slot model, at the
  sizes of configs/synthetic.py:steve_tiny (smaller frames)."""
  config = synthetic_contact.get_config('tiny')
  config.slot_model = 'steve'
  config.data.data_dir = str(data_dir)
  config.data.resolution = (16, 16)   # 4x4 tokens
  config.data.num_frames = 12
  config.data.observed_frames = config.readout.observed_frames = 6
  config.data.supersample = 1
  config.data.num_workers = 1
  config.extraction.chunk_length = 12
  dvae, steve = config.dvae, config.steve
  dvae.vocab_size, dvae.hidden_size = 32, 8
  steve.num_slots, steve.slot_size = 5, 16
  steve.encoder.features, steve.encoder.strides = (8, 8), (2, 1)
  steve.encoder.kernel_size, steve.encoder.output_size = 3, 16
  steve.slot_attention.mlp_size = 32
  steve.predictor.num_layers, steve.predictor.mlp_size = 1, 32
  steve.predictor.lstm_size = 16
  steve.decoder.num_layers, steve.decoder.num_heads = 1, 2
  steve.clip_length = 2
  for section in (dvae, steve, config.slotformer):
    section.num_train_steps = section.log_every = 2
    section.checkpoint_every = 2
    section.batch_size = 4
  config.slotformer.burn_in, config.slotformer.rollout = 2, 2
  config.slotformer.embed_dim, config.slotformer.num_layers = 16, 1
  config.readout.features = None      # the slot size, as the official one
  config.readout.epochs = 1
  config.readout.num_pictures = 1
  return config


def test_readout_reads_the_slot_models_slot_size():
  config = physion_contact.get_config()
  assert config.slot_model == 'steve'
  config.steve.slot_size = 48  # physion.py gives SAVi and STEVE both 192
  slot_size = lambda: slot_models.get(config).slot_shape[1]
  assert contact.build_readout(config, slot_size()).features == 48
  config.slot_model = 'savi'
  assert contact.build_readout(config, slot_size()).features == (
      config.savi.slot_size)


@pytest.mark.slow
def test_contact_stages_on_steve_slots(tmp_path):
  config = steve_micro_config(tmp_path / 'data')
  assert config.steve.slot_size != config.savi.slot_size
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  table = stages.stage_table(config)
  assert 'train_steve' in table and 'train_savi' not in table
  for mode in ('prepare_data', 'train_dvae', 'tokenize_frames',
               'train_steve', 'extract_slots', 'train_slotformer',
               'train_readout'):
    table[mode](config, workdir, mesh)
  meta = read_meta(os.path.join(workdir, 'slots', 'readout_test'))
  assert meta['slot_size'] == config.steve.slot_size
  results = table['evaluate_readout'](config, workdir, mesh)
  for condition in config.readout.conditions:
    assert 0.0 <= results[condition]['mean'] <= 1.0
  # The readout's first layer reads pairs of STEVE slots.
  with open(os.path.join(workdir, 'readout', 'rollout', 'seed_0',
                         'params.msgpack'), 'rb') as f:
    params = serialization.msgpack_restore(f.read())
  assert params['relation']['kernel'].shape == (2 * config.steve.slot_size,
                                                config.steve.slot_size)
  # The picture decodes STEVE's rollout slots (generated frames).
  assert os.path.exists(os.path.join(workdir, 'readout', 'test_0.png'))
  with open(os.path.join(workdir, 'readout', 'results.json')) as f:
    assert json.load(f)['num_test_videos'] == config.data.num_readout_test

