"""The interface of a dynamics model of stage 2, and its registry.

A dynamics model reads slots [batch, burn_in, num_slots, slot_dim] and
rolls them out for `num_steps` frames: `module(history, num_steps)` ->
[batch, num_steps, num_slots, slot_dim]. One class per model, registered by
name (`register`); the pipeline reads it through the registry only: its
training stage (`train_<name>`), its folder, its place in the evaluation,
the pictures and the explorer, its checks. docs/developing.md, "Adding a
dynamics model"; tests/pipeline/test_registered_dynamics.py is one in one
test file.
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import ml_collections

from slotformer_jax import losses
from slotformer_jax.config import defaults as defaults_lib
from slotformer_jax.config import sections


class DynamicsModel:
  """One dynamics model (subclass it; `register` the subclass).

  Attributes:
    name: its config section, its training stage `train_<name>`, its folder
      in the workdir and its method in the metrics.
    label: how tables, pictures and the explorer name it ('SlotFormer').
    colour: its colour in every curve (render/per_step.png, the explorer).
    inherits: None, or the dynamics model whose section's fields apply
      unless its own section sets them (Slot-LSTM: SlotFormer's; its own
      section then holds `train` and its overrides).
    interventions: whether its module takes the explorer's slot
      interventions (`slot_presence`, `frozen` [B, N] bool) and sows the
      attention the pictures draw: the first trained such model is the one
      the explorer intervenes on and whose masks the pictures show.
    shaping_fields: the section's fields that shape its parameters
      (model_config.json: a model trained with others is refused).
  """

  name: str = ''
  label: str = ''
  colour: str = '#9467bd'
  inherits: str | None = None
  interventions: bool = False
  shaping_fields: tuple[str, ...] = ()

  def build(self, section: ml_collections.ConfigDict) -> nn.Module:
    """Its linen module from its resolved section
    (`config.sections.dynamics_section`)."""
    raise NotImplementedError(f'{type(self).__name__}.build')

  def defaults(self) -> ml_collections.ConfigDict:
    """Its config section's defaults: a built-in model's are in
    `config/defaults.py:base_config`; a model from elsewhere overrides
    this and its config file sets `config.<name> = model.defaults()`."""
    return defaults_lib.base_config()[self.name]

  def loss_terms(self, section: ml_collections.ConfigDict
                 ) -> dict[str, float]:
    """{term: weight} of its training loss (`losses.LOSS_TERMS`): every
    registered term its resolved section weights (`<term>_weight`), L_S
    always; SlotFormer's L_S + image_loss_weight * L_I."""
    return losses.loss_weights(section)

  def trained(self, config: ml_collections.ConfigDict) -> bool:
    """Whether a run of `config` trains and compares it: its section's
    `train` (Slot-LSTM's; the first model of all overrides this); a config
    without its section does not."""
    return self.name in config and bool(config[self.name].train)


def register(cls: type[DynamicsModel]) -> type[DynamicsModel]:
  """Registers dynamics model `cls` under its `name` (a decorator)."""
  model = cls()
  if not model.name or not model.label:
    raise ValueError(f'{cls.__name__}: a dynamics model needs a name and a '
                     'label')
  if model.name in sections.DYNAMICS and type(
      sections.DYNAMICS[model.name]) is not cls:
    raise ValueError(f'dynamics model {model.name!r} is registered twice')
  if model.inherits is not None and model.inherits not in sections.DYNAMICS:
    raise ValueError(f'{model.name}: inherits {model.inherits!r}, which is '
                     'not registered (register it first)')
  sections.DYNAMICS[model.name] = model
  return cls


def get(name: str) -> DynamicsModel:
  """The registered dynamics model `name`."""
  return sections.dynamics_model(name)  # type: ignore[return-value]


def registered() -> tuple[DynamicsModel, ...]:
  """Every registered dynamics model, in registration order."""
  return tuple(sections.DYNAMICS.values())  # type: ignore[arg-type]


def label(name: str) -> str:
  """The label of method `name`: a dynamics model's, else `name`."""
  model = sections.DYNAMICS.get(name)
  return model.label if model is not None else name


def intervened(names: Any) -> str:
  """Of the dynamics models `names`, the first that takes interventions.

  Raises:
    ValueError: none does.
  """
  for name in names:
    if get(name).interventions:
      return name
  raise ValueError(f'none of the dynamics models {tuple(names)} takes slot '
                   'interventions (the explorer and the masks in the '
                   'pictures need one)')
