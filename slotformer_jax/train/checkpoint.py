"""A thin wrapper over orbax's CheckpointManager for one training stage.

Saves are asynchronous; a run killed mid-save leaves only a temporary folder
that orbax ignores, so the next run resumes from the last complete step.
"""

from __future__ import annotations

import os
from typing import Any

import jax
from jax.sharding import Sharding
import orbax.checkpoint as ocp


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

  def save(self, step: int, state: Any, *, force: bool = False) -> None:
    self._manager.save(step, args=ocp.args.StandardSave(state), force=force)

  def restore(self, abstract_state: Any, step: int | None = None) -> Any:
    """Restores `step` (default: the latest) into the given structure.

    Raises:
      FileNotFoundError: there is no checkpoint.
      ValueError: the checkpoint does not fit `abstract_state` (another
        model configuration).
    """
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f'no checkpoint in {self.directory}')
    try:
      return self._manager.restore(
          step, args=ocp.args.StandardRestore(abstract_state))
    except (ValueError, KeyError, TypeError) as error:
      raise ValueError(
          f'the checkpoint at {self.directory} (step {step}) does not fit the '
          f'model built from the current config: {error}') from error

  def wait_until_finished(self) -> None:
    self._manager.wait_until_finished()

  def close(self) -> None:
    self._manager.close()
