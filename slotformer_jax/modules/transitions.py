"""f_trans, SAVi's predictor: the next frame's initial slots from this frame's.

Two kinds, both called as `predictor(slots, state, deterministic=...)` ->
(next slots, new state), where `state` is a per-slot LSTM carry or ():
  SlotTransition         a Transformer over the frame's slots, optionally
                         followed by a per-slot LSTM ('transformer' /
                         'transformer_lstm');
  ResidualMLPTransition  LN -> MLP + residual, per slot ('residual_mlp', the
                         official CLEVRER StoSAVi).
`initial_state(slots)` gives the state of a video's first frame.

Shapes: slots [batch, num_slots, slot_size]; LSTM state (c, h) each
[batch, num_slots, lstm_size].
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotformer_jax.modules.transformer import TransformerEncoder

TRANSFORMER = 'transformer'
TRANSFORMER_LSTM = 'transformer_lstm'
RESIDUAL_MLP = 'residual_mlp'
PREDICTORS = (TRANSFORMER, TRANSFORMER_LSTM, RESIDUAL_MLP)

# A per-slot LSTM carry (c, h), or () for a predictor without one.
TransitionState = Any


def initial_lstm_state(slots: jax.Array, lstm_size: int) -> TransitionState:
  """Zero per-slot LSTM carry for slots [B, N, D]: (c, h) [B, N, lstm_size]."""
  if not lstm_size:
    return ()
  zeros = jnp.zeros((*slots.shape[:-1], lstm_size), slots.dtype)
  return (zeros, zeros)


class SlotTransition(nn.Module):
  """f_trans: a Transformer over one frame's slots, optionally + per-slot LSTM.

  The LSTM variant is the Transformer-LSTM module of PARTS (used by the
  official OBJ3D / PHYRE SAVi, by STEVE and by the Slot-LSTM baseline): the
  Transformer's output feeds an LSTM cell per slot whose hidden state is
  projected back to D, with no residual.

  Attributes:
    num_layers, num_heads, mlp_size, pre_norm, dropout_rate,
      layer_norm_epsilon, qkv_size: the Transformer (qkv_size None: D).
    lstm_size: hidden size of the per-slot LSTM; 0 disables it.
  """

  num_layers: int = 2
  num_heads: int = 4
  mlp_size: int = 512
  pre_norm: bool = True
  lstm_size: int = 0
  dropout_rate: float = 0.0
  layer_norm_epsilon: float = 1e-6
  qkv_size: int | None = None

  def initial_state(self, slots: jax.Array) -> TransitionState:
    """The first frame's state: zero LSTM carry, or () without the LSTM."""
    return initial_lstm_state(slots, self.lstm_size)

  @nn.compact
  def __call__(self, slots: jax.Array, lstm_state: TransitionState = (), *,
               deterministic: bool = True):
    """slots [B, N, D] -> (next slots [B, N, D], new LSTM state)."""
    x = TransformerEncoder(
        num_layers=self.num_layers, num_heads=self.num_heads,
        mlp_size=self.mlp_size, pre_norm=self.pre_norm,
        dropout_rate=self.dropout_rate,
        layer_norm_epsilon=self.layer_norm_epsilon, qkv_size=self.qkv_size,
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

  def initial_state(self, slots: jax.Array) -> TransitionState:
    """No recurrent state: ()."""
    del slots
    return ()

  @nn.compact
  def __call__(self, slots: jax.Array, lstm_state: TransitionState = (), *,
               deterministic: bool = True):
    """slots [B, N, D] -> (next slots [B, N, D], `lstm_state` unchanged)."""
    del deterministic  # no dropout here
    normed = nn.LayerNorm(epsilon=self.layer_norm_epsilon, name='norm')(slots)
    hidden = nn.relu(nn.Dense(self.mlp_size, name='hidden')(normed))
    out = nn.Dense(slots.shape[-1], name='out')(hidden)
    return out + (normed if self.pre_norm else slots), lstm_state


def build_predictor(kind: str, *, num_layers: int, num_heads: int,
                    mlp_size: int, lstm_size: int, pre_norm: bool,
                    dropout_rate: float, layer_norm_epsilon: float,
                    qkv_size: int | None = None
                    ) -> SlotTransition | ResidualMLPTransition:
  """The f_trans module of `kind` (one of PREDICTORS); `residual_mlp` uses
  only mlp_size, pre_norm and layer_norm_epsilon; qkv_size None: the slot
  size."""
  if kind == RESIDUAL_MLP:
    return ResidualMLPTransition(mlp_size=mlp_size, pre_norm=pre_norm,
                                 layer_norm_epsilon=layer_norm_epsilon)
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
      layer_norm_epsilon=layer_norm_epsilon, qkv_size=qkv_size)
