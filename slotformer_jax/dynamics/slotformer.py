"""SlotFormer (the paper's dynamics model): a Transformer over the slots of
the last frames, predicting the next frame's slots autoregressively."""

from __future__ import annotations

import flax.linen as nn
import ml_collections

from slotformer_jax.dynamics import base
from slotformer_jax.modules.slotformer import SlotFormer

# Its registered name (the official weights' converters read it).
NAME = 'slotformer'


@base.register
class SlotFormerModel(base.DynamicsModel):
  """`config.slotformer`; always trained."""

  name = NAME
  label = 'SlotFormer'
  colour = '#1f77b4'
  interventions = True
  shaping_fields = ('burn_in', 'embed_dim', 'num_layers', 'num_heads',
                    'mlp_ratio', 'residual', 'positional_encoding',
                    'max_context', 'layer_norm_epsilon')

  def build(self, section: ml_collections.ConfigDict) -> nn.Module:
    return SlotFormer(
        burn_in=section.burn_in, embed_dim=section.embed_dim,
        num_layers=section.num_layers, num_heads=section.num_heads,
        mlp_size=section.mlp_ratio * section.embed_dim,
        dropout_rate=section.dropout_rate, residual=section.residual,
        positional_encoding=section.positional_encoding,
        max_context=section.max_context,
        layer_norm_epsilon=section.layer_norm_epsilon)

  def trained(self, config: ml_collections.ConfigDict) -> bool:
    return True
