"""Shared by the pipeline tests: configs by file name, micro configs of every
slot model, making a config's data, and running its stages in table order."""

import importlib.util
import os

from slotformer_jax import stages
from slotformer_jax.stages import data as data_stage

CONFIGS = os.path.join(os.path.dirname(__file__), '..', 'configs')
SLOT_MODELS = ('savi', 'steve')


def load_config(name, variant=''):
  """configs/<name>.py's get_config(variant)."""
  spec = importlib.util.spec_from_file_location(
      name, os.path.join(CONFIGS, f'{name}.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant) if variant else module.get_config()


def micro_config(slot_model, data_dir):
  """The smallest whole pipeline of `slot_model` ('savi', 'steve') on the
  embedded data: 16x16 frames, a few steps per stage, two extraction chunks
  per video (the slot model's state is carried between them)."""
  if slot_model == 'steve':
    config = load_config('synthetic', 'steve_tiny')
    config.data.resolution = (16, 16)  # 4x4 tokens, 8x8 Slot Attention
  else:
    config = load_config('synthetic', 'tiny')
    config.data.resolution = (16, 16)
    config.data.num_frames = 8
    config.data.num_train, config.data.num_val, config.data.num_test = 8, 4, 4
    config.savi.decoder.features = (8, 8)
    config.savi.encoder.features = (8, 8)
    config.savi.encoder.strides = (1, 1)
    config.savi.num_train_steps = 4
    config.savi.log_every = config.savi.checkpoint_every = 2
    config.slotformer.burn_in, config.slotformer.rollout = 2, 2
    config.slotformer.num_train_steps = 4
    config.slotformer.log_every = config.slotformer.checkpoint_every = 2
    config.slot_lstm.train = True  # the baseline runs through every stage
    config.slot_lstm.num_train_steps = 2
    config.extraction.chunk_length = 4
    config.evaluation.rollout_steps = 6
    config.evaluation.batch_size = 4
    config.evaluation.chunk_length = 4
    config.render.num_videos = 1
  config.data.data_dir = str(data_dir)
  config.data.num_workers = 1
  return config


def prepare_data(config):
  """Makes and checks the data of `config` as `--mode=prepare_data` does
  (readers only open data; main runs this stage first in every mode)."""
  data_stage.prepare_data(config, None, None)


def run_stages(config, workdir, mesh, names=None):
  """Runs the data stage, then `names` (default: every stage of
  `--mode=all`), as main does; returns {name: what the stage returned}."""
  table = stages.stage_table(config)
  names = list(dict.fromkeys([*stages.DATA,
                              *(names or stages.selected_stages(config,
                                                                'all'))]))
  return {name: table[name](config, workdir, mesh) for name in names}
