"""Downstream tasks on top of the dynamics model (Sections 4.3-4.4)."""

from __future__ import annotations

from collections.abc import Callable


def stages_for(task: str | None) -> dict[str, Callable]:
  """The main-entry stages of a task config (config.task), by mode name."""
  # pylint: disable=g-import-not-at-top
  if task is None:
    return {}
  if task == 'contact':
    from slotformer_jax.tasks import contact
    return {'train_readout': contact.train_readout,
            'evaluate_readout': contact.evaluate_readout}
  if task == 'planning':
    from slotformer_jax.tasks import phyre_planning
    return {'train_readout': phyre_planning.train_readout,
            'plan': phyre_planning.plan}
  raise ValueError(f"unknown task {task!r}; 'contact' or 'planning'")
