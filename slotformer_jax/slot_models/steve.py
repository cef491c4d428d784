"""STEVE as the slot model (the paper's Physion pipeline): `slot_model='steve'`,
settings in `config.dvae` and `config.steve`.

Stage 1 is `train_dvae`, `tokenize_frames` (the frozen dVAE's tokens of every
training frame, stored once) and `train_steve` (trained on those tokens; its
parent is the dVAE). Decoding slots *generates* a frame token by token (a
key/value cache, then the dVAE's decoder); its masks are the token decoder's
last-layer cross-attention over the slots. STEVE has no differentiable pixel
decoder, so SlotFormer trains on its slots with L_S alone (as the paper), and
it computes in float32 only. Parameters (`Loaded.params`): {'dvae': the
dVAE's, 'steve': STEVE's}. The stages, the files each writes and their
parents: docs/steve.md; with several seeds: docs/seeds.md.
"""

from __future__ import annotations

from collections.abc import Iterator
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import losses
from slotformer_jax.data import slots as extracted
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.modules.dvae import DOWNSAMPLING as DVAE_DOWNSAMPLING
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.encoders import feature_grid
from slotformer_jax.modules.savi import FrameStep
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.slot_init import LearnedSlots
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.modules.token_decoder import TokenDecoder
from slotformer_jax.modules.transitions import SlotTransition
from slotformer_jax.slot_models.base import Decoded
from slotformer_jax.slot_models.base import Derived
from slotformer_jax.slot_models.base import Part
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.workdir import identity as identity_lib

DVAE_NAME = 'dvae'
NAME = 'steve'
TOKENS = 'tokens'
TOKENIZED_SPLITS = ('train',)  # STEVE trains on these; nothing else needs them


# --------------------------------------------------------------------------
# Building the modules from `config.dvae` / `config.steve`
# --------------------------------------------------------------------------


def build_dvae(dvae: ml_collections.ConfigDict) -> DVAE:
  """STEVE's tokenizer (`config.dvae`)."""
  return DVAE(vocab_size=dvae.vocab_size, hidden_size=dvae.hidden_size)


def build_steve(steve: ml_collections.ConfigDict, resolution: tuple[int, int],
                vocab_size: int) -> STEVE:
  """STEVE from `config.steve` for frames of `resolution` (H, W), predicting
  the tokens of a dVAE with `vocab_size` codes (`config.dvae.vocab_size`).

  Its slot encoder is SAVi's parts (learned initial slots, Slot Attention keeping
  its masks, Transformer + per-slot LSTM, no pixel decoder); the token
  decoder's size is `slot_size`, as officially.
  """
  epsilon = steve.layer_norm_epsilon
  predictor = steve.predictor
  parts = dict(
      encoder=CNNEncoder(
          features=tuple(steve.encoder.features),
          kernel_size=steve.encoder.kernel_size,
          strides=tuple(steve.encoder.strides),
          output_size=steve.encoder.output_size,
          padding=steve.encoder.padding, layer_norm_epsilon=epsilon),
      initializer=LearnedSlots(steve.num_slots, steve.slot_size),
      frame_step=FrameStep(
          corrector=SlotAttention(steve.slot_attention.num_iterations,
                                  steve.slot_attention.mlp_size,
                                  layer_norm_epsilon=epsilon,
                                  return_attention=True),
          predictor=SlotTransition(
              num_layers=predictor.num_layers, num_heads=predictor.num_heads,
              mlp_size=predictor.mlp_size, lstm_size=predictor.lstm_size,
              layer_norm_epsilon=epsilon)))
  height, width = resolution
  token_grid = (height // DVAE_DOWNSAMPLING, width // DVAE_DOWNSAMPLING)
  return STEVE(
      **parts,
      decoder=TokenDecoder(
          vocab_size=vocab_size, num_tokens=token_grid[0] * token_grid[1],
          dim=steve.slot_size, num_layers=steve.decoder.num_layers,
          num_heads=steve.decoder.num_heads,
          dropout_rate=steve.decoder.dropout_rate),
      token_grid=token_grid,
      feature_grid=feature_grid(resolution, steve.encoder.strides))


def token_decoder(steve: STEVE) -> TokenDecoder:
  """STEVE's token decoder alone; its parameters are steve_params['decoder']."""
  return steve.decoder


def dvae_model_fields(dvae: ml_collections.ConfigDict) -> dict[str, Any]:
  """The settings that determine the dVAE's parameters."""
  return identity_lib.plain({'vocab_size': dvae.vocab_size,
                             'hidden_size': dvae.hidden_size})


def steve_model_fields(steve: ml_collections.ConfigDict,
                       resolution: tuple[int, int],
                       vocab_size: int) -> dict[str, Any]:
  """The settings that determine STEVE's parameters (incl. its dVAE's
  vocabulary)."""
  section = steve.to_dict()
  fields = {key: section[key] for key in (
      'num_slots', 'slot_size', 'encoder', 'slot_attention', 'predictor',
      'decoder', 'layer_norm_epsilon')}
  fields['resolution'] = list(resolution)
  fields['vocab_size'] = vocab_size
  return identity_lib.plain(fields)


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
# The slot model
# --------------------------------------------------------------------------


class Steve(SlotModel):
  """dVAE + STEVE: `config.dvae`, `config.steve`."""

  name = NAME
  label = 'STEVE'
  mask_source = ('decoder cross-attention (rollouts), Slot Attention '
                 '(STEVE on the videos)')
  # `compute_dtype` wraps the losses and the rollout evaluation of SAVi and
  # SlotFormer, not STEVE's; refuse rather than ignore another setting.
  compute_dtypes = ('float32',)

  def __init__(self, config: ml_collections.ConfigDict):
    super().__init__(config)
    self.resolution = tuple(config.data.resolution)

  # Built on first use, so that the config checks report a bad value as one
  # line before any module is.
  @functools.cached_property
  def model(self) -> Any:
    return build_steve(self.config.steve, self.resolution,
                       self.config.dvae.vocab_size)

  @functools.cached_property
  def dvae(self) -> Any:
    return build_dvae(self.config.dvae)

  @functools.cached_property
  def token_decoder(self) -> Any:
    return token_decoder(self.model)

  @property
  def slot_shape(self) -> tuple[int, int]:
    return self.config.steve.num_slots, self.config.steve.slot_size

  @property
  def decode_steps(self) -> int:
    height, width = self.model.token_grid
    return height * width

  @property
  def parts(self) -> tuple[Part, ...]:
    config, dvae, steve = self.config, self.config.dvae, self.config.steve
    frame = np.zeros((1, *self.resolution, 3), np.float32)
    height, width = self.model.token_grid
    clip = np.zeros((1, steve.clip_length, *self.resolution, 3), np.float32)
    tokens = np.zeros((1, steve.clip_length, height * width), np.int32)
    schedule = dict(start=dvae.gumbel_start, final=dvae.gumbel_final,
                    anneal_fraction=dvae.gumbel_anneal_fraction)

    def with_temperature(batches, start_step):
      return with_gumbel_temperature(batches, start_step,
                                     dvae.num_train_steps, **schedule)

    data = config.data.to_dict()
    return (
        Part(name=DVAE_NAME, label='dVAE', module=self.dvae, section=dvae,
             example=(frame, 1.0),
             loss=functools.partial(losses.dvae_loss, model=self.dvae),
             batch_fields=('video',), clip_length=1,
             model_fields=dvae_model_fields(dvae),
             identity_fields=identity_lib.stage_fields(
                 config.seed, data, DVAE_NAME, dvae.to_dict()),
             with_batches=with_temperature),
        Part(name=NAME, label='STEVE', module=self.model, section=steve,
             example=(clip, tokens),
             loss=functools.partial(losses.steve_loss, model=self.model),
             batch_fields=('video', TOKENS), clip_length=steve.clip_length,
             model_fields=steve_model_fields(steve, self.resolution,
                                             dvae.vocab_size),
             identity_fields=identity_lib.stage_fields(
                 config.seed, data, NAME, steve.to_dict()),
             parent=DVAE_NAME, reads=(TOKENS,)),
    )

  @property
  def derived(self) -> tuple[Derived, ...]:
    height, width = self.model.token_grid
    return (Derived(
        name=TOKENS, mode='tokenize_frames', source=DVAE_NAME,
        splits=TOKENIZED_SPLITS,
        encode=functools.partial(tokenize, dvae=self.dvae),
        writer=lambda directory, num_videos, step, parent: (
            extracted.TokenWriter(directory, num_videos, height * width,
                                  step, parent=parent)),
        reader=extracted.TokenSource, read_meta=extracted.read_meta,
        batch_size=self.config.dvae.tokenize_batch_size,
        chunk_length=self.config.extraction.chunk_length),)

  def check_config(self, stages: frozenset[str]) -> list[str]:
    """The dVAE encodes 4x4 pixels per token and decodes two x2 pixel
    shuffles, so only multiples of 4 come back at the frame size."""
    del stages
    if not any(side % 4 for side in self.resolution):
      return []
    near = tuple(max(4, 4 * round(side / 4)) for side in self.resolution)
    return [
        f'data.resolution {self.resolution} is not a size the dVAE can '
        'reconstruct: it makes one token of every 4x4 pixels and decodes '
        f'them back x4, so both sides must be multiples of 4 (e.g. {near})']

  def encode(self, params: Any, video: jax.Array, rng: jax.Array,
             carry: Any) -> tuple[jax.Array, Any]:
    del rng  # deterministic
    slots, _, carry = self.model.apply(
        {'params': params[NAME]}, self.to_model(video), carry,
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
        {'params': params[NAME]}, self.to_model(video), carry,
        method=STEVE.encode)
    return upsample_masks(masks, self.resolution), None, carry
