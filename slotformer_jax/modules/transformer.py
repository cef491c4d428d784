"""Transformer encoder blocks (BERT-style, pre- or post-LayerNorm).

Shapes: tokens [batch, num_tokens, dim]. Used by the SAVi predictor, the
SlotFormer dynamics model and the Slot-LSTM baseline.
"""

from __future__ import annotations

import flax.linen as nn
import jax


class TransformerBlock(nn.Module):
  """Self-attention + MLP, each wrapped in a residual connection.

  Attributes:
    num_heads: attention heads.
    mlp_size: hidden size of the feed-forward network (4 x D_e in SlotFormer).
    dropout_rate: on attention weights, inside the MLP and on both residual
      branches (PyTorch's `nn.TransformerEncoderLayer` convention).
    pre_norm: Pre-LN (LayerNorm before each sub-layer, SlotFormer's choice:
      easier to optimise) or Post-LN.
  """

  num_heads: int
  mlp_size: int
  dropout_rate: float = 0.0
  pre_norm: bool = True

  @nn.compact
  def __call__(self, x: jax.Array, *, deterministic: bool = True,
               mask: jax.Array | None = None) -> jax.Array:
    """``mask``: optional bool [batch, 1, tokens, tokens], True = attend."""
    dim = x.shape[-1]
    attention = nn.MultiHeadDotProductAttention(
        num_heads=self.num_heads, dropout_rate=self.dropout_rate,
        name='attention')
    mlp = nn.Sequential([
        nn.Dense(self.mlp_size), nn.relu,
        nn.Dropout(self.dropout_rate, deterministic=deterministic),
        nn.Dense(dim),
    ], name='mlp')
    dropout = nn.Dropout(self.dropout_rate, deterministic=deterministic)
    norm_attention = nn.LayerNorm(name='norm_attention')
    norm_mlp = nn.LayerNorm(name='norm_mlp')

    def attend(tokens):
      # Attention weights [B, heads, tokens, tokens] are sown into
      # 'intermediates' (recorded only when that collection is mutable).
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

  @nn.compact
  def __call__(self, x: jax.Array, *, deterministic: bool = True,
               mask: jax.Array | None = None) -> jax.Array:
    for i in range(self.num_layers):
      x = TransformerBlock(
          num_heads=self.num_heads, mlp_size=self.mlp_size,
          dropout_rate=self.dropout_rate, pre_norm=self.pre_norm,
          name=f'block_{i}')(x, deterministic=deterministic, mask=mask)
    return x
