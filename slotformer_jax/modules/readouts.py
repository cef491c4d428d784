"""Readout heads that answer downstream questions from slot sequences.

* :class:`PhysionReadout`, object contact prediction (SlotFormer Section 4.3,
  after Relation Networks): per frame every pair of slots is concatenated and
  embedded by one linear layer, the pairs are max-pooled, a second linear layer
  gives a per-frame logit, and the video's logit is the max over frames
  ("do two objects touch at SOME time").
* :class:`PhyreReadout`, PHYRE task success (Section 4.4): the slots of a few
  selected frames are embedded, a temporal position code is added (the same
  for every slot of a frame), a [CLS] token is prepended, a 4-layer Pre-LN
  Transformer mixes them and an MLP on [CLS] gives the logit.

Both take slots [batch, time, num_slots, slot_size] and return logits [batch];
the loss (BCE) lives with the task code.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax.modules.slotformer import sinusoidal_encoding
from slotformer_jax.modules.transformer import TransformerEncoder

UNORDERED = 'unordered'
BOTH_ORDERS = 'both_orders'


def slot_pairs(num_slots: int, pairs: str) -> np.ndarray:
  """int32 [num_pairs, 2] slot indices of the pairs the readout looks at.

  'unordered' (the official readout): i < j, each pair once, concatenated as
  [slot_i, slot_j]. Because the linear layer sees the pair in index order,
  the result depends on the slot order. 'both_orders': (i, j) and (j, i) for
  every i != j; the max over pairs then makes the readout exactly invariant to
  permuting the slots (SAVi's slot order is arbitrary), at twice the pairs.
  """
  if pairs == UNORDERED:
    combos = list(itertools.combinations(range(num_slots), 2))
  elif pairs == BOTH_ORDERS:
    combos = list(itertools.permutations(range(num_slots), 2))
  else:
    raise ValueError(f"pairs must be '{UNORDERED}' or '{BOTH_ORDERS}', "
                     f'got {pairs!r}')
  if not combos:
    raise ValueError(f'need at least 2 slots for pairs, got {num_slots}')
  return np.asarray(combos, np.int32)


class PhysionReadout(nn.Module):
  """Relation readout: slots [B, T, N, D] -> contact logits [B].

  Attributes:
    features: width of the pair embedding (the slot size, officially).
    pairs: 'unordered' (official) or 'both_orders' (slot-permutation
      invariant); see :func:`slot_pairs`.
  """

  features: int = 192
  pairs: str = UNORDERED

  @nn.compact
  def __call__(self, slots: jax.Array) -> jax.Array:
    if slots.ndim != 4:
      raise ValueError(f'slots must be [batch, time, num_slots, slot_size], '
                       f'got {slots.shape}')
    index = slot_pairs(slots.shape[2], self.pairs)
    # [B, T, P, 2, D] -> [B, T, P, 2D]
    pairs = slots[:, :, index].reshape(*slots.shape[:2], len(index), -1)
    relation = nn.Dense(self.features, name='relation')(pairs).max(axis=2)
    per_frame = nn.Dense(1, name='logit')(relation)[..., 0]  # [B, T]
    return per_frame.max(axis=1)


class PhyreReadout(nn.Module):
  """Transformer readout: slots [B, T, N, D] -> success logits [B].

  Attributes:
    selected_steps: which frames of the slot sequence to look at (official:
      (0, 3) of the 1-fps rollout; frame 0 is the observed first frame).
    embed_dim: d_model (the slot size, officially).
    num_layers, num_heads, mlp_size: the Pre-LN Transformer (4, 8, 4 d_model).
    dropout_rate: PyTorch's default 0.1 in the official readout.
    layer_norm_epsilon: 1e-6 (flax) or 1e-5 (PyTorch's, the official
      readout's; configs/phyre.py:planning).
  """

  selected_steps: Sequence[int] = (0, 3)
  embed_dim: int = 128
  num_layers: int = 4
  num_heads: int = 8
  mlp_size: int = 512
  dropout_rate: float = 0.0
  layer_norm_epsilon: float = 1e-6

  @nn.compact
  def __call__(self, slots: jax.Array, *,
               deterministic: bool = True) -> jax.Array:
    if slots.ndim != 4:
      raise ValueError(f'slots must be [batch, time, num_slots, slot_size], '
                       f'got {slots.shape}')
    steps = tuple(self.selected_steps)
    if max(steps) >= slots.shape[1] or min(steps) < -slots.shape[1]:
      raise ValueError(f'selected_steps {steps} out of range for '
                       f'{slots.shape[1]} frames')
    selected = slots[:, jnp.asarray(steps)]  # [B, S, N, D]
    batch, num_steps, num_slots, _ = selected.shape
    tokens = nn.Dense(self.embed_dim, name='in_proj')(selected)
    # As the official sinusoidal code: positions count down to 0.
    temporal = sinusoidal_encoding(jnp.arange(num_steps - 1, -1, -1),
                                   self.embed_dim)
    tokens = (tokens + temporal[None, :, None]).reshape(
        batch, num_steps * num_slots, self.embed_dim)
    cls = self.param('cls', nn.initializers.zeros, (1, 1, self.embed_dim))
    tokens = jnp.concatenate(
        [jnp.broadcast_to(cls, (batch, 1, self.embed_dim)), tokens], axis=1)
    tokens = TransformerEncoder(
        num_layers=self.num_layers, num_heads=self.num_heads,
        mlp_size=self.mlp_size, dropout_rate=self.dropout_rate,
        pre_norm=True, layer_norm_epsilon=self.layer_norm_epsilon,
        name='transformer')(tokens, deterministic=deterministic)
    hidden = nn.relu(nn.Dense(self.embed_dim, name='cls_hidden')(tokens[:, 0]))
    return nn.Dense(1, name='cls_logit')(hidden)[:, 0]
