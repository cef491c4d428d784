"""The two-stage pipeline: train SAVi -> extract slots -> train SlotFormer.

The workdir layout and the checks of what each artifact was made from are in
`workdir.py`; reading trained parameters is in `inference.py`.
"""

from __future__ import annotations

import functools
import logging
import math
from typing import Any

import jax
from jax.experimental import multihost_utils
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import tqdm

from slotformer_jax import inference
from slotformer_jax import losses
from slotformer_jax import models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import pipeline
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.data.slots import read_meta
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.errors import UserError
from slotformer_jax.modules import initializers
from slotformer_jax.train import precision
from slotformer_jax.train import sharding
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit
from slotformer_jax.train import steps

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------
# Stage 1: SAVi
# --------------------------------------------------------------------------


def check_foreign_stage1(config: ml_collections.ConfigDict, workdir: str,
                         mesh: Mesh) -> None:
  """`stage1_workdir` is read-only: its SAVi must be complete and made with
  this config's stage-1 settings, its slots complete and made by that SAVi.

  Raises:
    UserError: what is missing or different, and where to fix it.
  """
  other = workdir_lib.stage1_workdir(config, workdir)
  identity = workdir_lib.savi_identity(config, workdir)
  _, step = inference.load_savi_params(config, workdir, mesh)
  if step < config.savi.num_train_steps:
    raise UserError(
        f'stage 1 in stage1_workdir={other} is incomplete (SAVi step {step} '
        f'of {config.savi.num_train_steps}); this run never trains there. '
        'Finish it with its own run: python -m slotformer_jax.main '
        f'--config=<its config> --workdir={other}')
  for split in config.extraction.splits:
    workdir_lib.check_slots_current(config, workdir, split, identity, step)


def train_savi(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh) -> None:
  if workdir_lib.uses_foreign_stage1(config, workdir):
    check_foreign_stage1(config, workdir, mesh)
    logger.info('SAVi: using the read-only stage 1 in %s',
                workdir_lib.stage1_workdir(config, workdir))
    return
  model = models.build_savi(config)
  source = get_video_source(config.data, 'train')
  stage_config = config.savi
  clip_shape = (1, stage_config.clip_length, *config.data.resolution, 3)
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  directory = workdir_lib.savi_dir(workdir)
  fields = workdir_lib.savi_model_fields(config)
  _start_stage(directory, workdir_lib.savi_identity_fields(config), None,
               'SAVi')
  workdir_lib.check_model_config(directory, fields, 'SAVi')
  workdir_lib.write_model_config(directory, fields)
  stage = Stage(
      name='savi',
      directory=directory,
      config=stage_config,
      loss_fn=precision.with_compute_dtype(functools.partial(
          losses.savi_loss, model=model,
          kl_weight=stage_config.kl_weight if stage_config.stochastic else 0.0),
          config.compute_dtype),
      init_params=lambda rng: initializers.initialize(
          steps.init_params(model, rng, jnp.zeros(clip_shape, jnp.float32)),
          jax.random.fold_in(rng, 1), stage_config.init),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=stage_config.clip_length, seed=config.seed,
          start_step=start_step, fields=('video',),
          process_index=jax.process_index(),
          process_count=jax.process_count()),
  )
  fit(stage, mesh=mesh, seed=config.seed)


def _start_stage(directory: str, fields: dict[str, Any],
                 parent: dict[str, Any] | None, what: str) -> dict[str, Any]:
  """See `workdir.start_stage` (shared with the STEVE stages)."""
  return workdir_lib.start_stage(directory, fields, parent, what)


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
  if workdir_lib.uses_foreign_stage1(config, workdir):
    check_foreign_stage1(config, workdir, mesh)
    return
  identity = workdir_lib.savi_identity(config, workdir)
  params, savi_step = inference.load_savi_params(config, workdir, mesh)
  parent = workdir_lib.slots_parent(identity, savi_step)
  slot_fields = workdir_lib.slots_identity_fields(config)
  model = models.build_savi(config)
  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  encode = jax.jit(
      functools.partial(inference.savi_encode, model=model),
      in_shardings=(replicated, batched, replicated, batched),
      out_shardings=(batched, batched))
  chunk_length = config.extraction.chunk_length
  local_batch_size = sharding.per_host_batch_size(
      config.extraction.batch_size, mesh)
  process_index, process_count = jax.process_index(), jax.process_count()

  for split in config.extraction.splits:
    directory = workdir_lib.slots_dir(workdir_lib.stage1_workdir(config, workdir), split)
    meta = read_meta(directory)
    if (meta and meta.get('complete') and meta.get('parent') == parent
        and meta.get('fields') == slot_fields):
      logger.info('slots of %s already extracted (SAVi %s)', split, parent)
      continue
    if meta and meta.get('complete'):
      logger.info('slots of %s are stale (from SAVi %s, now %s): '
                  're-extracting', split, meta.get('parent'), parent)
    source = get_video_source(config.data, split)
    num_videos = len(source)
    shard = list(range(process_index, num_videos, process_count))
    num_batches = math.ceil(
        math.ceil(num_videos / process_count) / local_batch_size)
    writer = None
    if process_index == 0:
      writer = SlotWriter(directory, num_videos, config.savi.num_slots,
                          config.savi.slot_size, savi_step,
                          parent=parent, fields=slot_fields)
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
      gathered = sharding.gather_to_host({
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


def train_dynamics(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh, name: str = models.SLOTFORMER) -> None:
  """Stage 2: trains dynamics model `name` on the extracted train slots."""
  savi_identity = workdir_lib.savi_identity(config, workdir)
  savi_params, savi_step = inference.load_savi_params(config, workdir, mesh)
  parent = workdir_lib.check_slots_current(config, workdir, 'train',
                                           savi_identity, savi_step)
  decoder = models.build_decoder(config)
  model = models.build_dynamics(config, name)
  stage_config = models.dynamics_config(config, name)
  burn_in, rollout = stage_config.burn_in, stage_config.rollout
  use_image_loss = stage_config.image_loss_weight > 0
  video_fields = ('video',) if use_image_loss else ()
  source = workdir_lib.slot_source_for(config, workdir, 'train', video_fields)
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  history_shape = (1, burn_in, config.savi.num_slots, config.savi.slot_size)
  directory = workdir_lib.dynamics_dir(workdir, name)
  fields = workdir_lib.dynamics_model_fields(config, name)
  _start_stage(directory, workdir_lib.dynamics_identity_fields(config, name),
               parent, name)
  workdir_lib.check_model_config(directory, fields, name)
  workdir_lib.write_model_config(directory, fields)
  stage = Stage(
      name=name,
      directory=directory,
      config=stage_config,
      loss_fn=precision.with_compute_dtype(functools.partial(
          losses.slotformer_loss, model=model, decoder=decoder,
          rollout=rollout, image_loss_weight=stage_config.image_loss_weight,
          teacher_forcing=stage_config.teacher_forcing), config.compute_dtype),
      init_params=lambda rng: initializers.initialize(
          steps.init_params(model, rng, jnp.zeros(history_shape, jnp.float32),
                            rollout),
          jax.random.fold_in(rng, 1), stage_config.get('init', 'flax')),
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


def load_slotformer_params(config: ml_collections.ConfigDict, workdir: str,
                           mesh: Mesh) -> tuple[Any, int]:
  return inference.load_dynamics_params(config, workdir, mesh,
                                        models.SLOTFORMER)
