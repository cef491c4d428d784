"""The slot models (stage 1), one file each behind one interface (base.py).

`get(config)` builds the one `config.slot_model` names. SAVi and STEVE are
registered here; a slot model defined elsewhere (a research file, a test)
registers itself with `register` when its module is imported, e.g. from the
config file that selects it (docs/developing.md).
"""

from __future__ import annotations

import ml_collections

from slotformer_jax.errors import ConfigError
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.slot_models.savi import Savi
from slotformer_jax.slot_models.steve import Steve

SLOT_MODELS: dict[str, type[SlotModel]] = {}


def register(slot_model: type[SlotModel]) -> type[SlotModel]:
  """Makes `slot_model` selectable as `config.slot_model = <its name>`
  (usable as a class decorator; registering the same class again is a
  no-op, another class under a taken name an error)."""
  taken = SLOT_MODELS.get(slot_model.name)
  if taken is not None and taken is not slot_model and (
      taken.__qualname__, taken.__module__) != (slot_model.__qualname__,
                                                slot_model.__module__):
    raise ValueError(f'slot model name {slot_model.name!r} is taken by '
                     f'{taken.__module__}.{taken.__qualname__}')
  SLOT_MODELS[slot_model.name] = slot_model
  return slot_model


register(Savi)
register(Steve)


def get(config: ml_collections.ConfigDict) -> SlotModel:
  """The slot model of `config.slot_model`, configured by `config`."""
  name = config.slot_model
  if name not in SLOT_MODELS:
    raise ConfigError(f'slot_model must be one of {sorted(SLOT_MODELS)}, got '
                      f'{name!r}' + ('' if name in ('savi', 'steve') else
                                     ' (a slot model of your own registers '
                                     'with slot_models.register)'))
  return SLOT_MODELS[name](config)
