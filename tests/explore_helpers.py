"""A run explorer page without a trained run: the micro SAVi config with
freshly initialised SAVi, SlotFormer and Slot-LSTM on random slots (shared
by the explorer's unit and browser tests)."""

import jax
import jax.numpy as jnp
import numpy as np

from pipeline_helpers import micro_config
from slotformer_jax import dynamics
from slotformer_jax.config.sections import dynamics_section
from slotformer_jax.evaluation import explore
from slotformer_jax.slot_models.savi import Savi

SLOTFORMER = 'slotformer'  # the dynamics models' registered names
SLOT_LSTM = 'slot_lstm'

NUM_VIDEOS = 2


def micro_explorer(data_dir, targets=None):
  """(config, slot model, Explorer, its arguments); `targets`: the SAVi's
  (`savi.targets`; default its frames)."""
  config = micro_config('savi', data_dir)
  if targets is not None:
    config.savi.targets = targets
  # A residual SlotFormer starts as copy-last, where freezing a slot
  # changes nothing: the explorer is tested on one that moves the slots.
  config.slotformer.residual = False
  config.explore.num_videos = NUM_VIDEOS
  slot_model = Savi(config)
  burn_in = config.slotformer.burn_in
  frames = burn_in + config.evaluation.rollout_steps
  num_slots, slot_size = slot_model.slot_shape
  height, width = config.data.resolution
  rngs = {name: jax.random.key(i) for i, name in
          enumerate(('params', 'sample', 'dropout'))}
  clip = jnp.zeros((1, config.savi.clip_length, height, width, 3))
  slot_params = {'savi': slot_model.model.init(rngs, clip)['params']}
  history = jnp.zeros((1, burn_in, num_slots, slot_size))
  names = (SLOTFORMER, SLOT_LSTM)
  modules = {name: dynamics.build(dynamics_section(config, name), name)
             for name in names}
  dynamics_params = {
      name: modules[name].init(jax.random.key(3 + i), history, 2)['params']
      for i, name in enumerate(names)}
  rng = np.random.default_rng(0)
  slots = rng.normal(size=(NUM_VIDEOS, frames, num_slots, slot_size)).astype(
      np.float32)
  video = rng.integers(0, 256, (NUM_VIDEOS, frames, height, width, 3),
                       dtype=np.uint8)
  segmentation = rng.integers(0, config.data.max_instances + 1,
                              (NUM_VIDEOS, frames, height, width))
  explorer = explore.Explorer(
      modules, slot_model, burn_in=burn_in,
      rollout=config.evaluation.rollout_steps,
      num_true=config.data.max_instances + 1,
      background_threshold=config.evaluation.background_threshold)
  return config, slot_model, explorer, (dynamics_params, slot_params, slots,
                                        video, segmentation)


def write_micro_page(directory, data_dir, curves=None):
  """Writes `directory`/index.html; returns (its path, the page's data).
  `curves`: the run's curves (default: one PSNR curve)."""
  config, slot_model, explorer, args = micro_explorer(data_dir)
  out = jax.device_get(explorer(*args))
  identity = {'savi': {'run_id': 'test', 'step': 0}}
  data = explore.page_data(
      out, args[3], list(range(NUM_VIDEOS)), slot_model=slot_model,
      title=f'{config.data.name}: {slot_model.label} + SlotFormer',
      burn_in=config.slotformer.burn_in,
      rollout=config.evaluation.rollout_steps,
      split=config.evaluation.split, explore_config=config.explore,
      identity=identity,
      curves=curves or {'psnr': {'SlotFormer': [20.0, 19.0, None]}},
      curves_note='test curves', seconds=0.0)
  return explore.write_page(str(directory), data), data
