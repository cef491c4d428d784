"""The slot models (stage 1), one file each behind one interface (base.py).

`get(config)` builds the one `config.slot_model` names. A new slot model is
a new file here implementing `base.SlotModel`, added to `SLOT_MODELS`.
"""

from __future__ import annotations

import ml_collections

from slotformer_jax.errors import ConfigError
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.slot_models.savi import Savi
from slotformer_jax.slot_models.steve import Steve

SLOT_MODELS: dict[str, type[SlotModel]] = {Savi.name: Savi, Steve.name: Steve}


def get(config: ml_collections.ConfigDict) -> SlotModel:
  """The slot model of `config.slot_model` ('savi' or 'steve')."""
  name = config.get('slot_model', 'savi')
  if name not in SLOT_MODELS:
    raise ConfigError(f'slot_model must be one of {sorted(SLOT_MODELS)}, got '
                      f'{name!r}')
  return SLOT_MODELS[name](config)
