"""Shared by the pipeline tests: configs by file name, micro configs of every
slot model, making a config's data, and running its stages in table order."""

import importlib.util
import os

from slotformer_jax import stages
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir.settings import accept_config
from slotformer_jax.stages import data as data_stage

ROOT = os.path.join(os.path.dirname(__file__), '..')
CONFIGS = os.path.join(ROOT, 'configs')
SLOT_MODELS = ('savi', 'steve')


def _load(folder, name):
  """<repository>/<folder>/<name>.py as a module (configs and experiments
  are scripts, not a package)."""
  spec = importlib.util.spec_from_file_location(
      name, os.path.join(ROOT, folder, f'{name}.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def load_config(name, variant=''):
  """configs/<name>.py's get_config(variant)."""
  module = _load('configs', name)
  return module.get_config(variant) if variant else module.get_config()


def load_experiment(name):
  """experiments/<name>.py as a module."""
  return _load('experiments', name)


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
  data_stage.prepare_data(Run.create(config, '/nonexistent/run',
                                     sharding.make_mesh()))


def run_stages(config, workdir, mesh, names=None):
  """Runs the data stage, then `names` (default: every stage of
  `--mode=all`) in table order, as main does (one Run, its loaded models
  forgotten after each stage); returns {name: what the stage returned}."""
  run = Run.create(config, str(workdir), mesh)
  table = stages.stage_table(run)
  names = list(dict.fromkeys([*stages.DATA, *(
      names or stages.selected_stages(run, 'all'))]))
  out = {}
  for name in names:
    out[name] = table[name](run)
    run.forget()
  return out


def run_stage(config, workdir, mesh, name):
  """One stage of `config` on `workdir` (what it returns)."""
  return run_stages(config, workdir, mesh, [name])[name]


def accept(config, workdir, **kwargs):
  """`settings.accept_config` of `config` (a ConfigDict or a plain dict)
  on `workdir`, as main calls it."""
  settings = config.to_dict() if hasattr(config, 'to_dict') else config
  return accept_config(settings, Paths.of(str(workdir)), **kwargs)


def slots_of(config, workdir, split, video_fields=()):
  """The extracted slots of `split` with `video_fields`, as stages read
  them."""
  return Run.create(config, str(workdir), sharding.make_mesh()).slots(
      split, tuple(video_fields))


def check(config, stages, **kwargs):
  """Every check main runs before any work (`stages.check`)."""
  from slotformer_jax import stages as stages_lib  # pylint: disable=g-import-not-at-top
  stages_lib.check(Run.create(config, '/nonexistent/run',
                              sharding.make_mesh()), tuple(stages), **kwargs)
