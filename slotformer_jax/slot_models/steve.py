"""STEVE as the slot model (the paper's Physion pipeline): `slot_model='steve'`.

Stage 1 is three stages: `train_dvae` (single frames, annealed
Gumbel-softmax), `tokenize_frames` (the frozen dVAE's argmax tokens of every
training frame, stored once), `train_steve` (slots through SAVi's encoder and
Slot Attention, trained by its token decoder's cross-entropy against those
tokens). Decoding slots *generates* a frame: greedy decoding of all h*w
tokens with a key/value cache, then the dVAE's decoder; its alpha masks are
the token decoder's last-layer cross-attention of each token over the slots
(mean over heads), upsampled bilinearly to the frame. STEVE's own account of
real frames is its Slot Attention masks (the last iteration's softmax over
slots), upsampled as the official code does. It has no differentiable pixel
decoder, so SlotFormer trains on its slots with L_S alone (as the paper), and
it computes in float32 only.

Workdir (inside the stage-1 workdir)::

    dvae/checkpoints/   dvae/identity.json (parent: null)
    tokens/train/       meta 'parent' = the dVAE run id + step
    steve/checkpoints/  steve/identity.json (parent: the dVAE run id + step)
    slots/<split>/      meta 'parent' = the STEVE run id + step

Parameters: {'steve': STEVE's, 'dvae': the dVAE's}.
"""

from __future__ import annotations

from collections.abc import Iterator
import functools
import json
import logging
import math
import os
from typing import Any

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import inference
from slotformer_jax import losses
from slotformer_jax import models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import pipeline
from slotformer_jax.data import tokens as tokens_lib
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.modules.token_decoder import TokenDecoder
from slotformer_jax.slot_models.base import Decoded
from slotformer_jax.slot_models.base import Loaded
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.slot_models.base import uses_foreign_stage1
from slotformer_jax.runtime import sharding
from slotformer_jax.train import steps
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit_stage

logger = logging.getLogger(__name__)

DVAE_NAME = 'dvae'
NAME = 'steve'
TOKENIZED_SPLITS = ('train',)  # STEVE trains on these; nothing else needs them


# --------------------------------------------------------------------------
# Paths, the fields that shape each model, and the identity chain
# --------------------------------------------------------------------------


def dvae_dir(workdir: str) -> str:
  return os.path.join(workdir, DVAE_NAME)


def steve_dir(workdir: str) -> str:
  return os.path.join(workdir, NAME)


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
      'decoder', 'layer_norm_epsilon')}
  fields['resolution'] = list(config.data.resolution)
  fields['vocab_size'] = config.dvae.vocab_size
  return _jsonable(fields)


def dvae_identity_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """Everything that shapes the dVAE: data, the dvae section, the seed."""
  return workdir_lib.stage_identity_fields(config, DVAE_NAME)


def steve_identity_fields(config: ml_collections.ConfigDict
                          ) -> dict[str, Any]:
  """Everything that shapes STEVE besides its dVAE (recorded as parent)."""
  return workdir_lib.stage_identity_fields(config, NAME)


def dvae_identity(config: ml_collections.ConfigDict, workdir: str
                  ) -> dict[str, Any]:
  root = workdir_lib.stage1_workdir(config, workdir)
  return workdir_lib.checked_identity(dvae_dir(root),
                                      dvae_identity_fields(config), 'dVAE',
                                      root, 'train_dvae')


def steve_identity(config: ml_collections.ConfigDict, workdir: str
                   ) -> dict[str, Any]:
  root = workdir_lib.stage1_workdir(config, workdir)
  return workdir_lib.checked_identity(steve_dir(root),
                                      steve_identity_fields(config), 'STEVE',
                                      root, 'train_steve')


def dvae_parent(identity: dict[str, Any], step: int) -> dict[str, Any]:
  """What tokens and STEVE descend from: the dVAE run id and step."""
  return {'dvae_run_id': identity['run_id'], 'dvae_step': int(step)}


def check_tokens_current(config: ml_collections.ConfigDict, workdir: str,
                         split: str, parent: dict[str, Any]) -> None:
  """The tokens of `split` must come from the dVAE `parent`.

  Raises:
    UserError: missing or stale tokens, with the command that rebuilds them.
  """
  root = workdir_lib.stage1_workdir(config, workdir)
  directory = tokens_dir(root, split)
  meta = tokens_lib.read_meta(directory)
  rebuild = ('python -m slotformer_jax.main --config=<config> '
             f'--workdir={root} --mode=tokenize_frames')
  if not (meta and meta.get('complete')):
    raise MissingInputError(f'no complete dVAE tokens in {directory}; '
                            f'compute them: {rebuild}')
  if meta.get('parent') != parent:
    raise UserError(
        f'the tokens in {directory} are stale: made by dVAE '
        f'{meta.get("parent")}, the current dVAE is {parent}. Recompute '
        f'them: {rebuild}')


def check_steve_current(config: ml_collections.ConfigDict, workdir: str,
                        dvae_step: int) -> dict[str, Any]:
  """STEVE's identity, checked to descend from the current dVAE at
  `dvae_step`.

  Raises:
    UserError: STEVE was trained with another dVAE (retrain it).
  """
  parent = dvae_parent(dvae_identity(config, workdir), dvae_step)
  identity = steve_identity(config, workdir)
  if identity.get('parent') != parent:
    raise UserError(
        f'STEVE in {steve_dir(workdir_lib.stage1_workdir(config, workdir))} '
        f'was trained with dVAE {identity.get("parent")}, the current dVAE '
        f'is {parent}; using both would mix them. Retrain STEVE (it is set '
        'aside and retrained): python -m slotformer_jax.main '
        f'--config=<config> --workdir={workdir} --mode=train_steve')
  return identity


# --------------------------------------------------------------------------
# Inference: frames -> tokens, slots -> tokens -> frames (pure functions)
# --------------------------------------------------------------------------


def tokenize(dvae_params: Any, frames: jax.Array, *, dvae: DVAE) -> jax.Array:
  """uint8 frames [..., H, W, 3] -> int32 tokens [..., h * w] (raster order)."""
  lead = frames.shape[:-3]
  images = frames_to_model(frames.reshape(-1, *frames.shape[-3:]))
  tokens = dvae.apply({'params': dvae_params}, images, method=DVAE.tokenize)
  return tokens.reshape(*lead, -1)


def decode_tokens(dvae_params: Any, tokens: jax.Array, *, dvae: DVAE,
                  token_grid: tuple[int, int]) -> jax.Array:
  """int tokens [..., h * w] -> frames [..., H, W, 3] in [0, 1]."""
  lead = tokens.shape[:-1]
  images = dvae.apply({'params': dvae_params},
                      tokens.reshape(-1, *token_grid),
                      method=DVAE.decode_tokens)
  return model_to_unit(images.reshape(*lead, *images.shape[1:]))


def generate_tokens(decoder_params: Any, slots: jax.Array, *,
                    decoder: TokenDecoder,
                    presence: jax.Array | None = None
                    ) -> tuple[jax.Array, jax.Array]:
  """Greedy decoding with a key/value cache (one token's work per step).

  slots [B, N, D] -> (tokens int32 [B, L], cross-attention of the last
  layer over the slots [B, L, N], each row summing to 1); `presence`
  (optional bool [B, N]) drops absent slots from every cross-attention.
  """
  variables = {'params': decoder_params}
  cache = decoder.apply(variables, slots, presence,
                        method=TokenDecoder.init_cache)
  batch = slots.shape[0]

  def step(carry, position):
    previous, cache = carry
    token = jnp.where(position == 0, decoder.vocab_size, previous)
    logits, weights, cache = decoder.apply(
        variables, token, position, cache, method=TokenDecoder.decode_step)
    chosen = jnp.argmax(logits, axis=-1).astype(jnp.int32)
    return (chosen, cache), (chosen, weights)

  initial = (jnp.zeros((batch,), jnp.int32), cache)
  _, (tokens, weights) = jax.lax.scan(
      step, initial, jnp.arange(decoder.num_tokens))
  return tokens.T, weights.transpose(1, 0, 2)


def generate_tokens_recomputed(decoder_params: Any, slots: jax.Array, *,
                               decoder: TokenDecoder) -> jax.Array:
  """Greedy decoding by re-running the decoder over all L positions at every
  step, as the official code does (causal, so the not-yet-generated
  positions do not matter): the reference `generate_tokens` is tested and
  timed against.

  slots [B, N, D] -> tokens int32 [B, L].
  """
  variables = {'params': decoder_params}
  length = decoder.num_tokens

  def step(tokens, position):
    logits = decoder.apply(variables, slots, tokens)
    chosen = jnp.argmax(logits[:, position], axis=-1).astype(jnp.int32)
    return tokens.at[:, position].set(chosen), None

  tokens = jnp.zeros((slots.shape[0], length), jnp.int32)
  tokens, _ = jax.lax.scan(step, tokens, jnp.arange(length))
  return tokens


def generate_frames(decoder_params: Any, dvae_params: Any, slots: jax.Array,
                    *, decoder: TokenDecoder, dvae: DVAE,
                    token_grid: tuple[int, int],
                    presence: jax.Array | None = None
                    ) -> tuple[jax.Array, jax.Array]:
  """slots [..., N, D] -> (frames [..., H, W, 3] in [0, 1], masks
  [..., N, h, w]: the decoder's last-layer cross-attention of each token
  over the slots, the segmentation of a generated frame); `presence`
  (optional bool [..., N]) drops absent slots from the cross-attention."""
  lead = slots.shape[:-2]
  if presence is not None:
    presence = jnp.broadcast_to(presence, slots.shape[:-1]).reshape(
        -1, slots.shape[-2])
  tokens, weights = generate_tokens(
      decoder_params, slots.reshape(-1, *slots.shape[-2:]), decoder=decoder,
      presence=presence)
  frames = decode_tokens(dvae_params, tokens, dvae=dvae,
                         token_grid=token_grid)
  masks = weights.transpose(0, 2, 1).reshape(-1, slots.shape[-2], *token_grid)
  return (frames.reshape(*lead, *frames.shape[1:]),
          masks.reshape(*lead, *masks.shape[1:]))


def upsample_masks(masks: jax.Array, resolution: tuple[int, int]
                   ) -> jax.Array:
  """[..., N, h, w] (softmax over N) -> [..., N, H, W] bilinear (half-pixel
  centres, PyTorch's align_corners=False)."""
  shape = (*masks.shape[:-2], *resolution)
  return jax.image.resize(masks, shape, 'bilinear', antialias=False)


def _steve_module(config: ml_collections.ConfigDict) -> STEVE:
  return models.build_steve(config.steve, tuple(config.data.resolution),
                            config.dvae.vocab_size)


def token_decoder(config: ml_collections.ConfigDict) -> TokenDecoder:
  """STEVE's token decoder alone; its parameters are steve_params['decoder']."""
  return _steve_module(config).decoder


# --------------------------------------------------------------------------
# The dVAE's temperature schedule
# --------------------------------------------------------------------------


def cosine_anneal(step: int, start_value: float, final_value: float,
                  num_steps: int) -> float:
  """start_value at step 0 -> final_value at `num_steps` along half a cosine;
  final_value from then on."""
  if step >= num_steps:
    return final_value
  progress = step / num_steps
  return final_value + 0.5 * (start_value - final_value) * (
      1.0 + math.cos(math.pi * progress))


def gumbel_temperature(step: int, num_train_steps: int, *,
                       start: float = 1.0, final: float = 0.1,
                       anneal_fraction: float = 0.15) -> float:
  """The dVAE's temperature at `step`: 1.0 -> 0.1 over the first 15% of the
  steps (the official Physion dVAE), then constant."""
  anneal_steps = max(1, int(anneal_fraction * num_train_steps))
  return cosine_anneal(step, start, final, anneal_steps)


def with_gumbel_temperature(batches: Iterator[dict[str, np.ndarray]],
                            start_step: int, num_train_steps: int,
                            **schedule) -> Iterator[dict[str, np.ndarray]]:
  """Adds `gumbel_temperature` float32 [B] of each batch's step (the loss
  does not see the step, so the batch carries it)."""
  step = start_step
  for batch in batches:
    size = len(next(iter(batch.values())))
    temperature = gumbel_temperature(step, num_train_steps, **schedule)
    yield dict(batch, gumbel_temperature=np.full(size, temperature,
                                                 np.float32))
    step += 1


# --------------------------------------------------------------------------
# Stage 1: dVAE -> tokens -> STEVE
# --------------------------------------------------------------------------


def _frame_shape(config: ml_collections.ConfigDict) -> tuple[int, int, int]:
  return (*config.data.resolution, 3)


def _dvae_example(config: ml_collections.ConfigDict) -> tuple[Any, ...]:
  return jnp.zeros((1, *_frame_shape(config))), 1.0


def _steve_example(config: ml_collections.ConfigDict) -> tuple[Any, ...]:
  height, width = _steve_module(config).token_grid
  clip = jnp.zeros((1, config.steve.clip_length, *_frame_shape(config)))
  tokens = jnp.zeros((1, config.steve.clip_length, height * width), jnp.int32)
  return clip, tokens


def dvae_stage(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh, source: Any) -> Stage:
  """The dVAE's training stage (single frames, annealed Gumbel-softmax) on
  `source` (the 'train' videos; only its `batches` read it)."""
  model = models.build_dvae(config.dvae)
  stage_config = config.dvae
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  schedule = dict(start=stage_config.gumbel_start,
                  final=stage_config.gumbel_final,
                  anneal_fraction=stage_config.gumbel_anneal_fraction)

  def batches(start_step):
    frames = pipeline.train_batches(
        source, batch_size=local_batch_size, clip_length=1, seed=config.seed,
        start_step=start_step, fields=('video',),
        process_index=jax.process_index(), process_count=jax.process_count())
    return with_gumbel_temperature(
        frames, start_step, stage_config.num_train_steps, **schedule)

  return Stage(
      name=DVAE_NAME,
      directory=dvae_dir(workdir_lib.stage1_workdir(config, workdir)),
      config=stage_config,
      loss_fn=functools.partial(losses.dvae_loss, model=model),
      init_params=lambda rng: steps.init_params(model, rng,
                                                *_dvae_example(config)),
      batches=batches, logging=config.get('logging'))


def train_dvae(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh) -> None:
  slot_model = Steve(config)
  slot_model.check_compute_dtype()
  if uses_foreign_stage1(slot_model, workdir, mesh, 'dVAE'):
    return
  stage = dvae_stage(config, workdir, mesh,
                     get_video_source(config.data, 'train'))
  fit_stage(stage, mesh=mesh, seed=config.seed, what='dVAE',
            identity_fields=dvae_identity_fields(config), parent=None,
            model_fields=dvae_model_fields(config))


def tokenize_frames(config: ml_collections.ConfigDict, workdir: str,
                    mesh: Mesh) -> None:
  """The frozen dVAE's argmax tokens of every training frame, stored once
  (skipped when they came from the current dVAE checkpoint)."""
  slot_model = Steve(config)
  if uses_foreign_stage1(slot_model, workdir, mesh, 'tokens'):
    return
  params, dvae_step = slot_model.load_dvae(workdir, mesh)
  parent = dvae_parent(dvae_identity(config, workdir), dvae_step)
  dvae = models.build_dvae(config.dvae)
  batched = sharding.batch_sharding(mesh)
  run = jax.jit(
      functools.partial(tokenize, dvae=dvae),
      in_shardings=(sharding.replicated_sharding(mesh), batched),
      out_shardings=batched)
  local_batch_size = sharding.per_host_batch_size(
      config.dvae.tokenize_batch_size, mesh)
  height, width = _steve_module(config).token_grid
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
    inference.encode_videos_into(
        lambda: tokens_lib.TokenWriter(directory, len(source), height * width,
                                       dvae_step, parent=parent),
        source, lambda b, c, frames, carry: (run(params, frames), None),
        chunk_length=config.extraction.chunk_length,
        batch_size=local_batch_size, mesh=mesh, desc=f'tokenize {split}')
    logger.info('tokenized %d %s videos', len(source), split)


def steve_stage(config: ml_collections.ConfigDict, workdir: str,
                mesh: Mesh, source: Any) -> Stage:
  """STEVE's training stage on `source` (the 'train' videos with their
  tokens, see `train_steve`; only its `batches` read it)."""
  model = _steve_module(config)
  stage_config = config.steve
  root = workdir_lib.stage1_workdir(config, workdir)
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  return Stage(
      name=NAME, directory=steve_dir(root), config=stage_config,
      loss_fn=functools.partial(losses.steve_loss, model=model),
      init_params=lambda rng: steps.init_params(model, rng,
                                                *_steve_example(config)),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=stage_config.clip_length, seed=config.seed,
          start_step=start_step, fields=('video', 'tokens'),
          process_index=jax.process_index(),
          process_count=jax.process_count()),
      logging=config.get('logging'))


def train_steve(config: ml_collections.ConfigDict, workdir: str,
                mesh: Mesh) -> None:
  """STEVE on the tokens of the current dVAE. A STEVE trained with another
  dVAE (or other settings) is set aside and retrained from scratch."""
  slot_model = Steve(config)
  slot_model.check_compute_dtype()
  if uses_foreign_stage1(slot_model, workdir, mesh, 'STEVE'):
    return
  _, dvae_step = slot_model.load_dvae(workdir, mesh)
  parent = dvae_parent(dvae_identity(config, workdir), dvae_step)
  for split in TOKENIZED_SPLITS:
    check_tokens_current(config, workdir, split, parent)
  root = workdir_lib.stage1_workdir(config, workdir)
  stage = steve_stage(config, workdir, mesh, tokens_lib.TokenSource(
      tokens_dir(root, 'train'), get_video_source(config.data, 'train')))
  fit_stage(stage, mesh=mesh, seed=config.seed, what='STEVE',
            identity_fields=steve_identity_fields(config), parent=parent,
            model_fields=steve_model_fields(config))


# --------------------------------------------------------------------------
# The slot model
# --------------------------------------------------------------------------


class Steve(SlotModel):
  """dVAE + STEVE: `config.dvae`, `config.steve`."""

  name = NAME
  label = 'STEVE'
  stage1 = {'train_dvae': train_dvae, 'tokenize_frames': tokenize_frames,
            'train_steve': train_steve}
  stage_labels = {DVAE_NAME: 'dVAE', NAME: 'STEVE'}
  mask_source = ('decoder cross-attention (rollouts), Slot Attention '
                 '(STEVE on the videos)')
  # `compute_dtype` wraps the losses and the rollout evaluation of SAVi and
  # SlotFormer, not STEVE's; refuse rather than ignore another setting.
  compute_dtypes = ('float32',)

  def __init__(self, config: ml_collections.ConfigDict):
    super().__init__(config)
    self.model = _steve_module(config)
    self.dvae = models.build_dvae(config.dvae)
    self.token_decoder = token_decoder(config)
    self.resolution = tuple(config.data.resolution)

  @property
  def slot_shape(self) -> tuple[int, int]:
    return self.config.steve.num_slots, self.config.steve.slot_size

  @property
  def num_train_steps(self) -> dict[str, int]:
    return {DVAE_NAME: self.config.dvae.num_train_steps,
            NAME: self.config.steve.num_train_steps}

  def dvae_param_shapes(self) -> Any:
    return inference.param_shapes(self.dvae, *_dvae_example(self.config))

  def steve_param_shapes(self) -> Any:
    return inference.param_shapes(self.model, *_steve_example(self.config))

  def _load_part(self, workdir: str, mesh: Mesh, key: str
                 ) -> tuple[Any, int]:
    root = workdir_lib.stage1_workdir(self.config, workdir)
    directory, fields, shapes = {
        DVAE_NAME: (dvae_dir, dvae_model_fields, self.dvae_param_shapes),
        NAME: (steve_dir, steve_model_fields, self.steve_param_shapes)}[key]
    label = self.stage_labels[key]
    workdir_lib.check_model_config(directory(root), fields(self.config),
                                   label)
    return inference.restore(
        directory(root), shapes(), mesh, what=label, workdir=root,
        mode=f'train_{key}', num_train_steps=self.num_train_steps[key])

  def load_dvae(self, workdir: str, mesh: Mesh) -> tuple[Any, int]:
    """The dVAE's trained parameters (replicated) and their step."""
    return self._load_part(workdir, mesh, DVAE_NAME)

  def load_steve(self, workdir: str, mesh: Mesh) -> tuple[Any, int]:
    """STEVE's trained parameters (replicated) and their step."""
    return self._load_part(workdir, mesh, NAME)

  def check_identity(self, workdir: str) -> dict[str, Any]:
    dvae_identity(self.config, workdir)
    return steve_identity(self.config, workdir)

  def chain(self, workdir: str, steps: dict[str, int]
            ) -> tuple[dict[str, Any], dict[str, Any]]:
    dvae_step, steve_step = int(steps[DVAE_NAME]), int(steps[NAME])
    dvae = dvae_identity(self.config, workdir)
    steve = check_steve_current(self.config, workdir, dvae_step)
    return ({DVAE_NAME: {'run_id': dvae['run_id'], 'step': dvae_step,
                         'fingerprint': dvae['fingerprint']},
             NAME: {'run_id': steve['run_id'], 'step': steve_step,
                    'fingerprint': steve['fingerprint'],
                    'parent': steve['parent']}},
            workdir_lib.slots_parent(steve, steve_step, NAME))

  def load(self, workdir: str, mesh: Mesh) -> Loaded:
    steve_params, steve_step = self.load_steve(workdir, mesh)
    dvae_params, dvae_step = self.load_dvae(workdir, mesh)
    steps = {DVAE_NAME: dvae_step, NAME: steve_step}
    identity, slots_parent = self.chain(workdir, steps)
    return Loaded(params={NAME: steve_params, DVAE_NAME: dvae_params},
                  steps=steps, identity=identity, step=steve_step,
                  slots_parent=slots_parent)

  def encode(self, params: Any, video: jax.Array, rng: jax.Array,
             carry: Any) -> tuple[jax.Array, Any]:
    del rng  # deterministic
    slots, _, carry = self.model.apply(
        {'params': params[NAME]}, frames_to_model(video), carry,
        method=STEVE.encode)
    return slots, carry

  def decode(self, params: Any, slots: jax.Array,
             presence: jax.Array | None = None) -> Decoded:
    frames, masks = generate_frames(
        params[NAME]['decoder'], params[DVAE_NAME], slots,
        decoder=self.token_decoder, dvae=self.dvae,
        token_grid=self.model.token_grid, presence=presence)
    return Decoded(recon=frames, alpha_masks=upsample_masks(
        masks, self.resolution)[..., None])

  def observe(self, params: Any, slots: jax.Array, video: jax.Array,
              carry: Any) -> tuple[jax.Array, None, Any]:
    """STEVE's Slot Attention masks of the real frames (re-encoded, the
    state carried across chunks), upsampled to the frame."""
    del slots
    _, masks, carry = self.model.apply(
        {'params': params[NAME]}, frames_to_model(video), carry,
        method=STEVE.encode)
    return upsample_masks(masks, self.resolution), None, carry
