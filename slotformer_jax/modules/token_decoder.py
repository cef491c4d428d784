"""STEVE's decoder: an autoregressive Transformer over dVAE tokens given slots.

The image of a frame is the sequence of its h*w dVAE tokens in raster order.
Token i is predicted from a BOS token, tokens < i and the frame's slots:
embedding + learned position -> `num_layers` Pre-LN blocks of (causal
self-attention, cross-attention to the projected slots, FFN) -> LayerNorm ->
linear head over the vocabulary.

Two ways to run it:
* `__call__`: teacher forcing, all positions at once (training; the logits of
  a full recomputation).
* `init_cache` + `decode_step`: one position at a time with a key/value cache
  of the self-attention and the slots' keys/values computed once
  (generation, see `slotformer_jax.steve_inference`).

Deviation from the official decoder: attention probabilities are not dropped
out. Attention runs through `jax.nn.dot_product_attention`, which has no
probability dropout; dropout stays on the position-embedded inputs, on every
attention output and in the FFN, as there. (Its default implementation is
XLA's on every platform in jax 0.10; cuDNN's flash attention would need
`implementation='cudnn'`, bfloat16 / float16 only, not used here.)

Shapes: slots [batch, num_slots, slot_size]; tokens int [batch, num_tokens];
logits [batch, num_tokens, vocab_size].
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

# PyTorch's default nn.Linear init (kaiming_uniform with a=sqrt(5)).
_TORCH_LINEAR = nn.initializers.variance_scaling(1 / 3, 'fan_in', 'uniform')
_KAIMING = nn.initializers.he_uniform()


def _xavier(gain: float = 1.0):
  return nn.initializers.variance_scaling(gain * gain, 'fan_avg', 'uniform')


# Per layer: (keys, values) of the self-attention cache [B, L, H, Dh] and of
# the slots [B, N, H, Dh].
DecoderCache = dict[str, Any]


class Attention(nn.Module):
  """Multi-head attention with bias-free q/k/v/o projections.

  Attributes:
    dim: model size (= heads * head size).
    num_heads: heads.
    output_gain: xavier gain of the output projection ((3 L)^-1/2 in STEVE,
      which keeps the residual stream's scale independent of depth).
    dropout_rate: on the output.
  """

  dim: int
  num_heads: int
  output_gain: float = 1.0
  dropout_rate: float = 0.0

  def setup(self):
    head_size = self.dim // self.num_heads
    if head_size * self.num_heads != self.dim:
      raise ValueError(f'dim {self.dim} is not divisible by {self.num_heads} '
                       'heads')
    shape = (self.num_heads, head_size)
    self.query = nn.DenseGeneral(shape, use_bias=False, kernel_init=_xavier())
    self.key = nn.DenseGeneral(shape, use_bias=False, kernel_init=_xavier())
    self.value = nn.DenseGeneral(shape, use_bias=False, kernel_init=_xavier())
    self.out = nn.DenseGeneral(self.dim, axis=(-2, -1), use_bias=False,
                               kernel_init=_xavier(self.output_gain))
    self.dropout = nn.Dropout(self.dropout_rate)

  def keys_values(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """x [B, S, dim] -> keys, values [B, S, H, Dh]."""
    return self.key(x), self.value(x)

  def output(self, attended: jax.Array, deterministic: bool) -> jax.Array:
    """[B, T, H, Dh] -> [B, T, dim]."""
    return self.dropout(self.out(attended), deterministic=deterministic)

  def __call__(self, x: jax.Array, context: jax.Array, *, causal: bool,
               deterministic: bool) -> jax.Array:
    """x [B, T, dim] attends to context [B, S, dim] -> [B, T, dim]."""
    keys, values = self.keys_values(context)
    attended = jax.nn.dot_product_attention(
        self.query(x), keys, values, is_causal=causal)
    return self.output(attended, deterministic)


class DecoderBlock(nn.Module):
  """Pre-LN: causal self-attention, cross-attention to slots, FFN.

  `is_first`: the official first block (SLATE's) replaces its input by the
  LayerNorm of it before the self-attention residual; kept so converted
  weights compute the same function.
  """

  dim: int
  num_heads: int
  output_gain: float
  dropout_rate: float = 0.0
  is_first: bool = False

  def setup(self):
    attention = lambda: Attention(self.dim, self.num_heads, self.output_gain,
                                  self.dropout_rate)
    self.norm_self = nn.LayerNorm(epsilon=1e-5)
    self.self_attention = attention()
    self.norm_cross = nn.LayerNorm(epsilon=1e-5)
    self.cross_attention = attention()
    self.norm_ffn = nn.LayerNorm(epsilon=1e-5)
    self.ffn_hidden = nn.Dense(4 * self.dim, kernel_init=_KAIMING,
                               bias_init=nn.initializers.zeros)
    self.ffn_out = nn.Dense(self.dim, kernel_init=_xavier(self.output_gain),
                            bias_init=nn.initializers.zeros)
    self.ffn_dropout = nn.Dropout(self.dropout_rate)

  def _ffn(self, x: jax.Array, deterministic: bool) -> jax.Array:
    hidden = nn.relu(self.ffn_hidden(self.norm_ffn(x)))
    return x + self.ffn_dropout(self.ffn_out(hidden),
                                deterministic=deterministic)

  def __call__(self, x: jax.Array, slots: jax.Array, *,
               deterministic: bool) -> jax.Array:
    """x [B, L, dim], projected slots [B, N, dim] -> [B, L, dim]."""
    normed = self.norm_self(x)
    if self.is_first:
      x = normed
    x = x + self.self_attention(normed, normed, causal=True,
                                deterministic=deterministic)
    normed = self.norm_cross(x)
    x = x + self.cross_attention(normed, slots, causal=False,
                                 deterministic=deterministic)
    return self._ffn(x, deterministic)

  def slot_keys_values(self, slots: jax.Array):
    """projected slots [B, N, dim] -> keys, values [B, N, H, Dh]."""
    return self.cross_attention.keys_values(slots)

  def step(self, x: jax.Array, position: jax.Array, cache: tuple,
           slot_keys_values: tuple, presence: jax.Array | None = None
           ) -> tuple[jax.Array, tuple, jax.Array]:
    """One position: x [B, 1, dim] -> (x, updated cache, cross weights).

    cache: (keys, values) [B, L, H, Dh] of positions < `position` (later
    entries are ignored). presence: optional bool [B, N]; absent slots are
    dropped from the softmax over slots (weight exactly 0). Returns the
    cross-attention weights over the slots [B, H, N] (softmax over slots)
    for the attention masks.
    """
    normed = self.norm_self(x)
    if self.is_first:
      x = normed
    keys, values = cache
    new_keys, new_values = self.self_attention.keys_values(normed)
    start = (0, position, 0, 0)
    keys = jax.lax.dynamic_update_slice(keys, new_keys, start)
    values = jax.lax.dynamic_update_slice(values, new_values, start)
    visible = (jnp.arange(keys.shape[1]) <= position)[None, None, None, :]
    attended = jax.nn.dot_product_attention(
        self.self_attention.query(normed), keys, values, mask=visible)
    x = x + self.self_attention.output(attended, True)

    # Cross-attention written out: only N slots, and the weights are the
    # per-token slot assignment the attention masks are made of.
    query = self.cross_attention.query(self.norm_cross(x))  # [B, 1, H, Dh]
    slot_keys, slot_values = slot_keys_values
    logits = jnp.einsum('bqhd,bnhd->bhqn', query, slot_keys)
    if presence is not None:
      logits = jnp.where(presence[:, None, None, :], logits,
                         jnp.finfo(logits.dtype).min)
    weights = jax.nn.softmax(logits * query.shape[-1] ** -0.5, axis=-1)
    attended = jnp.einsum('bhqn,bnhd->bqhd', weights, slot_values)
    x = x + self.cross_attention.output(attended, True)
    return self._ffn(x, True), (keys, values), weights[:, :, 0]


class TokenDecoder(nn.Module):
  """STEVE's autoregressive token decoder (see the module docstring).

  Attributes:
    vocab_size: dVAE codes; id `vocab_size` is the BOS token.
    num_tokens: L = h * w tokens per frame.
    dim: model size (the slot size, 192, in the official Physion STEVE).
    num_layers, num_heads: blocks and heads (4 and 4).
    dropout_rate: 0.1 officially (see the module docstring for where).
  """

  vocab_size: int = 4096
  num_tokens: int = 1024
  dim: int = 192
  num_layers: int = 4
  num_heads: int = 4
  dropout_rate: float = 0.1

  def setup(self):
    gain = (3 * self.num_layers) ** -0.5
    self.slot_projection = nn.Dense(self.dim, kernel_init=_TORCH_LINEAR)
    self.token_embedding = nn.Embed(
        self.vocab_size + 1, self.dim,
        embedding_init=nn.initializers.normal(stddev=1.0))
    self.position_embedding = self.param(
        'position_embedding', nn.initializers.truncated_normal(stddev=1.0),
        (self.num_tokens, self.dim))
    self.input_dropout = nn.Dropout(self.dropout_rate)
    self.blocks = [
        DecoderBlock(self.dim, self.num_heads, gain, self.dropout_rate,
                     is_first=i == 0) for i in range(self.num_layers)]
    self.final_norm = nn.LayerNorm(epsilon=1e-5)
    self.head = nn.Dense(self.vocab_size, use_bias=False,
                         kernel_init=_TORCH_LINEAR)

  @property
  def bos(self) -> int:
    return self.vocab_size

  def __call__(self, slots: jax.Array, tokens: jax.Array, *,
               deterministic: bool = True) -> jax.Array:
    """slots [B, N, D], target tokens int [B, L'] (L' <= L) -> logits
    [B, L', vocab]: position i is predicted from BOS and tokens[:, :i]."""
    length = tokens.shape[1]
    inputs = jnp.concatenate(
        [jnp.full_like(tokens[:, :1], self.bos), tokens[:, :-1]], axis=1)
    x = self.token_embedding(inputs) + self.position_embedding[:length]
    x = self.input_dropout(x, deterministic=deterministic)
    slots = self.slot_projection(slots)
    for block in self.blocks:
      x = block(x, slots, deterministic=deterministic)
    return self.head(self.final_norm(x))

  def init_cache(self, slots: jax.Array,
                 presence: jax.Array | None = None) -> DecoderCache:
    """Slots [B, N, D] -> an empty self-attention cache and the slots'
    per-layer keys/values (and `presence`, optional bool [B, N]: which
    slots the cross-attention may attend to)."""
    slots = self.slot_projection(slots)
    batch = slots.shape[0]
    head_size = self.dim // self.num_heads
    empty = jnp.zeros((batch, self.num_tokens, self.num_heads, head_size),
                      slots.dtype)
    cache = {
        'self': [(empty, empty) for _ in self.blocks],
        'slots': [block.slot_keys_values(slots) for block in self.blocks],
    }
    if presence is not None:
      cache['presence'] = presence.astype(bool)
    return cache

  def decode_step(self, token: jax.Array, position: jax.Array,
                  cache: DecoderCache
                  ) -> tuple[jax.Array, jax.Array, DecoderCache]:
    """The input token int [B] at `position` (BOS at 0, else the token of
    position - 1) -> (logits [B, vocab] of `position`, last layer's
    cross-attention over slots [B, N] (mean over heads), updated cache)."""
    x = self.token_embedding(token)[:, None] + jax.lax.dynamic_slice_in_dim(
        self.position_embedding, position, 1)[None]
    new_self = []
    for block, layer_cache, slot_kv in zip(self.blocks, cache['self'],
                                           cache['slots']):
      x, layer_cache, weights = block.step(x, position, layer_cache, slot_kv,
                                           cache.get('presence'))
      new_self.append(layer_cache)
    logits = self.head(self.final_norm(x))[:, 0]
    return logits, weights.mean(axis=1), {**cache, 'self': new_self}
