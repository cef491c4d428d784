"""SAVi: Slot Attention for Video (Kipf et al., 2022), unconditional variant.

Per frame t: CNN features h_t; slots S_t = SlotAttention(S~_t, h_t) (the
corrector); the next frame's initial slots S~_{t+1} = f_trans(S_t) (the
predictor); S~_1 are learned vectors. Each frame's slots are decoded by a
spatial-broadcast decoder. With `stochastic=True` the initial slots are
sampled from a Gaussian predicted from f_trans's output (stochastic SAVi).

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
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.stochastic_savi import GaussianSlotSampler
from slotformer_jax.modules.transformer import TransformerEncoder

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
  official OBJ3D SAVi and by the Slot-LSTM baseline).

  Attributes:
    num_layers, num_heads, mlp_size, pre_norm: the Transformer.
    lstm_size: hidden size of the per-slot LSTM; 0 disables it.
  """

  num_layers: int = 2
  num_heads: int = 4
  mlp_size: int = 512
  pre_norm: bool = True
  lstm_size: int = 0

  @nn.compact
  def __call__(self, slots: jax.Array, lstm_state=()):
    """slots [B, N, D] -> (next slots [B, N, D], new LSTM state)."""
    x = TransformerEncoder(
        num_layers=self.num_layers, num_heads=self.num_heads,
        mlp_size=self.mlp_size, pre_norm=self.pre_norm,
        name='transformer')(slots)
    if not self.lstm_size:
      return x, ()
    lstm_state, hidden = nn.OptimizedLSTMCell(self.lstm_size, name='lstm')(
        lstm_state, x)
    return nn.Dense(slots.shape[-1], name='lstm_out')(hidden), lstm_state


class SAViStep(nn.Module):
  """One frame of SAVi: (optionally sample,) correct, predict."""

  num_iterations: int
  slot_mlp_size: int
  predictor_layers: int
  predictor_heads: int
  predictor_mlp_size: int
  predictor_lstm_size: int
  stochastic: bool = False
  prior_sigma: float = 0.1

  @nn.compact
  def __call__(self, carry: SAViCarry, features: jax.Array):
    """carry, features [B, M, C] -> (carry, (slots [B, N, D], kl [B, N]))."""
    initial_slots, lstm_state = carry
    if self.stochastic:
      initial_slots, kl = GaussianSlotSampler(
          self.prior_sigma, name='sampler')(initial_slots)
    else:
      kl = jnp.zeros(initial_slots.shape[:-1], initial_slots.dtype)
    slots = SlotAttention(self.num_iterations, self.slot_mlp_size,
                          name='corrector')(initial_slots, features)
    next_slots, lstm_state = SlotTransition(
        num_layers=self.predictor_layers, num_heads=self.predictor_heads,
        mlp_size=self.predictor_mlp_size, lstm_size=self.predictor_lstm_size,
        name='predictor')(slots, lstm_state)
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
    encoder_features, encoder_kernel_size, encoder_strides, encoder_size:
      the CNN encoder (D_enc = encoder_size).
    num_iterations, slot_mlp_size: the Slot Attention corrector.
    predictor_*: f_trans (see SlotTransition).
    decoder_*: the spatial-broadcast decoder.
    stochastic, prior_sigma: stochastic SAVi.
    initial_slots: 'learned' or 'gaussian' (see `initial_carry`).
  """

  resolution: tuple[int, int] = (64, 64)
  num_slots: int = 6
  slot_size: int = 128
  encoder_features: Sequence[int] = (64, 64, 64, 64)
  encoder_kernel_size: int = 5
  encoder_strides: Sequence[int] = (1, 1, 1, 1)
  encoder_size: int = 128
  num_iterations: int = 2
  slot_mlp_size: int = 256
  predictor_layers: int = 2
  predictor_heads: int = 4
  predictor_mlp_size: int = 512
  predictor_lstm_size: int = 0
  decoder_broadcast_resolution: tuple[int, int] = (8, 8)
  decoder_features: Sequence[int] = (64, 64, 64, 64)
  decoder_kernel_size: int = 5
  stochastic: bool = False
  prior_sigma: float = 0.1
  initial_slots: str = 'learned'

  def setup(self):
    self.encoder = CNNEncoder(
        features=self.encoder_features, kernel_size=self.encoder_kernel_size,
        strides=self.encoder_strides, output_size=self.encoder_size)
    if self.initial_slots == 'learned':
      self.slot_init = self.param(
          'initial_slots', nn.initializers.normal(stddev=1.0),
          (self.num_slots, self.slot_size))
    elif self.initial_slots == 'gaussian':
      self.slot_init_mean = self.param(
          'initial_slots_mean', nn.initializers.normal(stddev=1.0),
          (self.slot_size,))
      self.slot_init_log_sigma = self.param(
          'initial_slots_log_sigma', nn.initializers.zeros_init(),
          (self.slot_size,))
    else:
      raise ValueError("initial_slots must be 'learned' or 'gaussian', got "
                       f'{self.initial_slots!r}')
    self.frame_step = nn.scan(
        SAViStep, variable_broadcast='params',
        split_rngs={'params': False, 'sample': True},
        in_axes=1, out_axes=1)(
            num_iterations=self.num_iterations,
            slot_mlp_size=self.slot_mlp_size,
            predictor_layers=self.predictor_layers,
            predictor_heads=self.predictor_heads,
            predictor_mlp_size=self.predictor_mlp_size,
            predictor_lstm_size=self.predictor_lstm_size,
            stochastic=self.stochastic, prior_sigma=self.prior_sigma)
    self.decoder = SpatialBroadcastDecoder(
        output_resolution=tuple(self.resolution),
        broadcast_resolution=tuple(self.decoder_broadcast_resolution),
        features=self.decoder_features, kernel_size=self.decoder_kernel_size)

  def initial_carry(self, batch_size: int) -> SAViCarry:
    """The first frame's initial slots (+ zero LSTM state).

    'learned': one learned vector per slot (SlotFormer's SAVi), so slot n
    starts the same way in every video. 'gaussian': every slot drawn from one
    learned Gaussian (the original Slot Attention; draws from the 'sample'
    RNG), so slots are exchangeable and cannot specialise by position.
    """
    shape = (batch_size, self.num_slots, self.slot_size)
    if self.initial_slots == 'learned':
      slots = jnp.broadcast_to(self.slot_init, shape)
    else:
      noise = jax.random.normal(self.make_rng('sample'), shape)
      slots = self.slot_init_mean + jnp.exp(self.slot_init_log_sigma) * noise
    return slots, initial_lstm_state(slots, self.predictor_lstm_size)

  def encode(self, video: jax.Array, carry: SAViCarry | None = None):
    """video [B, T, H, W, 3] -> (slots [B,T,N,D], kl [B,T,N], carry).

    `carry` continues a video from an earlier chunk (None: start fresh).
    """
    batch, time = video.shape[:2]
    features = self.encoder(video.reshape(batch * time, *video.shape[2:]))
    features = features.reshape(batch, time, *features.shape[1:])
    if carry is None:
      carry = self.initial_carry(batch)
    carry, (slots, kl) = self.frame_step(carry, features)
    return slots, kl, carry

  def decode(self, slots: jax.Array) -> DecodedSlots:
    """slots [..., N, D] -> DecodedSlots with leading [...]."""
    return self.decoder(slots)

  def __call__(self, video: jax.Array, carry: SAViCarry | None = None,
               decode: bool = True) -> SAViOutput:
    slots, kl, carry = self.encode(video, carry)
    decoded = self.decode(slots) if decode else None
    return SAViOutput(slots=slots, kl=kl, decoded=decoded, carry=carry)
