"""Stage 1 with STEVE (`config.slot_model='steve'`), and stage 2 on its slots.

train dVAE -> tokenize the training frames once -> train STEVE -> extract
slots -> train SlotFormer / Slot-LSTM on them. The stages share the SAVi
pipeline's data stream, trainer, checkpoints and slot files; what differs is
here. Paths and what each artifact descends from (run identities, as with
SAVi): steve_workdir.py; reading trained parameters: steve_inference.py.

    dvae/      identity parent: none
    tokens/    meta parent: the dVAE run id + step
    steve/     identity parent: the dVAE run id + step
    slots/     meta parent: the STEVE run id + step (re-extracted when stale)
    slotformer/, slot_lstm/   identity parent: the STEVE run id + step
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

from slotformer_jax import losses
from slotformer_jax import models
from slotformer_jax import steve_inference
from slotformer_jax import steve_workdir
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import pipeline
from slotformer_jax.data import tokens as tokens_lib
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.data.slots import read_meta
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import UserError
from slotformer_jax.train import sharding
from slotformer_jax.train import steps
from slotformer_jax.train import steve_steps
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit

logger = logging.getLogger(__name__)

DVAE = steve_workdir.DVAE
STEVE = steve_workdir.STEVE
TOKENIZED_SPLITS = ('train',)  # STEVE trains on these; nothing else needs tokens

# Paths and model fields live in steve_workdir.py (evaluation reads them);
# kept here under their old names.
dvae_dir = steve_workdir.dvae_dir
steve_dir = steve_workdir.steve_dir
tokens_dir = steve_workdir.tokens_dir
dvae_model_fields = steve_workdir.dvae_model_fields
steve_model_fields = steve_workdir.steve_model_fields
load_dvae_params = steve_inference.load_dvae_params
load_steve_params = steve_inference.load_steve_params
load_dynamics_params = steve_inference.load_dynamics_params


def _frame_shape(config: ml_collections.ConfigDict) -> tuple[int, int, int]:
  return (*config.data.resolution, 3)


def _token_grid(config: ml_collections.ConfigDict) -> tuple[int, int]:
  return models.build_steve(config).token_grid


def _init_dvae(config, rng):
  return steps.init_params(models.build_dvae(config), rng,
                           jnp.zeros((1, *_frame_shape(config))), 1.0)


def _init_steve(config, rng):
  clip = (1, config.steve.clip_length, *_frame_shape(config))
  height, width = _token_grid(config)
  tokens = jnp.zeros((1, config.steve.clip_length, height * width), jnp.int32)
  return steps.init_params(models.build_steve(config), rng, jnp.zeros(clip),
                           tokens)


def _init_dynamics(config, name, rng):
  stage_config = models.dynamics_config(config, name)
  history = jnp.zeros((1, stage_config.burn_in, config.steve.num_slots,
                       config.steve.slot_size))
  return steps.init_params(models.build_dynamics(config, name), rng, history,
                           stage_config.rollout)


# --------------------------------------------------------------------------
# Stage 1a: dVAE
# --------------------------------------------------------------------------


def check_foreign_stage1(config: ml_collections.ConfigDict, workdir: str,
                         mesh: Mesh) -> None:
  """`stage1_workdir` is read-only: its dVAE and STEVE must be complete and
  descend from each other, its slots made by that STEVE (as
  `stages.check_foreign_stage1` for SAVi).

  Raises:
    UserError: what is missing or different, and where to fix it.
  """
  other = workdir_lib.stage1_workdir(config, workdir)
  _, dvae_step = load_dvae_params(config, workdir, mesh)
  _, steve_step = load_steve_params(config, workdir, mesh)
  for what, step, total in (('dVAE', dvae_step, config.dvae.num_train_steps),
                            ('STEVE', steve_step,
                             config.steve.num_train_steps)):
    if step < total:
      raise UserError(
          f'stage 1 in stage1_workdir={other} is incomplete ({what} step '
          f'{step} of {total}); this run never trains there. Finish it with '
          'its own run: python -m slotformer_jax.main --config=<its config> '
          f'--workdir={other}')
  identity = steve_workdir.check_steve_current(config, workdir, dvae_step)
  for split in config.extraction.splits:
    workdir_lib.check_slots_current(config, workdir, split, identity,
                                    steve_step, STEVE)


def _foreign_stage1(config: ml_collections.ConfigDict, workdir: str,
                    mesh: Mesh, what: str) -> bool:
  """True (after checking it) when stage 1 is another workdir's."""
  if not workdir_lib.uses_foreign_stage1(config, workdir):
    return False
  check_foreign_stage1(config, workdir, mesh)
  logger.info('%s: using the read-only stage 1 in %s', what,
              workdir_lib.stage1_workdir(config, workdir))
  return True


def dvae_stage(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh) -> Stage:
  """The dVAE's training stage (single frames, annealed Gumbel-softmax)."""
  model = models.build_dvae(config)
  stage_config = config.dvae
  source = get_video_source(config.data, 'train')
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  schedule = dict(start=stage_config.gumbel_start,
                  final=stage_config.gumbel_final,
                  anneal_fraction=stage_config.gumbel_anneal_fraction)

  def batches(start_step):
    frames = pipeline.train_batches(
        source, batch_size=local_batch_size, clip_length=1, seed=config.seed,
        start_step=start_step, fields=('video',),
        process_index=jax.process_index(), process_count=jax.process_count())
    return steve_steps.with_gumbel_temperature(
        frames, start_step, stage_config.num_train_steps, **schedule)

  return Stage(
      name=DVAE,
      directory=dvae_dir(workdir_lib.stage1_workdir(config, workdir)),
      config=stage_config,
      loss_fn=functools.partial(steve_steps.dvae_loss, model=model),
      init_params=functools.partial(_init_dvae, config),
      batches=batches)


def train_dvae(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh) -> None:
  steve_workdir.check_float32(config)
  if _foreign_stage1(config, workdir, mesh, 'dVAE'):
    return
  stage = dvae_stage(config, workdir, mesh)
  fields = dvae_model_fields(config)
  workdir_lib.start_stage(stage.directory,
                          steve_workdir.dvae_identity_fields(config), None,
                          'dVAE')
  workdir_lib.check_model_config(stage.directory, fields, 'dVAE')
  workdir_lib.write_model_config(stage.directory, fields)
  fit(stage, mesh=mesh, seed=config.seed)


# --------------------------------------------------------------------------
# Tokens of the training frames, once per dataset and dVAE
# --------------------------------------------------------------------------


def _video_batches(source: Any, local_batch_size: int):
  """(indices, valid) of this host's videos in fixed-size batches; every host
  runs the same number of batches."""
  process_index, process_count = jax.process_index(), jax.process_count()
  shard = list(range(process_index, len(source), process_count))
  num_batches = math.ceil(
      math.ceil(len(source) / process_count) / local_batch_size)
  for batch_index in range(num_batches):
    indices = shard[batch_index * local_batch_size:
                    (batch_index + 1) * local_batch_size]
    valid = np.zeros(local_batch_size, bool)
    valid[:len(indices)] = True
    indices = indices + [indices[-1] if indices else shard[-1]] * (
        local_batch_size - len(indices))
    yield indices, valid


def _padded_clip(video: np.ndarray, num_frames: int) -> np.ndarray:
  """video [T, ...] -> [num_frames, ...], repeating the last frame."""
  if len(video) >= num_frames:
    return video[:num_frames]
  padding = np.repeat(video[-1:], num_frames - len(video), axis=0)
  return np.concatenate([video, padding], axis=0)


def _chunked_padded(videos: list[np.ndarray], chunk_length: int):
  """Stacked videos padded (last frame repeated) to a multiple of
  chunk_length frames, equal on every host, and the number of chunks."""
  lengths = np.array([len(v) for v in videos])
  num_chunks = math.ceil(lengths.max() / chunk_length)
  if jax.process_count() > 1:
    num_chunks = int(multihost_utils.process_allgather(
        np.array(num_chunks)).max())
  padded = np.stack([_padded_clip(v, num_chunks * chunk_length)
                     for v in videos])
  return padded, lengths, num_chunks


def tokenize_frames(config: ml_collections.ConfigDict, workdir: str,
                    mesh: Mesh) -> None:
  """The frozen dVAE's argmax tokens of every training frame, stored once
  (skipped when they came from the current dVAE checkpoint)."""
  if _foreign_stage1(config, workdir, mesh, 'tokens'):
    return
  params, dvae_step = load_dvae_params(config, workdir, mesh)
  parent = steve_workdir.dvae_parent(
      steve_workdir.dvae_identity(config, workdir), dvae_step)
  dvae = models.build_dvae(config)
  batched = sharding.batch_sharding(mesh)
  tokenize = jax.jit(
      functools.partial(steve_inference.tokenize, dvae=dvae),
      in_shardings=(sharding.replicated_sharding(mesh), batched),
      out_shardings=batched)
  chunk_length = config.extraction.chunk_length
  local_batch_size = sharding.per_host_batch_size(
      config.dvae.tokenize_batch_size, mesh)
  height, width = _token_grid(config)
  for split in TOKENIZED_SPLITS:
    directory = tokens_dir(workdir_lib.stage1_workdir(config, workdir), split)
    meta = tokens_lib.read_meta(directory)
    if meta and meta.get('complete') and meta.get('parent') == parent:
      logger.info('tokens of %s already computed (dVAE %s)', split, parent)
      continue
    if meta and meta.get('complete'):
      logger.info('tokens of %s are stale (from dVAE %s, now %s): '
                  'recomputing', split, meta.get('parent'), parent)
    source = get_video_source(config.data, split)
    writer = None
    if jax.process_index() == 0:
      writer = tokens_lib.TokenWriter(directory, len(source), height * width,
                                      dvae_step, parent=parent)
    for indices, valid in tqdm.tqdm(
        list(_video_batches(source, local_batch_size)),
        desc=f'tokenize {split}', disable=jax.process_index() != 0):
      padded, lengths, num_chunks = _chunked_padded(
          [source[i]['video'] for i in indices], chunk_length)
      chunks = []
      for chunk in range(num_chunks):
        frames = padded[:, chunk * chunk_length:(chunk + 1) * chunk_length]
        chunks.append(tokenize(params, sharding.to_global_batch(
            {'video': frames}, mesh)['video']))
      gathered = sharding.gather_to_host({
          'tokens': jnp.concatenate(chunks, axis=1),
          **sharding.to_global_batch(
              {'index': np.asarray(indices), 'length': lengths,
               'valid': valid}, mesh)})
      if writer is not None:
        for video_tokens, index, length, is_valid in zip(
            gathered['tokens'], gathered['index'], gathered['length'],
            gathered['valid']):
          if is_valid:
            writer.add(int(index), video_tokens[:length])
    if writer is not None:
      writer.close()
    if jax.process_count() > 1:
      multihost_utils.sync_global_devices(f'tokenized {split}')
    logger.info('tokenized %d %s videos', len(source), split)


# --------------------------------------------------------------------------
# Stage 1b: STEVE
# --------------------------------------------------------------------------


def steve_stage(config: ml_collections.ConfigDict, workdir: str,
                mesh: Mesh) -> Stage:
  model = models.build_steve(config)
  stage_config = config.steve
  root = workdir_lib.stage1_workdir(config, workdir)
  source = tokens_lib.TokenSource(tokens_dir(root, 'train'),
                                  get_video_source(config.data, 'train'))
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  return Stage(
      name=STEVE, directory=steve_dir(root), config=stage_config,
      loss_fn=functools.partial(steve_steps.steve_loss, model=model),
      init_params=functools.partial(_init_steve, config),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=stage_config.clip_length, seed=config.seed,
          start_step=start_step, fields=('video', 'tokens'),
          process_index=jax.process_index(),
          process_count=jax.process_count()))


def train_steve(config: ml_collections.ConfigDict, workdir: str,
                mesh: Mesh) -> None:
  """STEVE on the tokens of the current dVAE. A STEVE trained with another
  dVAE (or other settings) is set aside and retrained from scratch."""
  steve_workdir.check_float32(config)
  if _foreign_stage1(config, workdir, mesh, 'STEVE'):
    return
  _, dvae_step = load_dvae_params(config, workdir, mesh)
  parent = steve_workdir.dvae_parent(
      steve_workdir.dvae_identity(config, workdir), dvae_step)
  for split in TOKENIZED_SPLITS:
    steve_workdir.check_tokens_current(config, workdir, split, parent)
  stage = steve_stage(config, workdir, mesh)
  fields = steve_model_fields(config)
  workdir_lib.start_stage(stage.directory,
                          steve_workdir.steve_identity_fields(config), parent,
                          'STEVE')
  workdir_lib.check_model_config(stage.directory, fields, 'STEVE')
  workdir_lib.write_model_config(stage.directory, fields)
  fit(stage, mesh=mesh, seed=config.seed)


# --------------------------------------------------------------------------
# Slot extraction with STEVE
# --------------------------------------------------------------------------


def extract_slots(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh) -> None:
  """STEVE's slots of every video of every split, in chunks of
  `extraction.chunk_length` frames that carry STEVE's state."""
  if _foreign_stage1(config, workdir, mesh, 'slots'):
    return
  params, steve_step = load_steve_params(config, workdir, mesh)
  _, dvae_step = load_dvae_params(config, workdir, mesh)
  identity = steve_workdir.check_steve_current(config, workdir, dvae_step)
  parent = workdir_lib.slots_parent(identity, steve_step, STEVE)
  slot_fields = workdir_lib.slots_identity_fields(config)
  model = models.build_steve(config)
  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  encode = jax.jit(
      lambda params, video, carry: steve_inference.steve_encode(
          params, video, carry, model=model)[::2],  # (slots, carry)
      in_shardings=(replicated, batched, batched),
      out_shardings=(batched, batched))
  chunk_length = config.extraction.chunk_length
  local_batch_size = sharding.per_host_batch_size(
      config.extraction.batch_size, mesh)
  for split in config.extraction.splits:
    directory = workdir_lib.slots_dir(
        workdir_lib.stage1_workdir(config, workdir), split)
    meta = read_meta(directory)
    if (meta and meta.get('complete') and meta.get('parent') == parent
        and meta.get('fields') == slot_fields):
      logger.info('slots of %s already extracted (STEVE %s)', split, parent)
      continue
    if meta and meta.get('complete'):
      logger.info('slots of %s are stale (from %s, now STEVE %s): '
                  're-extracting', split, meta.get('parent'), parent)
    source = get_video_source(config.data, split)
    writer = None
    if jax.process_index() == 0:
      writer = SlotWriter(directory, len(source), config.steve.num_slots,
                          config.steve.slot_size, steve_step,
                          parent=parent, fields=slot_fields)
    for indices, valid in tqdm.tqdm(
        list(_video_batches(source, local_batch_size)),
        desc=f'extract {split}', disable=jax.process_index() != 0):
      padded, lengths, num_chunks = _chunked_padded(
          [source[i]['video'] for i in indices], chunk_length)
      carry, chunks = None, []
      for chunk in range(num_chunks):
        frames = padded[:, chunk * chunk_length:(chunk + 1) * chunk_length]
        slots, carry = encode(params, sharding.to_global_batch(
            {'video': frames}, mesh)['video'], carry)
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
    if jax.process_count() > 1:
      multihost_utils.sync_global_devices(f'extracted {split}')
    logger.info('extracted STEVE slots of %d %s videos', len(source), split)


# --------------------------------------------------------------------------
# Stage 2 on STEVE's slots
# --------------------------------------------------------------------------


def dynamics_stage(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh, name: str = models.SLOTFORMER) -> Stage:
  """SlotFormer (or Slot-LSTM) on STEVE's slots, trained with L_S alone."""
  stage_config = models.dynamics_config(config, name)
  if stage_config.image_loss_weight > 0:
    raise ConfigError(
        'L_I through STEVE\'s autoregressive decoder is not implemented (the '
        'paper trains SlotFormer on STEVE slots without it); set '
        f'--config.slotformer.image_loss_weight=0 (got '
        f'{stage_config.image_loss_weight})')
  model = models.build_dynamics(config, name)
  source = workdir_lib.slot_source_for(config, workdir, 'train', ())
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  return Stage(
      name=name, directory=workdir_lib.dynamics_dir(workdir, name),
      config=stage_config,
      loss_fn=functools.partial(
          losses.slotformer_loss, model=model, decoder=None,
          rollout=stage_config.rollout, image_loss_weight=0.0,
          teacher_forcing=stage_config.teacher_forcing),
      init_params=functools.partial(_init_dynamics, config, name),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=stage_config.burn_in + stage_config.rollout,
          seed=config.seed + 1, start_step=start_step, fields=('slots',),
          frame_stride=stage_config.frame_stride,
          process_index=jax.process_index(),
          process_count=jax.process_count()))


def train_dynamics(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh, name: str = models.SLOTFORMER) -> None:
  """Stage 2 on STEVE's current slots; a model trained on other slots (or
  with other settings) is set aside and retrained from scratch."""
  steve_workdir.check_float32(config)
  _, steve_step = load_steve_params(config, workdir, mesh)
  _, dvae_step = load_dvae_params(config, workdir, mesh)
  identity = steve_workdir.check_steve_current(config, workdir, dvae_step)
  parent = workdir_lib.check_slots_current(config, workdir, 'train', identity,
                                           steve_step, STEVE)
  stage = dynamics_stage(config, workdir, mesh, name)
  fields = workdir_lib.dynamics_model_fields(config, name)
  workdir_lib.start_stage(stage.directory,
                          workdir_lib.dynamics_identity_fields(config, name),
                          parent, name)
  workdir_lib.check_model_config(stage.directory, fields, name)
  workdir_lib.write_model_config(stage.directory, fields)
  fit(stage, mesh=mesh, seed=config.seed + 1)


def train_slotformer(config, workdir, mesh) -> None:
  train_dynamics(config, workdir, mesh, models.SLOTFORMER)


def train_slot_lstm(config, workdir, mesh) -> None:
  train_dynamics(config, workdir, mesh, models.SLOT_LSTM)
