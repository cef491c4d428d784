"""Slot-LSTM: the paper's appendix baseline (PARTS' Transformer-LSTM).

Each frame's slots are projected to D_e, mixed by the same kind of Pre-LN
Transformer as SlotFormer's but over the N slots of *one* frame only
(spatial interaction, no temporal context), then a per-slot LSTM carries the
temporal dynamics and a linear layer maps its output to the next frame's
slots. The burn-in frames are consumed one by one to warm the LSTM up; the
rollout feeds each prediction back as the next input.

It has SlotFormer's call signature, so it trains with the same losses and
evaluates with the same code.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotformer_jax.modules.time_loop import scan_with_shared_params
from slotformer_jax.modules.transformer import TransformerEncoder

LSTMState = tuple[jax.Array, jax.Array]


class SlotLSTMStep(nn.Module):
  """One frame: (LSTM state, slots [B, N, D]) -> (state, next slots)."""

  embed_dim: int = 128
  num_layers: int = 4
  num_heads: int = 8
  mlp_size: int = 512
  dropout_rate: float = 0.0
  residual: bool = False

  @nn.compact
  def __call__(self, state: LSTMState, slots: jax.Array, *,
               deterministic: bool = True) -> tuple[LSTMState, jax.Array]:
    batch, num_slots, slot_size = slots.shape
    tokens = nn.Dense(self.embed_dim, name='in_proj')(slots)
    tokens = TransformerEncoder(
        num_layers=self.num_layers, num_heads=self.num_heads,
        mlp_size=self.mlp_size, dropout_rate=self.dropout_rate,
        pre_norm=True, name='transformer')(tokens, deterministic=deterministic)
    # Slots are independent samples of the LSTM: fold them into the batch.
    state, hidden = nn.OptimizedLSTMCell(self.embed_dim, name='lstm')(
        state, tokens.reshape(batch * num_slots, self.embed_dim))
    hidden = hidden.reshape(batch, num_slots, self.embed_dim)
    if self.residual:
      # As SlotFormer's residual variant: a zero-initialised refinement of
      # the input slots.
      refinement = nn.Dense(slot_size, kernel_init=nn.initializers.zeros,
                            name='out_proj')(hidden)
      return state, slots + refinement
    return state, nn.Dense(slot_size, name='out_proj')(hidden)


class SlotLSTM(nn.Module):
  """Transformer-LSTM dynamics over slots, with SlotFormer's interface.

  Attributes:
    burn_in: number of observed frames (only checked; the LSTM itself has
      no window).
    embed_dim, num_layers, num_heads, mlp_size, dropout_rate: the
      per-frame Transformer; the LSTM's hidden size is embed_dim.
    residual: add the input slots to the prediction.
  """

  burn_in: int = 6
  embed_dim: int = 128
  num_layers: int = 4
  num_heads: int = 8
  mlp_size: int = 512
  dropout_rate: float = 0.0
  residual: bool = False

  def setup(self):
    self.step = SlotLSTMStep(
        embed_dim=self.embed_dim, num_layers=self.num_layers,
        num_heads=self.num_heads, mlp_size=self.mlp_size,
        dropout_rate=self.dropout_rate, residual=self.residual)

  def __call__(self, burn_in_slots: jax.Array, num_steps: int,
               teacher_slots: jax.Array | None = None, *,
               deterministic: bool = True) -> jax.Array:
    """[B, burn_in, N, D] -> [B, num_steps, N, D] predicted slots.

    teacher_slots: optional [B, num_steps, N, D]; when given the ground truth
    rather than the prediction is fed back (teacher forcing).
    """
    if burn_in_slots.ndim != 4 or burn_in_slots.shape[1] != self.burn_in:
      raise ValueError(
          f'SlotLSTM expects slots [batch, {self.burn_in}, num_slots, '
          f'slot_size], got {burn_in_slots.shape}')
    batch, _, num_slots, _ = burn_in_slots.shape
    zeros = jnp.zeros((batch * num_slots, self.embed_dim),
                      burn_in_slots.dtype)
    state = (zeros, zeros)

    def observe(step, state, slots):
      state, prediction = step(state, slots, deterministic=deterministic)
      return state, prediction

    scan_observe = scan_with_shared_params(
        observe, self,
        split_rngs={'params': False, 'dropout': True},
        in_axes=1, out_axes=1, length=self.burn_in)
    state, observed_predictions = scan_observe(self.step, state,
                                               burn_in_slots)
    first = observed_predictions[:, -1]
    if num_steps == 1:
      return first[:, None]

    def imagine(step, carry, teacher):
      state, previous = carry
      fed = previous if teacher is None else teacher
      state, prediction = step(state, fed, deterministic=deterministic)
      return (state, prediction), prediction

    scan_imagine = scan_with_shared_params(
        imagine, self,
        split_rngs={'params': False, 'dropout': True},
        in_axes=1, out_axes=1, length=num_steps - 1)
    teacher = None if teacher_slots is None else teacher_slots[:, :-1]
    _, rest = scan_imagine(self.step, (state, first), teacher)
    return jnp.concatenate([first[:, None], rest], axis=1)
