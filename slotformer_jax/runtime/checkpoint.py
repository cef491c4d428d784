"""A thin wrapper over orbax's CheckpointManager for one training stage.

Saves are asynchronous; a run killed mid-save leaves only a temporary folder
that orbax ignores, so the next run resumes from the last complete step. A
checkpoint that is complete but damaged (disk fault, truncated file) is
skipped with a warning and the newest intact one is used.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import jax
from jax.sharding import Sharding
import orbax.checkpoint as ocp

from slotformer_jax.errors import brief
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError

logger = logging.getLogger(__name__)


class CheckpointSaveError(UserError):
  """Writing a checkpoint failed (disk full, permissions): training stops."""


def abstract_like(tree: Any, sharding: Sharding) -> Any:
  """ShapeDtypeStructs of `tree` (arrays or structs) placed on `sharding`."""
  return jax.tree.map(
      lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
      tree)


class Checkpointer:
  """Checkpoints of one stage under `directory` (absolute or relative)."""

  def __init__(self, directory: str, *, max_to_keep: int = 2,
               read_only: bool = False):
    self.directory = os.path.abspath(directory)
    self._manager = ocp.CheckpointManager(
        self.directory,
        options=ocp.CheckpointManagerOptions(
            max_to_keep=max_to_keep, create=not read_only,
            read_only=read_only))

  def latest_step(self) -> int | None:
    return self._manager.latest_step()

  def all_steps(self) -> list[int]:
    return sorted(self._manager.all_steps())

  def save(self, step: int, state: Any, *, force: bool = False) -> None:
    """Starts an async save; an earlier save's failure is raised here.

    Raises:
      CheckpointSaveError: this or the previous save failed.
    """
    try:
      self._manager.save(step, args=ocp.args.StandardSave(state),
                         force=force)
      self._manager.check_for_errors()
    except Exception as error:  # pylint: disable=broad-except
      # Async: the failure may be this save's or an earlier one's.
      raise CheckpointSaveError(
          f'saving checkpoints to {self.directory} failed by step {step} '
          f'({brief(error)}); training stopped. Free disk space (or fix '
          'the folder) and re-run: it resumes from the last saved step '
          f'({self.last_saved_step()}).') from None

  def last_saved_step(self) -> int | str:
    steps = self.all_steps()
    return steps[-1] if steps else 'none'

  def _restore_newest_intact(self, restore_step, what: str,
                             step: int | None) -> tuple[Any, int]:
    """Tries `step` (default: newest first, then older ones)."""
    candidates = [step] if step is not None else self.all_steps()[::-1]
    if not candidates:
      raise FileNotFoundError(f'no checkpoint in {self.directory}')
    failures = []
    for candidate in candidates:
      try:
        restored = restore_step(candidate)
      except Exception as error:  # pylint: disable=broad-except
        failures.append((candidate, error))
        continue
      if failures:
        logger.warning(
            '%s: checkpoint step(s) %s in %s could not be read (%s); using '
            'the newest intact checkpoint, step %d', what,
            [s for s, _ in failures], self.directory,
            brief(failures[0][1]), candidate)
      return restored, candidate
    newest, error = failures[0]
    raise ConfigError(
        f'no checkpoint in {self.directory} can be restored into the {what} '
        f'model built from the current config (tried steps '
        f'{[s for s, _ in failures]}; step {newest}: {brief(error)}). '
        'Either the config differs from the one it was trained with, or the '
        'checkpoints are damaged: use the training config, or delete the '
        'folder to retrain.') from None

  def restore(self, abstract_state: Any, step: int | None = None,
              what: str = 'training') -> Any:
    """Restores `step` (default: the newest intact one) into the structure.

    Raises:
      FileNotFoundError: there is no checkpoint.
      ConfigError (a ValueError): no checkpoint fits `abstract_state`
        (another model configuration, or every checkpoint damaged).
    """
    restored, _ = self._restore_newest_intact(
        lambda s: self._manager.restore(
            s, args=ocp.args.StandardRestore(abstract_state)), what, step)
    return restored

  def restore_params(self, abstract_params: Any, step: int | None = None,
                     what: str = 'model') -> tuple[Any, int]:
    """Only `params` (and the step) of a saved TrainState: no optimizer is
    needed to read a model. Returns (params, step)."""
    fields, step = self.restore_fields({'params': abstract_params}, step,
                                       what)
    return fields['params'], step

  def restore_fields(self, abstract_fields: dict[str, Any],
                     step: int | None = None, what: str = 'model'
                     ) -> tuple[dict[str, Any], int]:
    """Only the named fields of a saved state ({'params': ...,
    'diverged_at': ...} of a SeedsState) and the step."""
    restore_args = ocp.checkpoint_utils.construct_restore_args(
        abstract_fields)

    def restore_step(s):
      restored = self._manager.restore(s, args=ocp.args.PyTreeRestore(
          item=abstract_fields, restore_args=restore_args,
          partial_restore=True))
      return {name: restored[name] for name in abstract_fields}
    return self._restore_newest_intact(restore_step, what, step)

  def wait_until_finished(self) -> None:
    self._manager.wait_until_finished()

  def check_for_errors(self) -> None:
    self._manager.check_for_errors()

  def close(self) -> None:
    self._manager.close()


def restore_params(stage_directory: str, param_shapes: Any,
                   sharding: Sharding, *, what: str,
                   train_command: str) -> tuple[Any, int]:
  """The newest intact parameters of a stage folder (`<dir>/checkpoints`),
  placed on `sharding`, and their step; reading never builds an optimizer.

  Raises:
    UserError: no checkpoint (the message names `train_command`), or none
      fits `param_shapes`.
  """
  fields, step = restore_fields(stage_directory, {'params': param_shapes},
                                sharding, what=what,
                                train_command=train_command)
  return fields['params'], step


def restore_fields(stage_directory: str, shapes: dict[str, Any],
                   sharding: Sharding, *, what: str,
                   train_command: str) -> tuple[dict[str, Any], int]:
  """`restore_params` of the named fields of the saved state ({'params':
  shapes, 'diverged_at': shape} of a several-seed stage), each placed on
  `sharding`, and their step.

  Raises:
    UserError: no checkpoint (the message names `train_command`), or none
      fits `shapes`.
  """
  directory = os.path.join(stage_directory, 'checkpoints')
  if not os.path.isdir(directory):
    raise MissingInputError(f'no {what} checkpoint under {directory}. Train '
                            f'it first: {train_command}')
  checkpointer = Checkpointer(directory, read_only=True)
  try:
    if checkpointer.latest_step() is None:
      raise MissingInputError(f'no {what} checkpoint under {directory}. '
                              f'Train it first: {train_command}')
    return checkpointer.restore_fields(abstract_like(shapes, sharding),
                                       what=what)
  finally:
    checkpointer.close()
