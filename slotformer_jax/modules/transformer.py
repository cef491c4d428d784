"""Transformer encoder blocks (BERT-style, pre- or post-LayerNorm).

Shapes: tokens [batch, num_tokens, dim]. Used by the SAVi predictor, the
SlotFormer dynamics model, Aloe, the readouts and the Slot-LSTM baseline.

Attention: flax's explicit softmax(QK^T / sqrt(d))V on CPU (the form every
CPU result of this project was computed with), `jax.nn.dot_product_attention`
on GPU / TPU (its default implementation, XLA's, in jax 0.10: one
softmax(QK^T)V graph with float32 logits that the accelerator compilers fuse;
cuDNN's flash attention would need `implementation='cudnn'`, bfloat16 /
float16 only, and cannot be traced without the CUDA plugin, so it is not
used), chosen when the computation is lowered
(`slotformer_jax.modules.platform`). The explicit form runs on every
platform where the result needs it: when attention probabilities are
dropped out (training with dropout_rate > 0;
`jax.nn.dot_product_attention` has no probability dropout) and when the weights are recorded ('intermediates'
mutable, e.g. the attention figures). The parameters are
`nn.MultiHeadDotProductAttention`'s whatever the form.
"""

from __future__ import annotations

import functools
from typing import Any

import flax.linen as nn
import jax

from slotformer_jax.modules import platform


def _fused_attention(query: jax.Array, key: jax.Array, value: jax.Array,
                     mask: jax.Array | None) -> jax.Array:
  """query [B, Q, H, Dh], key / value [B, K, H, Dh], mask bool broadcastable
  to [B, H, Q, K] (True / non-zero = may attend) -> [B, Q, H, Dh]."""
  if mask is not None:
    # flax's masks (`nn.make_attention_mask`) are float 0 / 1; jax.nn wants
    # bool, and flax reads any non-zero as "may attend".
    mask = mask != 0
  return jax.nn.dot_product_attention(query, key, value, mask=mask)


def _explicit_attention(query: jax.Array, key: jax.Array, value: jax.Array,
                        mask: jax.Array | None) -> jax.Array:
  return nn.dot_product_attention(query, key, value, mask=mask)


def attention_by_platform(
    query: jax.Array, key: jax.Array, value: jax.Array,
    mask: jax.Array | None = None, *, kernels: str = platform.AUTO,
    dropout_rng: jax.Array | None = None, dropout_rate: float = 0.0,
    broadcast_dropout: bool = True, deterministic: bool = True,
    dtype: Any = None, precision: Any = None,
    module: nn.Module | None = None) -> jax.Array:
  """An `attention_fn` for `nn.MultiHeadDotProductAttention` (same
  arguments as `nn.dot_product_attention`): the explicit form where
  dropout or recorded weights need it, else the form of `kernels`.

  query [B, Q, H, Dh], key / value [B, K, H, Dh] -> [B, Q, H, Dh].
  """
  drops = dropout_rate > 0.0 and not deterministic
  # `module` is given whenever the caller asks to sow; the sow records only
  # where 'intermediates' is mutable, and only then are the weights needed.
  records = module is not None and module.is_mutable_collection(
      'intermediates')
  # A dtype / precision override is flax's to honour (none is set here).
  if drops or records or dtype is not None or precision is not None:
    return nn.dot_product_attention(
        query, key, value, mask=mask, dropout_rng=dropout_rng,
        dropout_rate=dropout_rate, broadcast_dropout=broadcast_dropout,
        deterministic=deterministic, dtype=dtype, precision=precision,
        module=module)
  return platform.by_platform(kernels, _explicit_attention, _fused_attention,
                              query, key, value, mask)


class TransformerBlock(nn.Module):
  """Self-attention + MLP, each wrapped in a residual connection.

  Attributes:
    num_heads: attention heads.
    mlp_size: hidden size of the feed-forward network (4 x D_e in SlotFormer).
    dropout_rate: on attention weights, inside the MLP and on both residual
      branches (PyTorch's `nn.TransformerEncoderLayer` convention).
    pre_norm: Pre-LN (LayerNorm before each sub-layer, SlotFormer's choice:
      easier to optimise) or Post-LN.
    layer_norm_epsilon: 1e-6 (flax) or 1e-5 (PyTorch, the official models).
    kernels: the attention's form, 'auto' (explicit on CPU, fused on GPU /
      TPU), 'cpu' or 'accelerator' (see the module docstring).
    qkv_size: width of the queries, keys and values (all heads together);
      None: the input's D (SAVi++'s predictor: 256 on 128-d slots).
  """

  num_heads: int
  mlp_size: int
  dropout_rate: float = 0.0
  pre_norm: bool = True
  layer_norm_epsilon: float = 1e-6
  kernels: str = platform.AUTO
  qkv_size: int | None = None

  @nn.compact
  def __call__(self, x: jax.Array, mask: jax.Array | None = None, *,
               deterministic: bool = True) -> jax.Array:
    """x [B, L, D]; mask: optional bool [B, 1, L, L], True = may attend."""
    dim = x.shape[-1]
    attention = nn.MultiHeadDotProductAttention(
        num_heads=self.num_heads, qkv_features=self.qkv_size,
        dropout_rate=self.dropout_rate,
        attention_fn=functools.partial(attention_by_platform,
                                       kernels=self.kernels),
        name='attention')
    mlp = nn.Sequential([
        nn.Dense(self.mlp_size), nn.relu,
        nn.Dropout(self.dropout_rate, deterministic=deterministic),
        nn.Dense(dim),
    ], name='mlp')
    dropout = nn.Dropout(self.dropout_rate, deterministic=deterministic)
    norm_attention = nn.LayerNorm(epsilon=self.layer_norm_epsilon,
                                  name='norm_attention')
    norm_mlp = nn.LayerNorm(epsilon=self.layer_norm_epsilon, name='norm_mlp')

    def attend(tokens):
      # Attention weights [B, heads, tokens, tokens] are sown into
      # 'intermediates' (recorded only when that collection is mutable;
      # then the attention is the explicit form on every platform).
      return attention(tokens, mask=mask, deterministic=deterministic,
                       sow_weights=True)

    if self.pre_norm:
      x = x + dropout(attend(norm_attention(x)))
      return x + dropout(mlp(norm_mlp(x)))
    x = norm_attention(x + dropout(attend(x)))
    return norm_mlp(x + dropout(mlp(x)))


class TransformerEncoder(nn.Module):
  """A stack of `TransformerBlock`s (no final LayerNorm, as PyTorch's)."""

  num_layers: int
  num_heads: int
  mlp_size: int
  dropout_rate: float = 0.0
  pre_norm: bool = True
  layer_norm_epsilon: float = 1e-6
  kernels: str = platform.AUTO
  qkv_size: int | None = None  # TransformerBlock's

  @nn.compact
  def __call__(self, x: jax.Array, mask: jax.Array | None = None, *,
               deterministic: bool = True) -> jax.Array:
    """x [B, L, D]; mask: optional bool [B, 1, L, L], True = may attend."""
    for i in range(self.num_layers):
      x = TransformerBlock(
          num_heads=self.num_heads, mlp_size=self.mlp_size,
          dropout_rate=self.dropout_rate, pre_norm=self.pre_norm,
          layer_norm_epsilon=self.layer_norm_epsilon, kernels=self.kernels,
          qkv_size=self.qkv_size, name=f'block_{i}')(x, mask, deterministic=deterministic)
    return x
