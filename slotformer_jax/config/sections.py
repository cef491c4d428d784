"""Config sections that are derived from others, resolved in one place.

Slot-LSTM is trained "with the same setup" as SlotFormer (the paper's
appendix): its section is `config.slotformer` with the fields set in
`config.slot_lstm` (all but `train`) overriding it. Every reader of a
dynamics model's settings goes through `dynamics_section`.
"""

from __future__ import annotations

import ml_collections

SLOTFORMER = 'slotformer'
SLOT_LSTM = 'slot_lstm'
DYNAMICS_MODELS = (SLOTFORMER, SLOT_LSTM)


def dynamics_section(config: ml_collections.ConfigDict,
                     name: str) -> ml_collections.ConfigDict:
  """The stage-2 hyper-parameters of dynamics model `name`."""
  if name == SLOTFORMER:
    return config.slotformer
  if name != SLOT_LSTM:
    raise ValueError(f'unknown dynamics model {name!r}; one of '
                     f'{DYNAMICS_MODELS}')
  merged = ml_collections.ConfigDict(config.slotformer.to_dict())
  for key, value in config.slot_lstm.items():
    if key != 'train' and value is not None:
      merged[key] = value
  return merged


def several_seeds(config: ml_collections.ConfigDict
                  ) -> tuple[int, ...] | None:
  """`config.seeds` when it names several seeds (trained in one program,
  each chained through the stages after stage 1: docs/seeds.md), else None:
  one seed, `config.seed` (also for a one-value `seeds`, as the trainer
  reads it: train/seeds.py `Seeds.of_config`)."""
  seeds = config.seeds
  if seeds is None or len(seeds) < 2:
    return None
  return tuple(int(s) for s in seeds)


def trained_dynamics(config: ml_collections.ConfigDict) -> tuple[str, ...]:
  """The dynamics models a run trains and compares: SlotFormer, plus
  Slot-LSTM when `slot_lstm.train`."""
  return (SLOTFORMER,) + ((SLOT_LSTM,) if config.slot_lstm.train else ())
