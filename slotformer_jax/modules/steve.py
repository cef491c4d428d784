"""STEVE (Singh et al., 2022) as SlotFormer uses it for Physion.

Slot encoder: SAVi's without its pixel decoder. Per frame t: CNN features
h_t; slots S_t = SlotAttention(S~_t, h_t), which also yields the last
iteration's attention (softmax over slots) as per-slot masks at the feature
resolution; S~_{t+1} = f_trans(S_t) (Transformer + per-slot LSTM);
S~_1 are learned vectors. Decoder: an autoregressive Transformer over the
frozen dVAE's tokens of the frame, conditioned on the frame's slots
(`TokenDecoder`). SlotFormer's two-stage variant: the dVAE is trained first
and frozen, so STEVE only learns to predict its tokens.

Shapes: video [batch, time, height, width, 3] in [-1, 1];
slots [batch, time, num_slots, slot_size];
masks [batch, time, num_slots, feature_height, feature_width];
tokens int [batch, time, num_tokens].
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.savi import SAViCarry
from slotformer_jax.modules.savi import SlotTransition
from slotformer_jax.modules.savi import initial_lstm_state
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.token_decoder import TokenDecoder


class STEVEStep(nn.Module):
  """One frame: correct the initial slots (keeping the masks), predict."""

  num_iterations: int
  slot_mlp_size: int
  predictor_layers: int
  predictor_heads: int
  predictor_mlp_size: int
  predictor_lstm_size: int
  layer_norm_epsilon: float = 1e-6

  @nn.compact
  def __call__(self, carry: SAViCarry, features: jax.Array):
    """carry, features [B, M, C] -> (carry, (slots [B, N, D], masks [B, N, M]))."""
    initial_slots, lstm_state = carry
    slots, masks = SlotAttention(
        self.num_iterations, self.slot_mlp_size, return_attention=True,
        layer_norm_epsilon=self.layer_norm_epsilon,
        name='corrector')(initial_slots, features)
    next_slots, lstm_state = SlotTransition(
        num_layers=self.predictor_layers, num_heads=self.predictor_heads,
        mlp_size=self.predictor_mlp_size, lstm_size=self.predictor_lstm_size,
        layer_norm_epsilon=self.layer_norm_epsilon,
        name='predictor')(slots, lstm_state)
    return (next_slots, lstm_state), (slots, masks)


class STEVE(nn.Module):
  """STEVE's slot encoder + token decoder. See the module docstring.

  Attributes:
    resolution: (H, W) of the frames.
    num_slots, slot_size: N and D_slot (6 and 192 for Physion).
    encoder_*: SAVi's CNN encoder (first stride 2 at 128x128);
      `encoder_padding` 'same' or 'pytorch' (K // 2 on every side, the
      official Conv2d; the two differ at stride 2 only).
    num_iterations, slot_mlp_size: Slot Attention.
    predictor_*: f_trans; `predictor_lstm_size` the per-slot LSTM (384).
    vocab_size: the dVAE's codes.
    token_downsampling: frame pixels per token side (4: 128 -> 32x32).
    decoder_*: the token decoder (its size is `slot_size`, as officially).
    layer_norm_epsilon: of the encoder, Slot Attention and the predictor
      (1e-6 flax's, 1e-5 PyTorch's, the official model's); the token
      decoder always uses 1e-5.
  """

  resolution: tuple[int, int] = (128, 128)
  num_slots: int = 6
  slot_size: int = 192
  encoder_features: Sequence[int] = (64, 64, 64, 64)
  encoder_kernel_size: int = 5
  encoder_strides: Sequence[int] = (2, 1, 1, 1)
  encoder_size: int = 192
  encoder_padding: str = 'same'
  num_iterations: int = 2
  slot_mlp_size: int = 384
  predictor_layers: int = 2
  predictor_heads: int = 4
  predictor_mlp_size: int = 768
  predictor_lstm_size: int = 384
  vocab_size: int = 4096
  token_downsampling: int = 4
  decoder_layers: int = 4
  decoder_heads: int = 4
  decoder_dropout: float = 0.1
  layer_norm_epsilon: float = 1e-6

  @property
  def token_grid(self) -> tuple[int, int]:
    """(h, w) of a frame's token map."""
    height, width = self.resolution
    return (height // self.token_downsampling,
            width // self.token_downsampling)

  @property
  def feature_grid(self) -> tuple[int, int]:
    """(h', w') of the encoder's feature map, the resolution of the masks."""
    height, width = self.resolution
    for stride in self.encoder_strides:
      height, width = -(-height // stride), -(-width // stride)
    return height, width

  def setup(self):
    self.encoder = CNNEncoder(
        features=self.encoder_features, kernel_size=self.encoder_kernel_size,
        strides=self.encoder_strides, output_size=self.encoder_size,
        padding=self.encoder_padding,
        layer_norm_epsilon=self.layer_norm_epsilon)
    self.slot_init = self.param(
        'initial_slots', nn.initializers.normal(stddev=1.0),
        (self.num_slots, self.slot_size))
    self.frame_step = nn.scan(
        STEVEStep, variable_broadcast='params', split_rngs={'params': False},
        in_axes=1, out_axes=1)(
            num_iterations=self.num_iterations,
            slot_mlp_size=self.slot_mlp_size,
            predictor_layers=self.predictor_layers,
            predictor_heads=self.predictor_heads,
            predictor_mlp_size=self.predictor_mlp_size,
            predictor_lstm_size=self.predictor_lstm_size,
            layer_norm_epsilon=self.layer_norm_epsilon)
    height, width = self.token_grid
    self.decoder = TokenDecoder(
        vocab_size=self.vocab_size, num_tokens=height * width,
        dim=self.slot_size, num_layers=self.decoder_layers,
        num_heads=self.decoder_heads, dropout_rate=self.decoder_dropout)

  def initial_carry(self, batch_size: int) -> SAViCarry:
    """The learned first-frame slots (the same in every video) + zero LSTM."""
    slots = jnp.broadcast_to(self.slot_init,
                             (batch_size, self.num_slots, self.slot_size))
    return slots, initial_lstm_state(slots, self.predictor_lstm_size)

  def encode(self, video: jax.Array, carry: SAViCarry | None = None):
    """video [B, T, H, W, 3] -> (slots [B, T, N, D], masks [B, T, N, h', w'],
    carry). `carry` continues a video from an earlier chunk (None: fresh)."""
    batch, time = video.shape[:2]
    features = self.encoder(video.reshape(batch * time, *video.shape[2:]))
    features = features.reshape(batch, time, *features.shape[1:])
    if carry is None:
      carry = self.initial_carry(batch)
    carry, (slots, masks) = self.frame_step(carry, features)
    masks = masks.reshape(*masks.shape[:3], *self.feature_grid)
    return slots, masks, carry

  def token_logits(self, slots: jax.Array, tokens: jax.Array, *,
                   deterministic: bool = True) -> jax.Array:
    """slots [..., N, D], tokens int [..., L] -> logits [..., L, vocab]
    (teacher forcing: position i sees tokens < i)."""
    lead = slots.shape[:-2]
    logits = self.decoder(slots.reshape(-1, *slots.shape[-2:]),
                          tokens.reshape(-1, tokens.shape[-1]),
                          deterministic=deterministic)
    return logits.reshape(*lead, *logits.shape[1:])

  def __call__(self, video: jax.Array, tokens: jax.Array, *,
               deterministic: bool = True):
    """video [B, T, H, W, 3], tokens int [B, T, L] -> (logits [B, T, L, V],
    slots [B, T, N, D], masks [B, T, N, h', w'])."""
    slots, masks, _ = self.encode(video)
    logits = self.token_logits(slots, tokens, deterministic=deterministic)
    return logits, slots, masks
