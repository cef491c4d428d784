"""The embedded families by data name, and the generation parameters each
reads from a run's ``config.data``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from slotformer_jax.data.embedded import clevrer_like
from slotformer_jax.data.embedded import contact
from slotformer_jax.data.embedded import phyre_like
from slotformer_jax.data.embedded import synthetic

# data.name -> the family's parameters of a data config (each has
# `num_frames`, the frames per stored video).
PARAMETERS: dict[str, Callable[[Any], Any]] = {
    'synthetic': synthetic.config_from_data_config,
    'synthetic_contact': contact.config_from_data_config,
    'synthetic_phyre': phyre_like.config_from_data_config,
    'clevrer_like': clevrer_like.config_from_data_config,
}
NAMES: tuple[str, ...] = tuple(PARAMETERS)


def generation_config(data_config: Any) -> Any:
  """The generation parameters of an embedded family's data config."""
  return PARAMETERS[data_config.name](data_config)
