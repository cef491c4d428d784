"""SAVi: Slot Attention for Video (Kipf et al., 2022), unconditional or
conditioned on the first frame's boxes / centre points.

SAVi is composed from its parts, each chosen by a field:
  encoder    CNN -> position embedding -> LayerNorm + MLP (`CNNEncoder`);
  posterior  optional head on the initial slots: none | linear | mlp
             (`GaussianSlotSampler`: its mean, or a sample when stochastic);
  corrector  Slot Attention;
  predictor  f_trans: transformer | transformer_lstm | residual_mlp;
  decoder    spatial broadcast (`SpatialBroadcastDecoder`).
Per frame t: CNN features h_t; S~'_t = head(S~_t); slots S_t =
SlotAttention(S~'_t, h_t); the next frame's initial slots S~_{t+1} =
f_trans(S_t); S~_1 are learned vectors, Gaussian draws, or (conditional
SAVi, `initial_slots` 'boxes' / 'points') an MLP of the first frame's
object boxes or their centres (`CoordinateSlotInit`). Each frame's slots
are decoded by the decoder. With `stochastic=True` the head samples from
the Gaussian it predicts (stochastic SAVi). docs/official_architectures.md lists which
choices reproduce each official model.

Shapes: video [batch, time, height, width, 3] in [-1, 1];
slots [batch, time, num_slots, slot_size].
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.linen as nn
from flax import struct
import jax
import jax.numpy as jnp

from slotformer_jax.modules.decoders import DecodedSlots
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.encoders import SAME
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.stochastic_savi import GaussianSlotSampler
from slotformer_jax.modules.stochastic_savi import NO_HEAD
from slotformer_jax.modules.stochastic_savi import POSTERIOR_HEADS
from slotformer_jax.modules.transformer import TransformerEncoder

TRANSFORMER = 'transformer'
TRANSFORMER_LSTM = 'transformer_lstm'
RESIDUAL_MLP = 'residual_mlp'
PREDICTORS = (TRANSFORMER, TRANSFORMER_LSTM, RESIDUAL_MLP)

# (initial slots of the next frame [B, N, D], LSTM carry or ()).
SAViCarry = tuple[jax.Array, Any]


def initial_lstm_state(slots: jax.Array, lstm_size: int):
  """Zero per-slot LSTM carry for slots [B, N, D]: (c, h) [B, N, lstm_size]."""
  if not lstm_size:
    return ()
  zeros = jnp.zeros((*slots.shape[:-1], lstm_size), slots.dtype)
  return (zeros, zeros)


class SlotTransition(nn.Module):
  """f_trans: a Transformer over one frame's slots, optionally + per-slot LSTM.

  The LSTM variant is the Transformer-LSTM module of PARTS (used by the
  official OBJ3D / PHYRE SAVi and by the Slot-LSTM baseline): the
  Transformer's output feeds an LSTM cell per slot whose hidden state is
  projected back to D, with no residual.

  Attributes:
    num_layers, num_heads, mlp_size, pre_norm, dropout_rate,
      layer_norm_epsilon: the Transformer.
    lstm_size: hidden size of the per-slot LSTM; 0 disables it.
  """

  num_layers: int = 2
  num_heads: int = 4
  mlp_size: int = 512
  pre_norm: bool = True
  lstm_size: int = 0
  dropout_rate: float = 0.0
  layer_norm_epsilon: float = 1e-6

  @nn.compact
  def __call__(self, slots: jax.Array, lstm_state=(), *,
               deterministic: bool = True):
    """slots [B, N, D] -> (next slots [B, N, D], new LSTM state)."""
    x = TransformerEncoder(
        num_layers=self.num_layers, num_heads=self.num_heads,
        mlp_size=self.mlp_size, pre_norm=self.pre_norm,
        dropout_rate=self.dropout_rate,
        layer_norm_epsilon=self.layer_norm_epsilon,
        name='transformer')(slots, deterministic=deterministic)
    if not self.lstm_size:
      return x, ()
    lstm_state, hidden = nn.OptimizedLSTMCell(self.lstm_size, name='lstm')(
        lstm_state, x)
    return nn.Dense(slots.shape[-1], name='lstm_out')(hidden), lstm_state


class ResidualMLPTransition(nn.Module):
  """f_trans of the official CLEVRER StoSAVi: LN -> MLP, plus a residual.

  x' = LN(x); out = Linear(ReLU(Linear(x'))) + (x' if pre_norm else x).
  With pre_norm the residual is the *normalised* input, as in the official
  model (Slot Attention normalises its slots anyway). The MLP mixes no
  information between slots, which the official config says keeps slots
  from sharing objects.

  Attributes:
    mlp_size: hidden size (2 * D officially).
    pre_norm: residual from the normalised (True) or the raw input.
    layer_norm_epsilon: of the LayerNorm.
  """

  mlp_size: int = 256
  pre_norm: bool = True
  layer_norm_epsilon: float = 1e-6

  @nn.compact
  def __call__(self, slots: jax.Array, lstm_state=(), *,
               deterministic: bool = True):
    """slots [B, N, D] -> (next slots [B, N, D], ())."""
    del deterministic  # no dropout here
    normed = nn.LayerNorm(epsilon=self.layer_norm_epsilon, name='norm')(slots)
    hidden = nn.relu(nn.Dense(self.mlp_size, name='hidden')(normed))
    out = nn.Dense(slots.shape[-1], name='out')(hidden)
    return out + (normed if self.pre_norm else slots), lstm_state


def build_predictor(kind: str, *, num_layers: int, num_heads: int,
                    mlp_size: int, lstm_size: int, pre_norm: bool,
                    dropout_rate: float, layer_norm_epsilon: float,
                    name: str) -> nn.Module:
  """The f_trans module of `kind` (one of PREDICTORS)."""
  if kind == RESIDUAL_MLP:
    return ResidualMLPTransition(mlp_size=mlp_size, pre_norm=pre_norm,
                                 layer_norm_epsilon=layer_norm_epsilon,
                                 name=name)
  if kind not in (TRANSFORMER, TRANSFORMER_LSTM):
    raise ValueError(f'predictor kind must be one of {PREDICTORS}, got '
                     f'{kind!r}')
  if (kind == TRANSFORMER_LSTM) != bool(lstm_size):
    raise ValueError(
        f"predictor '{kind}' with lstm_size={lstm_size}: "
        f"'{TRANSFORMER_LSTM}' needs lstm_size > 0, '{TRANSFORMER}' needs 0")
  return SlotTransition(
      num_layers=num_layers, num_heads=num_heads, mlp_size=mlp_size,
      pre_norm=pre_norm, lstm_size=lstm_size, dropout_rate=dropout_rate,
      layer_norm_epsilon=layer_norm_epsilon, name=name)


LEARNED = 'learned'
GAUSSIAN = 'gaussian'
BOXES = 'boxes'
POINTS = 'points'
INITIAL_SLOTS = (LEARNED, GAUSSIAN, BOXES, POINTS)
CONDITIONAL = (BOXES, POINTS)


def conditioning_coordinates(boxes: jax.Array, num_slots: int,
                             kind: str) -> jax.Array:
  """The per-slot coordinates conditional SAVi embeds.

  boxes [B, O, 4] (ymin, xmin, ymax, xmax) normalised, an absent object all
  zeros (SAVi's padding box) -> [B, num_slots, 4] ('boxes') or [B,
  num_slots, 2] ('points': the box centres (y, x)). Slot 0 gets a zero
  background box (as SAVi's `prepend_background`), slot 1 + i object row i,
  rows past the objects zero boxes (as SAVi pads to its max_instances).
  """
  batch, rows = boxes.shape[:2]
  if rows + 1 > num_slots:
    raise ValueError(f'conditional SAVi needs a slot per box row plus one '
                     f'for the background: {rows} box rows, {num_slots} '
                     'slots')
  coords = jnp.concatenate([
      jnp.zeros((batch, 1, 4), boxes.dtype), boxes,
      jnp.zeros((batch, num_slots - rows - 1, 4), boxes.dtype)], axis=1)
  if kind == POINTS:
    coords = jnp.stack([(coords[..., 0] + coords[..., 2]) / 2,
                        (coords[..., 1] + coords[..., 3]) / 2], axis=-1)
  return coords


class CoordinateSlotInit(nn.Module):
  """Initial slots from coordinates: Linear -> ReLU -> Linear, per slot.

  SAVi's conditional initialiser (`CoordinateEncoderStateInit` with an MLP
  of hidden size 256 and no LayerNorm in its MOVi configs).
  """

  slot_size: int
  hidden_size: int = 256

  @nn.compact
  def __call__(self, coords: jax.Array) -> jax.Array:
    """coords [B, N, 4 or 2] -> slots [B, N, slot_size]."""
    hidden = nn.relu(nn.Dense(self.hidden_size, name='hidden')(coords))
    return nn.Dense(self.slot_size, name='out')(hidden)


class SAViStep(nn.Module):
  """One frame of SAVi: posterior head, correct, predict."""

  num_iterations: int
  slot_mlp_size: int
  predictor_kind: str
  predictor_layers: int
  predictor_heads: int
  predictor_mlp_size: int
  predictor_lstm_size: int
  predictor_pre_norm: bool = True
  predictor_dropout_rate: float = 0.0
  posterior_head: str = NO_HEAD
  stochastic: bool = False
  prior_sigma: float = 0.1
  layer_norm_epsilon: float = 1e-6

  @nn.compact
  def __call__(self, carry: SAViCarry, features: jax.Array, *,
               deterministic: bool = True):
    """carry, features [B, M, C] -> (carry, (slots [B, N, D], kl [B, N]))."""
    initial_slots, lstm_state = carry
    if self.posterior_head != NO_HEAD:
      initial_slots, kl = GaussianSlotSampler(
          self.prior_sigma, kind=self.posterior_head,
          stochastic=self.stochastic,
          layer_norm_epsilon=self.layer_norm_epsilon,
          name='posterior_head')(initial_slots)
    else:
      kl = jnp.zeros(initial_slots.shape[:-1], initial_slots.dtype)
    slots = SlotAttention(self.num_iterations, self.slot_mlp_size,
                          layer_norm_epsilon=self.layer_norm_epsilon,
                          name='corrector')(initial_slots, features)
    next_slots, lstm_state = build_predictor(
        self.predictor_kind, num_layers=self.predictor_layers,
        num_heads=self.predictor_heads, mlp_size=self.predictor_mlp_size,
        lstm_size=self.predictor_lstm_size, pre_norm=self.predictor_pre_norm,
        dropout_rate=self.predictor_dropout_rate,
        layer_norm_epsilon=self.layer_norm_epsilon,
        name='predictor')(slots, lstm_state, deterministic=deterministic)
    return (next_slots, lstm_state), (slots, kl)


@struct.dataclass
class SAViOutput:
  """slots [B, T, N, D]; kl [B, T, N] (zeros unless stochastic);
  decoded frames (see DecodedSlots) with leading [B, T]; the carry that
  continues the video in a later call."""

  slots: jax.Array
  kl: jax.Array
  decoded: DecodedSlots | None
  carry: SAViCarry


class SAVi(nn.Module):
  """Unconditional (stochastic) SAVi. See the module docstring.

  Attributes:
    resolution: (H, W) of the input frames.
    num_slots, slot_size: N and D_slot.
    encoder_features, encoder_kernel_size, encoder_strides, encoder_size,
      encoder_padding: the CNN encoder (D_enc = encoder_size).
    num_iterations, slot_mlp_size: the Slot Attention corrector.
    predictor_kind: f_trans, one of PREDICTORS; predictor_*: its sizes
      (see SlotTransition and ResidualMLPTransition).
    posterior_head: 'none', 'linear' or 'mlp' (see GaussianSlotSampler).
    decoder_*: the spatial-broadcast decoder.
    stochastic, prior_sigma: stochastic SAVi (needs a posterior head).
    initial_slots: one of INITIAL_SLOTS (see `initial_carry`).
    conditioning_mlp_size: hidden size of the conditional initialiser.
    layer_norm_epsilon: of every LayerNorm (1e-5 in the official models).
  """

  resolution: tuple[int, int] = (64, 64)
  num_slots: int = 6
  slot_size: int = 128
  encoder_features: Sequence[int] = (64, 64, 64, 64)
  encoder_kernel_size: int = 5
  encoder_strides: Sequence[int] = (1, 1, 1, 1)
  encoder_size: int = 128
  encoder_padding: str = SAME
  num_iterations: int = 2
  slot_mlp_size: int = 256
  predictor_kind: str = TRANSFORMER
  predictor_layers: int = 2
  predictor_heads: int = 4
  predictor_mlp_size: int = 512
  predictor_lstm_size: int = 0
  predictor_pre_norm: bool = True
  predictor_dropout_rate: float = 0.0
  posterior_head: str = NO_HEAD
  decoder_broadcast_resolution: tuple[int, int] = (8, 8)
  decoder_features: Sequence[int] = (64, 64, 64, 64)
  decoder_kernel_size: int = 5
  stochastic: bool = False
  prior_sigma: float = 0.1
  initial_slots: str = LEARNED
  conditioning_mlp_size: int = 256
  layer_norm_epsilon: float = 1e-6

  def setup(self):
    if self.posterior_head not in POSTERIOR_HEADS:
      raise ValueError(f'posterior_head must be one of {POSTERIOR_HEADS}, '
                       f'got {self.posterior_head!r}')
    if self.stochastic and self.posterior_head == NO_HEAD:
      raise ValueError("stochastic SAVi samples from its posterior head: set "
                       "posterior_head to 'linear' or 'mlp'")
    self.encoder = CNNEncoder(
        features=self.encoder_features, kernel_size=self.encoder_kernel_size,
        strides=self.encoder_strides, output_size=self.encoder_size,
        padding=self.encoder_padding,
        layer_norm_epsilon=self.layer_norm_epsilon)
    if self.initial_slots == LEARNED:
      self.slot_init = self.param(
          'initial_slots', nn.initializers.normal(stddev=1.0),
          (self.num_slots, self.slot_size))
    elif self.initial_slots in CONDITIONAL:
      self.slot_init_mlp = CoordinateSlotInit(
          self.slot_size, self.conditioning_mlp_size)
    elif self.initial_slots == GAUSSIAN:
      self.slot_init_mean = self.param(
          'initial_slots_mean', nn.initializers.normal(stddev=1.0),
          (self.slot_size,))
      self.slot_init_log_sigma = self.param(
          'initial_slots_log_sigma', nn.initializers.zeros_init(),
          (self.slot_size,))
    else:
      raise ValueError("initial_slots must be 'learned' or 'gaussian', got "
                       f'{self.initial_slots!r}')
    # Scanned over time in `encode`; its parameters are shared by all frames.
    self.frame_step = SAViStep(
        num_iterations=self.num_iterations,
        slot_mlp_size=self.slot_mlp_size,
        predictor_kind=self.predictor_kind,
        predictor_layers=self.predictor_layers,
        predictor_heads=self.predictor_heads,
        predictor_mlp_size=self.predictor_mlp_size,
        predictor_lstm_size=self.predictor_lstm_size,
        predictor_pre_norm=self.predictor_pre_norm,
        predictor_dropout_rate=self.predictor_dropout_rate,
        posterior_head=self.posterior_head,
        stochastic=self.stochastic, prior_sigma=self.prior_sigma,
        layer_norm_epsilon=self.layer_norm_epsilon)
    self.decoder = SpatialBroadcastDecoder(
        output_resolution=tuple(self.resolution),
        broadcast_resolution=tuple(self.decoder_broadcast_resolution),
        features=self.decoder_features, kernel_size=self.decoder_kernel_size)

  def initial_carry(self, batch_size: int,
                    boxes: jax.Array | None = None) -> SAViCarry:
    """The first frame's initial slots (+ zero LSTM state).

    'learned': one learned vector per slot (SlotFormer's SAVi), so slot n
    starts the same way in every video. 'gaussian': every slot drawn from one
    learned Gaussian (the original Slot Attention; draws from the 'sample'
    RNG), so slots are exchangeable and cannot specialise by position.
    'boxes' / 'points' (conditional SAVi): slot 1 + i embeds the first
    frame's box i [B, O, 4] (or its centre), slot 0 the background (see
    `conditioning_coordinates`); `boxes` is required then, ignored otherwise.
    """
    shape = (batch_size, self.num_slots, self.slot_size)
    if self.initial_slots in CONDITIONAL:
      if boxes is None:
        raise ValueError(f"initial_slots={self.initial_slots!r} needs the "
                         "first frame's boxes")
      slots = self.slot_init_mlp(conditioning_coordinates(
          boxes.astype(jnp.float32), self.num_slots, self.initial_slots))
    elif self.initial_slots == LEARNED:
      slots = jnp.broadcast_to(self.slot_init, shape)
    else:
      noise = jax.random.normal(self.make_rng('sample'), shape)
      slots = self.slot_init_mean + jnp.exp(self.slot_init_log_sigma) * noise
    lstm_size = (self.predictor_lstm_size
                 if self.predictor_kind == TRANSFORMER_LSTM else 0)
    return slots, initial_lstm_state(slots, lstm_size)

  def encode(self, video: jax.Array, carry: SAViCarry | None = None, *,
             deterministic: bool = True, boxes: jax.Array | None = None):
    """video [B, T, H, W, 3] -> (slots [B,T,N,D], kl [B,T,N], carry).

    `carry` continues a video from an earlier chunk (None: start fresh, from
    `boxes` [B, O, 4] of the first frame for conditional SAVi).
    `deterministic=False` enables the predictor's dropout ('dropout' RNG).
    """
    batch, time = video.shape[:2]
    features = self.encoder(video.reshape(batch * time, *video.shape[2:]))
    features = features.reshape(batch, time, *features.shape[1:])
    if carry is None:
      carry = self.initial_carry(batch, boxes)
    scan = nn.scan(
        lambda step, c, x: step(c, x, deterministic=deterministic),
        variable_broadcast='params',
        split_rngs={'params': False, 'sample': True, 'dropout': True},
        in_axes=1, out_axes=1)
    carry, (slots, kl) = scan(self.frame_step, carry, features)
    return slots, kl, carry

  def decode(self, slots: jax.Array) -> DecodedSlots:
    """slots [..., N, D] -> DecodedSlots with leading [...]."""
    return self.decoder(slots)

  def __call__(self, video: jax.Array, carry: SAViCarry | None = None,
               decode: bool = True, *,
               deterministic: bool = True,
               boxes: jax.Array | None = None) -> SAViOutput:
    slots, kl, carry = self.encode(video, carry, deterministic=deterministic,
                                   boxes=boxes)
    decoded = self.decode(slots) if decode else None
    return SAViOutput(slots=slots, kl=kl, decoded=decoded, carry=carry)
