"""The registry of official model families: which one converts a state dict.

One file per family (savi.py, slotformer.py, steve.py: dVAE, STEVE,
STEVESlotFormer), their shared parts and checks in common.py. Families that
are recognised but not convertible yet say so instead of failing on keys.
"""

from __future__ import annotations

import ml_collections
import numpy as np

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
    Family(
        'phyre_readout', lambda keys: 'in_proj.weight' in keys and any(
            k.startswith('cls_mlp.') for k in keys),
        missing_reason='the PHYRE success readout: its converter is not '
        'written yet.'),
    Family(
        'physion_readout', lambda keys: 'comb_idx' in keys
        and 'linear1.weight' in keys,
        missing_reason='the Physion contact readout: its converter is not '
        'written yet.'),
    Family(
        'aloe', lambda keys: any('cls_answer_mlp.' in k or 'mc_answer_mlp.' in k
                                 for k in keys),
        missing_reason='Aloe (CLEVRER VQA): its converter is not written yet.'),
    steve.DVAE_FAMILY,
)


def families() -> tuple[Family, ...]:
  return FAMILIES


def detect_family(state_dict: dict[str, np.ndarray]) -> Family:
  keys = set(state_dict)
  for family in FAMILIES:
    if family.detect(keys):
      return family
  some = ', '.join(sorted(keys)[:8])
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
