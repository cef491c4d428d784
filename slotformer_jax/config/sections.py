"""Config sections that are derived from others, resolved in one place.

The dynamics models are registered by name (`slotformer_jax/dynamics/`):
the registry lives here, on the config floor, because the checks and the
resolved sections read it; the models register themselves from above
(`dynamics.base.register`). A model whose `inherits` names another trains
"with the same setup" as that one (Slot-LSTM as SlotFormer, the paper's
appendix): its section is the inherited one with the fields set in its own
(all but `train`) overriding it. Every reader of a dynamics model's
settings goes through `dynamics_section`.
"""

from __future__ import annotations

from typing import Protocol

import ml_collections


class DynamicsSection(Protocol):
  """What the config floor reads of a registered dynamics model
  (`dynamics/base.py:DynamicsModel`)."""

  name: str
  inherits: str | None

  def trained(self, config: ml_collections.ConfigDict) -> bool:
    """Whether a run of `config` trains and compares it."""


# {name: model}, in registration order (the built-in ones first, the
# first of them the one the protocol and the tasks read).
DYNAMICS: dict[str, DynamicsSection] = {}


def dynamics_model(name: str) -> DynamicsSection:
  """The registered dynamics model `name`."""
  if name not in DYNAMICS:
    raise ValueError(f'unknown dynamics model {name!r}; one of '
                     f'{tuple(DYNAMICS)}')
  return DYNAMICS[name]


def dynamics_section(config: ml_collections.ConfigDict,
                     name: str) -> ml_collections.ConfigDict:
  """The stage-2 hyper-parameters of dynamics model `name`."""
  model = dynamics_model(name)
  if model.inherits is None:
    return config[name]
  merged = ml_collections.ConfigDict(
      dynamics_section(config, model.inherits).to_dict())
  for key, value in config[name].items():
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
  """The dynamics models a run trains and compares, in registration order
  (SlotFormer; Slot-LSTM when `slot_lstm.train`; ...)."""
  if not DYNAMICS:
    raise RuntimeError('no dynamics model is registered: import '
                       'slotformer_jax.dynamics first')
  return tuple(name for name, model in DYNAMICS.items()
               if model.trained(config))


def primary_dynamics(config: ml_collections.ConfigDict) -> str:
  """The dynamics model whose burn-in and frame stride set the evaluation
  protocol for all, and whose rollouts the tasks read: the first trained."""
  return trained_dynamics(config)[0]


def dynamics_stages(config: ml_collections.ConfigDict) -> tuple[str, ...]:
  """The training stage of every registered dynamics model whose section
  `config` has (a model registered by other code, e.g. a test, is no stage
  of a config without its section)."""
  return tuple(f'train_{name}' for name in DYNAMICS if name in config)
