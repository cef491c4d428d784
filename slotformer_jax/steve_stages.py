"""Stage 1 with STEVE (`config.slot_model='steve'`), and stage 2 on its slots.

train dVAE -> tokenize the training frames once -> train STEVE -> extract
slots -> train SlotFormer / Slot-LSTM on them. The stages share the SAVi
pipeline's data stream, trainer, checkpoints and slot files; what differs is
here. Workdir layout::

    dvae/checkpoints/   dvae/model_config.json   dvae/train_log.jsonl
    tokens/train/       the frozen dVAE's tokens (see data/tokens.py)
    steve/checkpoints/  steve/model_config.json  steve/train_log.jsonl
    slots/<split>/      STEVE's slots (meta 'savi_step' = STEVE's step)
    slotformer/ ...     as with SAVi
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
from slotformer_jax import stages
from slotformer_jax import steve_inference
from slotformer_jax.data import pipeline
from slotformer_jax.data import tokens as tokens_lib
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.data.slots import read_meta
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.train import sharding
from slotformer_jax.train import steps
from slotformer_jax.train import steve_steps
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import abstract_train_state
from slotformer_jax.train.trainer import checkpointer_for
from slotformer_jax.train.trainer import fit

logger = logging.getLogger(__name__)

DVAE = 'dvae'
STEVE = 'steve'
TOKENIZED_SPLITS = ('train',)  # STEVE trains on these; nothing else needs tokens


def dvae_dir(workdir: str) -> str:
  return os.path.join(workdir, DVAE)


def steve_dir(workdir: str) -> str:
  return os.path.join(workdir, STEVE)


def tokens_dir(workdir: str, split: str) -> str:
  return os.path.join(workdir, 'tokens', split)


def _jsonable(fields: dict[str, Any]) -> dict[str, Any]:
  return json.loads(json.dumps(fields))  # tuples -> lists, for comparison


def dvae_model_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """The config values that determine the dVAE's parameters."""
  return _jsonable({'vocab_size': config.dvae.vocab_size,
                    'hidden_size': config.dvae.hidden_size})


def steve_model_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """The config values that determine STEVE's parameters (incl. its dVAE)."""
  steve = config.steve.to_dict()
  fields = {key: steve[key] for key in (
      'num_slots', 'slot_size', 'encoder', 'slot_attention', 'predictor',
      'decoder')}
  fields['resolution'] = list(config.data.resolution)
  fields['vocab_size'] = config.dvae.vocab_size
  return _jsonable(fields)


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


def _load(directory: str, what: str, init_params, stage_config, mesh: Mesh,
          fields: dict[str, Any] | None, mode: str) -> tuple[Any, int]:
  """The newest parameters (replicated) of a stage and their step."""
  checkpointer = checkpointer_for(directory, read_only=True)
  if checkpointer.latest_step() is None:
    raise FileNotFoundError(
        f'no {what} checkpoint under {directory}/checkpoints. Train it '
        'first: python -m slotformer_jax.main --config=<config> '
        f'--workdir=<workdir> --mode={mode}')
  if fields is not None:
    stages._check_model_config(directory, fields, what)  # pylint: disable=protected-access
  state = checkpointer.restore(
      abstract_train_state(init_params, stage_config, mesh))
  step = int(state.step)
  if step < stage_config.num_train_steps:
    logger.warning('%s was trained for %d of %d steps only', what, step,
                    stage_config.num_train_steps)
  return state.params, step


# --------------------------------------------------------------------------
# Stage 1a: dVAE
# --------------------------------------------------------------------------


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
      name=DVAE, directory=dvae_dir(stages.stage1_workdir(config, workdir)),
      config=stage_config,
      loss_fn=functools.partial(steve_steps.dvae_loss, model=model),
      init_params=functools.partial(_init_dvae, config),
      batches=batches)


def train_dvae(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh) -> None:
  stage = dvae_stage(config, workdir, mesh)
  fields = dvae_model_fields(config)
  stages._check_model_config(stage.directory, fields, 'dVAE')  # pylint: disable=protected-access
  stages._write_model_config(stage.directory, fields)  # pylint: disable=protected-access
  fit(stage, mesh=mesh, seed=config.seed)


def load_dvae_params(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh) -> tuple[Any, int]:
  return _load(dvae_dir(stages.stage1_workdir(config, workdir)), 'dVAE',
               functools.partial(_init_dvae, config), config.dvae, mesh,
               dvae_model_fields(config), 'train_dvae')


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


def _chunked_padded(videos: list[np.ndarray], chunk_length: int):
  """Stacked videos padded (last frame repeated) to a multiple of
  chunk_length frames, equal on every host, and the number of chunks."""
  lengths = np.array([len(v) for v in videos])
  num_chunks = math.ceil(lengths.max() / chunk_length)
  if jax.process_count() > 1:
    num_chunks = int(multihost_utils.process_allgather(
        np.array(num_chunks)).max())
  padded = np.stack([stages._padded_clip(v, num_chunks * chunk_length)  # pylint: disable=protected-access
                     for v in videos])
  return padded, lengths, num_chunks


def tokenize_frames(config: ml_collections.ConfigDict, workdir: str,
                    mesh: Mesh) -> None:
  """The frozen dVAE's argmax tokens of every training frame, stored once
  (skipped when they came from the current dVAE checkpoint)."""
  params, dvae_step = load_dvae_params(config, workdir, mesh)
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
    directory = tokens_dir(stages.stage1_workdir(config, workdir), split)
    meta = tokens_lib.read_meta(directory)
    if meta and meta.get('complete') and meta.get('dvae_step') == dvae_step:
      logger.info('tokens of %s already computed (dVAE step %d)', split,
                   dvae_step)
      continue
    source = get_video_source(config.data, split)
    writer = None
    if jax.process_index() == 0:
      writer = tokens_lib.TokenWriter(directory, len(source), height * width,
                                      dvae_step)
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
      gathered = stages.gather_to_host({
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
  root = stages.stage1_workdir(config, workdir)
  meta = tokens_lib.read_meta(tokens_dir(root, 'train'))
  if not meta or not meta.get('complete'):
    raise FileNotFoundError(
        f'no dVAE tokens under {tokens_dir(root, "train")}; run '
        '--mode=tokenize_frames first')
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
  stage = steve_stage(config, workdir, mesh)
  fields = steve_model_fields(config)
  stages._check_model_config(stage.directory, fields, 'STEVE')  # pylint: disable=protected-access
  stages._write_model_config(stage.directory, fields)  # pylint: disable=protected-access
  fit(stage, mesh=mesh, seed=config.seed)


def load_steve_params(config: ml_collections.ConfigDict, workdir: str,
                      mesh: Mesh) -> tuple[Any, int]:
  return _load(steve_dir(stages.stage1_workdir(config, workdir)), 'STEVE',
               functools.partial(_init_steve, config), config.steve, mesh,
               steve_model_fields(config), 'train_steve')


# --------------------------------------------------------------------------
# Slot extraction with STEVE
# --------------------------------------------------------------------------


def extract_slots(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh) -> None:
  """STEVE's slots of every video of every split, in chunks of
  `extraction.chunk_length` frames that carry STEVE's state."""
  params, steve_step = load_steve_params(config, workdir, mesh)
  model = models.build_steve(config)
  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  encode = jax.jit(
      lambda params, video, carry: steve_steps.steve_encode(
          params, video, carry, model=model)[::2],  # (slots, carry)
      in_shardings=(replicated, batched, batched),
      out_shardings=(batched, batched))
  chunk_length = config.extraction.chunk_length
  local_batch_size = sharding.per_host_batch_size(
      config.extraction.batch_size, mesh)
  for split in config.extraction.splits:
    directory = stages.slots_dir(stages.stage1_workdir(config, workdir), split)
    meta = read_meta(directory)
    if meta and meta.get('complete') and meta.get('savi_step') == steve_step:
      logger.info('slots of %s already extracted (STEVE step %d)', split,
                   steve_step)
      continue
    source = get_video_source(config.data, split)
    writer = None
    if jax.process_index() == 0:
      writer = SlotWriter(directory, len(source), config.steve.num_slots,
                          config.steve.slot_size, steve_step)
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
      gathered = stages.gather_to_host({
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
    raise ValueError(
        'L_I through STEVE\'s autoregressive decoder is not implemented (the '
        'paper trains SlotFormer on STEVE slots without it); set '
        f'--config.slotformer.image_loss_weight=0 (got '
        f'{stage_config.image_loss_weight})')
  model = models.build_dynamics(config, name)
  source = stages.slot_source_for(config, workdir, 'train', ())
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  return Stage(
      name=name, directory=stages.dynamics_dir(workdir, name),
      config=stage_config,
      loss_fn=functools.partial(
          steps.slotformer_loss, model=model, decoder=None,
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
  stage = dynamics_stage(config, workdir, mesh, name)
  fields = stages.dynamics_model_fields(config, name)
  stages._check_model_config(stage.directory, fields, name)  # pylint: disable=protected-access
  stages._write_model_config(stage.directory, fields)  # pylint: disable=protected-access
  fit(stage, mesh=mesh, seed=config.seed + 1)


def load_dynamics_params(config: ml_collections.ConfigDict, workdir: str,
                         mesh: Mesh, name: str = models.SLOTFORMER
                         ) -> tuple[Any, int]:
  return _load(stages.dynamics_dir(workdir, name), name,
               functools.partial(_init_dynamics, config, name),
               models.dynamics_config(config, name), mesh,
               stages.dynamics_model_fields(config, name), f'train_{name}')


def train_slotformer(config, workdir, mesh) -> None:
  train_dynamics(config, workdir, mesh, models.SLOTFORMER)


def train_slot_lstm(config, workdir, mesh) -> None:
  train_dynamics(config, workdir, mesh, models.SLOT_LSTM)
