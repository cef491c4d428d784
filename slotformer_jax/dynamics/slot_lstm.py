"""The Slot-LSTM baseline (the paper's appendix): the same per-frame
Transformer followed by a per-slot LSTM, trained with SlotFormer's data,
losses and schedule (`config.slot_lstm` holds `train` and overrides)."""

from __future__ import annotations

import flax.linen as nn
import ml_collections

from slotformer_jax.dynamics import base
from slotformer_jax.modules.slot_lstm import SlotLSTM


@base.register
class SlotLSTMModel(base.DynamicsModel):
  """Trained when `slot_lstm.train`."""

  name = 'slot_lstm'
  label = 'Slot-LSTM'
  colour = '#2ca02c'
  inherits = 'slotformer'
  shaping_fields = ('burn_in', 'embed_dim', 'num_layers', 'num_heads',
                    'mlp_ratio', 'residual')

  def build(self, section: ml_collections.ConfigDict) -> nn.Module:
    return SlotLSTM(
        burn_in=section.burn_in, embed_dim=section.embed_dim,
        num_layers=section.num_layers, num_heads=section.num_heads,
        mlp_size=section.mlp_ratio * section.embed_dim,
        dropout_rate=section.dropout_rate, residual=section.residual)
