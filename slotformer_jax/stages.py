"""The two-stage pipeline: train SAVi -> extract slots -> train SlotFormer.

Workdir layout (shared by all stages; each stage resumes from it)::

    savi/checkpoints/<step>/   savi/model_config.json   savi/train_log.jsonl
    slots/<split>/             extracted slots (see data/slots.py)
    slotformer/checkpoints/    slotformer/train_log.jsonl
    eval/metrics.json          eval/per_step.csv
    render/*.gif, *.png
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
from typing import Any

import jax
from jax.experimental import multihost_utils
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import tqdm

from slotformer_jax import models
from slotformer_jax.data import pipeline
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.data.slots import read_meta
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.train import precision
from slotformer_jax.train import sharding
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import abstract_train_state
from slotformer_jax.train.trainer import checkpointer_for
from slotformer_jax.train.trainer import fit
from slotformer_jax.train import steps

logger = logging.getLogger(__name__)

_MODEL_CONFIG_FILE = 'model_config.json'


def stage1_workdir(config: ml_collections.ConfigDict, workdir: str) -> str:
  """Where SAVi and the extracted slots live: `config.stage1_workdir` when
  set (stage-2 ablations reuse one stage 1), else the run's own workdir."""
  return config.get('stage1_workdir') or workdir


def savi_dir(workdir: str) -> str:
  return os.path.join(workdir, 'savi')


def slots_dir(workdir: str, split: str) -> str:
  return os.path.join(workdir, 'slots', split)


def savi_model_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """The config values that determine SAVi's parameter shapes / behaviour."""
  savi = config.savi.to_dict()
  fields = {key: savi[key] for key in (
      'num_slots', 'slot_size', 'encoder', 'slot_attention', 'predictor',
      'decoder', 'stochastic', 'initial_slots')}
  fields['resolution'] = list(config.data.resolution)
  return json.loads(json.dumps(fields))  # tuples -> lists, for comparison


def dynamics_model_fields(config: ml_collections.ConfigDict,
                          name: str = models.SLOTFORMER) -> dict[str, Any]:
  """The config values that determine a stage-2 model's parameters."""
  dynamics = models.dynamics_config(config, name).to_dict()
  keys = ['burn_in', 'embed_dim', 'num_layers', 'num_heads', 'mlp_ratio',
          'residual']
  if name == models.SLOTFORMER:
    keys.append('positional_encoding')
  return json.loads(json.dumps({key: dynamics[key] for key in keys}))


def _write_model_config(directory: str, fields: dict[str, Any]) -> None:
  if jax.process_index() == 0:
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, _MODEL_CONFIG_FILE), 'w') as f:
      json.dump(fields, f, indent=1, sort_keys=True)


def _check_model_config(directory: str, fields: dict[str, Any],
                        what: str) -> None:
  """Fails clearly when a checkpoint was trained with another architecture."""
  path = os.path.join(directory, _MODEL_CONFIG_FILE)
  if not os.path.exists(path):
    return
  with open(path) as f:
    saved = json.load(f)
  differences = [
      f'{key}: checkpoint {saved.get(key)!r} vs config {fields.get(key)!r}'
      for key in sorted(set(saved) | set(fields))
      if saved.get(key) != fields.get(key)]
  if differences:
    raise ValueError(
        f'the {what} checkpoint in {directory} was trained with a different '
        'model configuration:\n  ' + '\n  '.join(differences) +
        '\nUse the config it was trained with, or another --workdir.')


def gather_to_host(tree: Any) -> Any:
  """Global batch-sharded arrays -> numpy on every host."""
  if jax.process_count() == 1:
    return jax.tree.map(np.asarray, tree)
  return multihost_utils.process_allgather(tree, tiled=True)


# --------------------------------------------------------------------------
# Stage 1: SAVi
# --------------------------------------------------------------------------


def train_savi(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh) -> None:
  model = models.build_savi(config)
  source = get_video_source(config.data, 'train')
  stage_config = config.savi
  clip_shape = (1, stage_config.clip_length, *config.data.resolution, 3)
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  directory = savi_dir(stage1_workdir(config, workdir))
  fields = savi_model_fields(config)
  _check_model_config(directory, fields, 'SAVi')
  _write_model_config(directory, fields)
  stage = Stage(
      name='savi',
      directory=directory,
      config=stage_config,
      loss_fn=precision.with_compute_dtype(functools.partial(
          steps.savi_loss, model=model,
          kl_weight=stage_config.kl_weight if stage_config.stochastic else 0.0),
          config.compute_dtype),
      init_params=lambda rng: steps.init_params(
          model, rng, jnp.zeros(clip_shape, jnp.float32)),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=stage_config.clip_length, seed=config.seed,
          start_step=start_step, fields=('video',),
          process_index=jax.process_index(),
          process_count=jax.process_count()),
  )
  fit(stage, mesh=mesh, seed=config.seed)


def load_savi_params(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh) -> tuple[Any, int]:
  """SAVi's trained parameters (replicated) and the step they are from."""
  directory = savi_dir(stage1_workdir(config, workdir))
  checkpointer = checkpointer_for(directory, read_only=True)
  if checkpointer.latest_step() is None:
    raise FileNotFoundError(
        f'no SAVi checkpoint under {directory}/checkpoints. Train stage 1 '
        'first: python -m slotformer_jax.main --config=<config> '
        f'--workdir={workdir} --mode=train_savi')
  _check_model_config(directory, savi_model_fields(config), 'SAVi')
  model = models.build_savi(config)
  clip_shape = (1, config.savi.clip_length, *config.data.resolution, 3)
  abstract = abstract_train_state(
      lambda rng: steps.init_params(model, rng, jnp.zeros(clip_shape)),
      config.savi, mesh)
  state = checkpointer.restore(abstract)
  step = int(state.step)
  if step < config.savi.num_train_steps:
    logger.warning('SAVi was trained for %d of %d steps only', step,
                    config.savi.num_train_steps)
  return state.params, step


# --------------------------------------------------------------------------
# Slot extraction
# --------------------------------------------------------------------------


def _padded_clip(video: np.ndarray, num_frames: int) -> np.ndarray:
  """video [T, ...] -> [num_frames, ...], repeating the last frame."""
  if len(video) >= num_frames:
    return video[:num_frames]
  padding = np.repeat(video[-1:], num_frames - len(video), axis=0)
  return np.concatenate([video, padding], axis=0)


def extract_slots(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh) -> None:
  """Runs SAVi over every video of every split and stores the slots.

  Videos are processed in chunks of `extraction.chunk_length` frames that
  carry SAVi's state, so memory does not grow with the video length. A split
  whose slots came from the current SAVi checkpoint is skipped.
  """
  params, savi_step = load_savi_params(config, workdir, mesh)
  model = models.build_savi(config)
  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  encode = jax.jit(
      functools.partial(steps.savi_encode, model=model),
      in_shardings=(replicated, batched, replicated, batched),
      out_shardings=(batched, batched))
  chunk_length = config.extraction.chunk_length
  local_batch_size = sharding.per_host_batch_size(
      config.extraction.batch_size, mesh)
  process_index, process_count = jax.process_index(), jax.process_count()

  for split in config.extraction.splits:
    directory = slots_dir(stage1_workdir(config, workdir), split)
    meta = read_meta(directory)
    if meta and meta.get('complete') and meta.get('savi_step') == savi_step:
      logger.info('slots of %s already extracted (SAVi step %d)', split,
                   savi_step)
      continue
    source = get_video_source(config.data, split)
    num_videos = len(source)
    shard = list(range(process_index, num_videos, process_count))
    num_batches = math.ceil(
        math.ceil(num_videos / process_count) / local_batch_size)
    writer = None
    if process_index == 0:
      writer = SlotWriter(directory, num_videos, config.savi.num_slots,
                          config.savi.slot_size, savi_step)
    for batch_index in tqdm.trange(num_batches, desc=f'extract {split}',
                                   disable=process_index != 0):
      indices = shard[batch_index * local_batch_size:
                      (batch_index + 1) * local_batch_size]
      valid = np.zeros(local_batch_size, bool)
      valid[:len(indices)] = True
      indices = indices + [indices[-1] if indices else shard[-1]] * (
          local_batch_size - len(indices))
      videos = [source[i]['video'] for i in indices]
      lengths = np.array([len(v) for v in videos])
      num_chunks = math.ceil(lengths.max() / chunk_length)
      # All hosts must run the same number of chunks.
      num_chunks = int(multihost_utils.process_allgather(
          np.array(num_chunks)).max()) if process_count > 1 else num_chunks
      padded = np.stack([_padded_clip(v, num_chunks * chunk_length)
                         for v in videos])
      carry = None  # SAVi starts from its initial slots
      chunks = []
      for chunk in range(num_chunks):
        frames = padded[:, chunk * chunk_length:(chunk + 1) * chunk_length]
        rng = jax.random.fold_in(
            jax.random.key(config.seed), batch_index * 10_000 + chunk)
        slots, carry = encode(params, sharding.to_global_batch(
            {'video': frames}, mesh)['video'], rng, carry)
        chunks.append(slots)
      gathered = gather_to_host({
          'slots': jnp.concatenate(chunks, axis=1),
          **sharding.to_global_batch(
              {'index': np.asarray(indices), 'length': lengths,
               'valid': valid}, mesh)})
      if writer is not None:
        for slots, index, length, is_valid in zip(
            gathered['slots'], gathered['index'], gathered['length'],
            gathered['valid']):
          if is_valid:
            writer.add(int(index), slots[:length])
    if writer is not None:
      writer.close()
    if process_count > 1:
      multihost_utils.sync_global_devices(f'extracted {split}')
    logger.info('extracted slots of %d %s videos', num_videos, split)


# --------------------------------------------------------------------------
# Stage 2: SlotFormer
# --------------------------------------------------------------------------


def slot_source_for(config: ml_collections.ConfigDict, workdir: str,
                    split: str, video_fields: tuple[str, ...]) -> SlotSource:
  """Extracted slots of `split` served together with `video_fields`."""
  video_source = get_video_source(config.data, split) if video_fields else None
  return SlotSource(slots_dir(stage1_workdir(config, workdir), split),
                    video_source, video_fields)


def dynamics_dir(workdir: str, name: str = models.SLOTFORMER) -> str:
  """Where stage-2 model `name` keeps checkpoints and logs."""
  return os.path.join(workdir, name)


def train_dynamics(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh, name: str = models.SLOTFORMER) -> None:
  """Stage 2: trains dynamics model `name` on the extracted train slots."""
  savi_params, _ = load_savi_params(config, workdir, mesh)
  decoder = models.build_decoder(config)
  model = models.build_dynamics(config, name)
  stage_config = models.dynamics_config(config, name)
  burn_in, rollout = stage_config.burn_in, stage_config.rollout
  use_image_loss = stage_config.image_loss_weight > 0
  video_fields = ('video',) if use_image_loss else ()
  source = slot_source_for(config, workdir, 'train', video_fields)
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  history_shape = (1, burn_in, config.savi.num_slots, config.savi.slot_size)
  directory = dynamics_dir(workdir, name)
  fields = dynamics_model_fields(config, name)
  _check_model_config(directory, fields, name)
  _write_model_config(directory, fields)
  stage = Stage(
      name=name,
      directory=directory,
      config=stage_config,
      loss_fn=precision.with_compute_dtype(functools.partial(
          steps.slotformer_loss, model=model, decoder=decoder,
          rollout=rollout, image_loss_weight=stage_config.image_loss_weight,
          teacher_forcing=stage_config.teacher_forcing), config.compute_dtype),
      init_params=lambda rng: steps.init_params(
          model, rng, jnp.zeros(history_shape, jnp.float32), rollout),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=burn_in + rollout, seed=config.seed + 1,
          start_step=start_step, fields=('slots',) + video_fields,
          frame_stride=stage_config.frame_stride,
          process_index=jax.process_index(),
          process_count=jax.process_count()),
      frozen_params=savi_params['decoder'],
  )
  fit(stage, mesh=mesh, seed=config.seed + 1)


def train_slotformer(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh) -> None:
  train_dynamics(config, workdir, mesh, models.SLOTFORMER)


def train_slot_lstm(config: ml_collections.ConfigDict, workdir: str,
                    mesh: Mesh) -> None:
  """The Slot-LSTM baseline, with SlotFormer's data, losses and schedule."""
  train_dynamics(config, workdir, mesh, models.SLOT_LSTM)


def load_dynamics_params(config: ml_collections.ConfigDict, workdir: str,
                         mesh: Mesh, name: str = models.SLOTFORMER
                         ) -> tuple[Any, int]:
  """The newest parameters of stage-2 model `name` and their step."""
  directory = dynamics_dir(workdir, name)
  checkpointer = checkpointer_for(directory, read_only=True)
  if checkpointer.latest_step() is None:
    raise FileNotFoundError(
        f'no {name} checkpoint under {directory}/checkpoints. Train it '
        'first: python -m slotformer_jax.main --config=<config> '
        f'--workdir={workdir} --mode=train_{name}')
  _check_model_config(directory, dynamics_model_fields(config, name), name)
  model = models.build_dynamics(config, name)
  stage_config = models.dynamics_config(config, name)
  history_shape = (1, stage_config.burn_in, config.savi.num_slots,
                   config.savi.slot_size)
  abstract = abstract_train_state(
      lambda rng: steps.init_params(model, rng, jnp.zeros(history_shape),
                                    stage_config.rollout),
      stage_config, mesh)
  state = checkpointer.restore(abstract)
  return state.params, int(state.step)


def load_slotformer_params(config: ml_collections.ConfigDict, workdir: str,
                           mesh: Mesh) -> tuple[Any, int]:
  return load_dynamics_params(config, workdir, mesh, models.SLOTFORMER)
