"""Slot Attention (Locatello et al., 2020) as used by SAVi's corrector.

Shapes: slots [batch, num_slots, slot_size], inputs [batch, num_inputs, input_size].
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


def inverted_attention_weights(
    queries: jax.Array, keys: jax.Array, epsilon: float
) -> jax.Array:
  """Softmax over the *slot* axis, then a weighted mean over the inputs.

  Args:
    queries: [batch, num_slots, dim].
    keys: [batch, num_inputs, dim].
    epsilon: added before the renormalisation over inputs, so a slot that wins
      no input still gets a well-defined (uniform-ish) mean.

  Returns:
    (attention [batch, num_slots, num_inputs] summing to 1 over inputs,
     competition [batch, num_slots, num_inputs] summing to 1 over slots).
  """
  scale = queries.shape[-1] ** -0.5
  logits = jnp.einsum('bnd,bmd->bnm', queries, keys) * scale
  # Slots compete for every input: normalise over the slot axis.
  competition = jax.nn.softmax(logits, axis=1)
  weights = competition + epsilon
  weights = weights / jnp.sum(weights, axis=-1, keepdims=True)
  return weights, competition


class SlotAttention(nn.Module):
  """Iterative slot update by inverted dot-product attention + GRU + MLP.

  Attributes:
    num_iterations: attention rounds per call (2 in SlotFormer's SAVi).
    mlp_size: hidden size of the residual MLP after the GRU; None: no MLP
      (SAVi's MOVi configs set none; SlotFormer's SAVi has one).
    qkv_size: width of the queries, keys and values, and so of the updates
      the GRU reads; None: the slot size (SAVi++: 256 on 128-d slots).
    epsilon: see `inverted_attention_weights`.
    layer_norm_epsilon: 1e-6 (flax) or 1e-5 (PyTorch, the official models).
    return_attention: also return the last iteration's slot competition
      [B, N, M] (softmax over slots): STEVE's per-slot masks.
  """

  num_iterations: int = 2
  mlp_size: int | None = 256
  qkv_size: int | None = None
  epsilon: float = 1e-6
  layer_norm_epsilon: float = 1e-6
  return_attention: bool = False

  @nn.compact
  def __call__(self, slots: jax.Array, inputs: jax.Array):
    """slots [B, N, D], inputs [B, M, C] -> updated slots [B, N, D]
    (and the attention [B, N, M] when `return_attention`)."""
    slot_size = slots.shape[-1]
    qkv_size = self.qkv_size or slot_size
    layer_norm = lambda **kw: nn.LayerNorm(epsilon=self.layer_norm_epsilon,
                                           **kw)
    # Per-input LayerNorm and projections on a [B*M, C] view (the same
    # math; faster gradients on XLA:CPU than the 3-D view, as in
    # `CNNEncoder`).
    batch, num_inputs, _ = inputs.shape
    flat = layer_norm(name='norm_inputs')(inputs.reshape(batch * num_inputs, -1))
    keys = nn.Dense(qkv_size, use_bias=False, name='key')(flat).reshape(
        batch, num_inputs, qkv_size)
    values = nn.Dense(qkv_size, use_bias=False, name='value')(flat).reshape(
        batch, num_inputs, qkv_size)

    norm_slots = layer_norm(name='norm_slots')
    to_query = nn.Dense(qkv_size, use_bias=False, name='query')
    gru = nn.GRUCell(slot_size, name='gru')
    mlp = None if self.mlp_size is None else nn.Sequential([
        layer_norm(),
        nn.Dense(self.mlp_size),
        nn.relu,
        nn.Dense(slot_size),
    ], name='mlp')

    for _ in range(self.num_iterations):
      queries = to_query(norm_slots(slots))
      weights, competition = inverted_attention_weights(
          queries, keys, self.epsilon)
      # Kept for visualisation: the per-input slot assignment of the last
      # iteration, [B, N, M].
      self.sow('intermediates', 'attention', competition)
      updates = jnp.einsum('bnm,bmd->bnd', weights, values)
      slots, _ = gru(slots, updates)
      if mlp is not None:
        slots = slots + mlp(slots)
    if self.return_attention:
      return slots, competition
    return slots
