"""The official SlotFormer family on SAVi slots
(slotformer/video_prediction/models/slotformer.py) -> the `slotformer/` stage,
with its frozen copy of SAVi's decoder to be checked against `savi/`."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import dynamics
from slotformer_jax.dynamics.slotformer import NAME as SLOTFORMER
from slotformer_jax.slot_models.savi import build_decoder
from slotformer_jax.official import common
from slotformer_jax.official.common import Converted
from slotformer_jax.official.common import Family
from slotformer_jax.official.layers import StateDictMapper


def abstract_params(config: ml_collections.ConfigDict) -> Any:
  return dynamics.param_shapes(
      config.slotformer, SLOTFORMER,
      (config.savi.num_slots, config.savi.slot_size))


def convert_slotformer(state_dict: dict[str, np.ndarray],
                       config: ml_collections.ConfigDict) -> Converted:
  """Official SlotFormer: `rollouter.*` plus its frozen copy of SAVi's
  decoder, returned in `extras['decoder']` to be checked against the SAVi
  checkpoint of the same run."""
  common.require(config, 'slot_model', 'savi', 'runs on SAVi slots')
  m = StateDictMapper(state_dict)
  common.map_rollouter(m, config)
  decoder = StateDictMapper(state_dict)
  common.map_spatial_broadcast_decoder(decoder, config, target='decoder')
  for key in state_dict:  # what the decoder read is known to `m` too
    if key.startswith('decoder'):
      m.skip(key)
  params = common.assemble(m, abstract_params(config), hints={
      'rollouter.transformer_encoder': 'config.slotformer.num_layers',
  })
  decoder_model = build_decoder(config.savi.decoder,
                                       tuple(config.data.resolution))
  decoder_abstract = jax.eval_shape(lambda: decoder_model.init(
      jax.random.key(0), jnp.zeros((1, config.savi.num_slots,
                                    config.savi.slot_size))))['params']
  decoder_params = common.assemble(
      common.only(decoder, 'decoder/'), {'decoder': decoder_abstract}, hints={})
  return Converted('slotformer', common.SLOTFORMER_STAGE, params,
                   extras={'decoder': decoder_params['decoder']})


def _is_slotformer(keys: set[str]) -> bool:
  return 'rollouter.in_proj.weight' in keys


FAMILY = Family('slotformer', _is_slotformer, convert_slotformer)
