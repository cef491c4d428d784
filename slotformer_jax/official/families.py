"""The registry of official model families: which one converts a state dict.

One file per family (savi.py, slotformer.py, steve.py: dVAE, STEVE,
STEVESlotFormer; aloe.py; readouts.py: the Physion and PHYRE readouts),
their shared parts and checks in common.py. A family recognised but not
convertible (`convert` None) says so instead of failing on keys.
"""

from __future__ import annotations

import ml_collections
import numpy as np

from slotformer_jax.errors import shown
from slotformer_jax.official import aloe
from slotformer_jax.official import readouts
from slotformer_jax.official import savi
from slotformer_jax.official import slotformer
from slotformer_jax.official import steve
from slotformer_jax.official.common import ConversionError
from slotformer_jax.official.common import Converted
from slotformer_jax.official.common import Family

# Order matters: the first family whose keys match converts (STEVE's keys
# include SAVi's, STEVESlotFormer's SlotFormer's).
FAMILIES: tuple[Family, ...] = (
    steve.STEVE_SLOTFORMER_FAMILY,
    steve.STEVE_FAMILY,
    savi.FAMILY,
    slotformer.FAMILY,
    Family('phyre_readout', readouts.is_phyre_readout,
           readouts.convert_phyre_readout),
    Family('physion_readout', readouts.is_physion_readout,
           readouts.convert_physion_readout),
    Family('aloe', aloe.is_aloe, aloe.convert_aloe),
    steve.DVAE_FAMILY,
)


def families() -> tuple[Family, ...]:
  return FAMILIES


def detect_family(state_dict: dict[str, np.ndarray]) -> Family:
  keys = set(state_dict)
  for family in FAMILIES:
    if family.detect(keys):
      return family
  some = ', '.join(shown(key, 80) for key in sorted(keys)[:8])
  raise ConversionError(
      f'no official model family recognises this state dict (keys: {some}, '
      f'...); known families: {[f.name for f in FAMILIES]}')


def convert_state_dict(state_dict: dict[str, np.ndarray],
                       config: ml_collections.ConfigDict) -> Converted:
  family = detect_family(state_dict)
  if family.convert is None:
    raise NotImplementedError(
        f'official {family.name} checkpoints are recognised but not '
        f'convertible yet: {family.missing_reason}')
  return family.convert(state_dict, config)
