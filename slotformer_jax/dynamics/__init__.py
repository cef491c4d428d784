"""The dynamics models of stage 2 as the pipeline uses them: registered by
name (`base.py`, one file each: `slotformer.py`, `slot_lstm.py`), built
from their config section, the fields that shape them, and their trained
parameters loaded from a workdir.

A dynamics model reads slots [B, T, N, D] and rolls them out; it knows
nothing of the slot model but its slot shape (N, D).
"""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
from typing import Any

import flax.linen as nn
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import inference
from slotformer_jax import targets as targets_lib
from slotformer_jax.dynamics import base
# The built-in models register themselves, SlotFormer first (Slot-LSTM
# inherits its section).
from slotformer_jax.dynamics import slotformer  # pylint: disable=unused-import
from slotformer_jax.dynamics import slot_lstm  # pylint: disable=unused-import
from slotformer_jax.dynamics.base import DynamicsModel
from slotformer_jax.dynamics.base import get
from slotformer_jax.dynamics.base import label
from slotformer_jax.dynamics.base import register
from slotformer_jax.dynamics.base import registered
from slotformer_jax.frames import labelled_grid
from slotformer_jax.frames import to_uint8
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir.paths import command

__all__ = ['DynamicsModel', 'Loaded', 'build', 'example', 'get',
           'identity_fields', 'label', 'load', 'model_fields', 'param_shapes',
           'register', 'registered', 'rollout_images']


def build(section: ml_collections.ConfigDict, name: str) -> nn.Module:
  """Dynamics model `name`'s module from its resolved section
  (`config.sections.dynamics_section`)."""
  return get(name).build(section)


def model_fields(section: ml_collections.ConfigDict,
                 name: str) -> dict[str, Any]:
  """The settings that determine the model's parameters (model_config.json)."""
  return identity_lib.plain({key: section[key]
                             for key in get(name).shaping_fields})


def identity_fields(seed: int, section: ml_collections.ConfigDict,
                    name: str) -> dict[str, Any]:
  """Everything that shapes the trained model besides the slots it reads
  (recorded as its parent)."""
  return identity_lib.plain({'seed': seed, name: identity_lib.shaping(
      section.to_dict())})


def example(section: ml_collections.ConfigDict,
            slot_shape: tuple[int, int]) -> tuple[jax.Array, int]:
  """(history zeros [1, burn_in, N, D], rollout): the example inputs the
  model is initialised with, for slots of `slot_shape` (N, D)."""
  history = jnp.zeros((1, section.burn_in, *slot_shape), jnp.float32)
  return history, section.rollout


def param_shapes(section: ml_collections.ConfigDict, name: str,
                 slot_shape: tuple[int, int]) -> Any:
  """The parameter shapes of dynamics model `name` over slots of
  `slot_shape` (no compute)."""
  return inference.param_shapes(build(section, name),
                                *example(section, slot_shape))


@dataclasses.dataclass(frozen=True)
class Loaded:
  """A trained dynamics model of a workdir.

  Attributes:
    name: the dynamics model's (`base.DynamicsModel.name`).
    module: the linen module (apply with {'params': params}).
    params: its newest parameters (replicated over the mesh).
    step: the step they were saved at.
    diverged_at: for one seed of several trained in one program, the update
      in which it diverged (its parameters are its last finite ones); 0
      when it did not (always, for one seed).
  """

  name: str
  module: nn.Module
  params: Any
  step: int
  diverged_at: int = 0


def load(paths: Paths, mesh: Mesh, name: str,
         section: ml_collections.ConfigDict,
         slot_shape: tuple[int, int],
         stacked: inference.StackedSeed | None = None) -> Loaded:
  """The newest parameters of dynamics model `name` of the run `paths`,
  trained on slots of `slot_shape` with `section`'s architecture;
  `stacked`: a seed view's share of the stacked checkpoint of a K-seed
  run.

  Raises:
    UserError: never trained (the message names the stage), or trained with
      another architecture.
  """
  directory = paths.dynamics(name)
  identity_lib.check_model_config(directory, model_fields(section, name),
                                  name)
  shapes = param_shapes(section, name, slot_shape)
  train_command = command(paths.root, f'train_{name}')
  diverged_at = 0
  if stacked is None:
    params, step = inference.restore(
        directory, shapes, mesh, what=name, train_command=train_command,
        num_train_steps=section.num_train_steps)
  else:
    params, step, diverged_at = inference.restore_seed(
        directory, shapes, mesh, stacked, what=name,
        train_command=train_command, num_train_steps=section.num_train_steps)
  return Loaded(name=name, module=build(section, name), params=params,
                step=step, diverged_at=diverged_at)


def rollout_images(slot_model: Any, slot_params: Any, model: nn.Module,
                   burn_in: int, rollout: int, name: str
                   ) -> Callable[[Any, dict[str, Any]], dict[str, Any]] | None:
  """The training stage's TensorBoard pictures, (params, batch) -> {'rollout':
  strip}: the first clip of the batch, its frames (when the batch has them),
  its extracted slots decoded, and the burn-in slots followed by the model's
  rollout, decoded (the frames; a SAVi that reconstructs no frames: its
  first target, flow in colour or depth in grey). None for a slot model
  without a pixel decoder (STEVE would generate every frame token by
  token)."""
  if slot_model.image_decoder(slot_params) is None:
    return None

  @jax.jit
  def decode(params, slots):
    predicted = inference.rollout_slots(params, slots[:, :burn_in],
                                        model=model, num_steps=rollout)
    both = jnp.concatenate([slots, jnp.concatenate(
        [slots[:, :burn_in], predicted], axis=1)])
    decoded = slot_model.decode(slot_params, both)
    if decoded.recon is not None:  # frames in [0, 1]
      return {targets_lib.RGB.name: decoded.recon}
    target = next(iter(decoded.targets))  # in its data's range
    return {target: decoded.targets[target]}

  def images(params, batch):
    (target, recon), = jax.device_get(
        decode(params, batch['slots'][:1])).items()
    if target != targets_lib.RGB.name:
      recon = targets_lib.picture(targets_lib.TARGETS[target], recon)
    rows = {}
    if 'video' in batch:  # the rollout's frames (L_I reads no others)
      frames = batch['video'][0]
      rows['real frames'] = np.concatenate([np.full(
          (burn_in + rollout - len(frames), *frames.shape[1:]), 255,
          np.uint8), frames])  # white under the burn-in
    rows['slots decoded'] = to_uint8(recon[0])
    rows[f'burn-in {burn_in} + {name}'] = to_uint8(recon[1])
    return {'rollout': labelled_grid(rows)}

  return images
