"""A thin wrapper over orbax's CheckpointManager for one training stage.

Saves are asynchronous; a run killed mid-save leaves only a temporary folder
that orbax ignores, so the next run resumes from the last complete step.

Once orbax has committed a step, process 0 writes `<step>/sha256.json`: the
size and SHA-256 of every file of the step. A restore checks it first, so a
step whose bytes differ from what was saved (a disk fault, a truncated or
overwritten file) is never loaded: training sets it aside as
`<step>.damaged-<time>` (orbax ignores that name, and the step can be saved
again) and resumes from the newest intact step; a read-only restore
(evaluation, extraction) skips it. With several processes, process 0 checks
and every process restores the step it chose.

Before its first save, process 0 writes `digests.json` beside the steps:
the first step saved with a digest. A step from then on without
sha256.json (the process killed between orbax finishing it and its digest)
is not intact and is set aside as a damaged one is. A step from before
(a folder saved before digests existed) restores as before: nothing is
recorded retroactively, since a digest taken now would bless whatever bytes
are there, and a read-only workdir must not be written. Orbax's own read
errors still skip such a step. The digest files are read as untrusted
(`checkpoint_digest`). A step that cannot be renamed (a read-only folder)
is named in the warning and skipped.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Iterator
from typing import Any, Callable

import jax
from jax.sharding import Sharding
import orbax.checkpoint as ocp

from slotformer_jax.errors import brief
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.runtime import processes
from slotformer_jax.runtime.checkpoint_digest import damage_of
from slotformer_jax.runtime.checkpoint_digest import DIGEST_FILE
from slotformer_jax.runtime.checkpoint_digest import digests_since
from slotformer_jax.runtime.checkpoint_digest import record_digests_since
from slotformer_jax.runtime.checkpoint_digest import write_digest

logger = logging.getLogger(__name__)


class CheckpointSaveError(UserError):
  """Writing a checkpoint failed (disk full, permissions): training stops."""


class DamagedCheckpointError(UserError):
  """Every checkpoint step there is holds other bytes than were saved."""


_DAMAGED = '.damaged-'  # a step set aside: '30.damaged-20250102T030405'


def set_aside(directory: str, step: int) -> str:
  """Renames step folder `step` to a name orbax ignores; returns it."""
  stamp = time.strftime('%Y%m%dT%H%M%S')
  for attempt in range(100):
    name = f'{step}{_DAMAGED}{stamp}' + (f'-{attempt}' if attempt else '')
    target = os.path.join(directory, name)
    if not os.path.lexists(target):
      os.rename(os.path.join(directory, str(step)), target)
      return name
  raise FileExistsError(f'no free name for step {step} set aside in '
                        f'{directory}')


def abstract_like(tree: Any, sharding: Sharding) -> Any:
  """ShapeDtypeStructs of `tree` (arrays or structs) placed on `sharding`."""
  return jax.tree.map(
      lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
      tree)


class _OrbaxNotice(logging.Filter):
  """Drops orbax's warnings that begin with `prefix`."""

  def __init__(self, prefix: str):
    super().__init__()
    self.prefix = prefix

  def filter(self, record: logging.LogRecord) -> bool:
    return not record.getMessage().startswith(self.prefix)


@contextlib.contextmanager
def _without_orbax_notice(prefix: str) -> Iterator[None]:
  absl_logger = logging.getLogger('absl')
  notice = _OrbaxNotice(prefix)
  absl_logger.addFilter(notice)
  try:
    yield
  finally:
    absl_logger.removeFilter(notice)


# orbax saves a replicated array in slices, one per device ("replica
# parallel"). For a slice under 1 MiB the split costs more than it saves (a
# device op and a write per slice; docs/performance.md, "The test suite's
# wall time"). Arrays whose slices would be smaller are written whole by one
# replica, as orbax writes every array on GPUs; larger ones still split.
# orbax's handler registry is per process: set once, here, unless someone
# registered a handler of their own.
MIN_REPLICA_SLICE_BYTES = 1 << 20


def _save_small_arrays_whole() -> None:
  current = ocp.type_handlers.get_type_handler(jax.Array)
  if type(current) is not ocp.type_handlers.ArrayHandler:  # pylint: disable=unidiomatic-typecheck
    return
  # pylint: disable=protected-access
  handler = ocp.type_handlers.ArrayHandler(
      array_metadata_store=current._array_metadata_store,
      use_replica_parallel=current._use_replica_parallel,
      min_slice_bytes_for_replica_parallel=MIN_REPLICA_SLICE_BYTES)
  with _without_orbax_notice('Type handler registry type'):
    ocp.type_handlers.register_type_handler(jax.Array, handler, override=True)


_save_small_arrays_whole()


class Checkpointer:
  """Checkpoints of one stage under `directory` (absolute or relative)."""

  def __init__(self, directory: str, *, max_to_keep: int = 2,
               read_only: bool = False):
    self.directory = os.path.abspath(directory)
    self.read_only = read_only
    # Read-only: the options orbax would otherwise reset with a warning
    # each, and its notice that the folder is read only (what was asked)
    # dropped: loading a trained model prints nothing.
    with _without_orbax_notice('Given directory is read only'):
      self._manager = ocp.CheckpointManager(
          self.directory,
          options=ocp.CheckpointManagerOptions(
              max_to_keep=None if read_only else max_to_keep,
              save_interval_steps=0 if read_only else 1,
              create=not read_only, read_only=read_only))
    # The thread that writes the digest of the step being saved.
    self._digester: threading.Thread | None = None

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
      self._join_digester()
      if jax.process_index() == 0:
        # Before the step exists: a step of this folder without a digest
        # from now on was cut short before its digest, and is not intact.
        record_digests_since(self.directory, step)
      saved = self._manager.save(step, args=ocp.args.StandardSave(state),
                                 force=force)
      self._manager.check_for_errors()
      if saved and jax.process_index() == 0:
        self._digester = threading.Thread(
            target=self._digest_when_finished, args=(step,),
            name=f'checkpoint digest {step}', daemon=True)
        # A watchdog ending this process (a peer lost) waits for it first.
        processes.before_exit(self._digest_before_exit)
        self._digester.start()
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

  def _digest_when_finished(self, step: int) -> None:
    """(A thread of process 0.) Once orbax has committed `step` (renamed its
    temporary folder to `<step>`), records its digest. Not after
    `wait_until_finished`: after the commit orbax still waits for every
    process at a barrier, which a process killed just then never reaches,
    and the step would stay without a digest (damaged). A failed save
    leaves no folder; the next save or wait reports it."""
    step_directory = os.path.join(self.directory, str(step))
    try:
      # Saving ends (the barrier passed) only after the commit: a folder
      # absent then never comes.
      while (not os.path.isdir(step_directory)
             and self._manager.is_saving_in_progress()):
        time.sleep(0.02)
      if os.path.isdir(step_directory):
        write_digest(step_directory)
    except OSError as error:
      logger.warning('checkpoint step %d in %s: its %s could not be written '
                     '(%s); a restore will not take it as intact (it uses '
                     'the step before)', step, self.directory, DIGEST_FILE,
                     brief(error))
    finally:
      processes.not_before_exit(self._digest_before_exit)

  def _digest_before_exit(self, seconds: float) -> None:
    """(`processes.before_exit` hook.) Up to `seconds` for the digest in
    flight: the survivor of a lost peer must not end before it."""
    digester = self._digester
    if digester is not None:
      digester.join(seconds)

  def _join_digester(self) -> None:
    if self._digester is not None:
      self._digester.join()
      self._digester = None

  def _agreed(self, values: list[int], *, every: bool = False) -> list[int]:
    """Process 0's `values` (`every`: the minimum over the processes),
    the same on every process; with one process, `values`."""
    if jax.process_count() == 1 or not values:
      return values
    rows = processes.gathered(values)
    return [int(v) for v in (rows.min(axis=0) if every else rows[0])]

  def _restore_newest_intact(self, restore_step: Callable[[int], Any],
                             what: str, step: int | None,
                             train_command: str | None = None
                             ) -> tuple[Any, int]:
    """Tries `step` (default: newest first, then older ones), never one
    whose bytes differ from what was saved. Writable: the damaged steps,
    and the unreadable ones newer than the restored one (orbax would refuse
    to save those steps again), are set aside."""
    self._join_digester()
    candidates = [step] if step is not None else self.all_steps()[::-1]
    if not candidates:
      raise FileNotFoundError(f'no checkpoint in {self.directory}')
    # Process 0 checks the digests; every process goes by its verdict.
    reasons = {}
    if jax.process_index() == 0:
      since = digests_since(self.directory)
      for candidate in candidates:
        reason = damage_of(os.path.join(self.directory, str(candidate)),
                           required=candidate >= since)
        if reason is not None:
          reasons[candidate] = reason
    damaged = self._agreed([int(c in reasons) for c in candidates])
    for candidate, is_damaged in zip(candidates, damaged):
      if is_damaged and candidate not in reasons:
        reasons[candidate] = 'found by process 0'
    failures, restored, chosen = [], None, None
    for candidate, is_damaged in zip(candidates, damaged):
      if is_damaged:
        continue
      error = None
      try:
        restored = restore_step(candidate)
      except Exception as raised:  # pylint: disable=broad-except
        error = raised
      # A step is used only when every process could read it.
      if self._agreed([int(error is None)], every=True) == [1]:
        chosen = candidate
        break
      failures.append((candidate, error or RuntimeError(
          'another process could not read it')))
    set_aside_names = self._set_aside_unusable(
        [c for c, bad in zip(candidates, damaged) if bad]
        + ([c for c, _ in failures] if chosen is not None else []))
    damage = self._damage_note(reasons, set_aside_names)
    if chosen is not None:
      if damage or failures:
        aside = [set_aside_names[c] for c, _ in failures
                 if c in set_aside_names]
        unreadable = (f'step(s) {[c for c, _ in failures]} could not be read '
                      f'({brief(failures[0][1])})'
                      + (f', {", ".join(aside)}' if aside else '')
                      + '; ' if failures else '')
        logger.warning('%s: in %s, %s%susing the newest intact checkpoint, '
                       'step %d', what, self.directory,
                       f'{damage}; ' if damage else '', unreadable, chosen)
      return restored, chosen
    if not failures:
      stuck = any(n.startswith('not ') for n in set_aside_names.values())
      raise DamagedCheckpointError(
          f'{what}: no intact checkpoint in {self.directory}: {damage}. '
          + ('Make the folder writable (or move the damaged steps out of '
             'it) and re-run the same command: it trains from step 0.'
             if stuck else
             'Re-run the same command: it trains from step 0 (or put back '
             'an intact copy of the step first).' if not self.read_only
             else 'Re-run the training stage'
             + (f' ({train_command})' if train_command else '')
             + ': it sets the damaged step aside and trains again.'))
    newest, error = failures[0]
    raise ConfigError(
        f'no checkpoint in {self.directory} can be restored into the {what} '
        f'model built from the current config (tried steps '
        f'{[s for s, _ in failures]}; step {newest}: {brief(error)}'
        f'{"; " + damage if damage else ""}). '
        'Either the config differs from the one it was trained with, or the '
        'checkpoints are damaged: use the training config, or delete the '
        'folder to retrain.') from None

  def _set_aside_unusable(self, steps: list[int]) -> dict[int, str]:
    """{step: new name, or why it could not be renamed} of `steps`, renamed
    by process 0 (writable only); every process then sees the folder
    without them. A folder that cannot be renamed in (read-only, no
    permission) keeps the step: the restore goes on with an older one."""
    if self.read_only or not steps:
      return {}
    names = {}
    if jax.process_index() == 0:
      for step in steps:
        try:
          names[step] = 'set aside as ' + set_aside(self.directory, step)
        except OSError as error:
          why = error.strerror or brief(error)
          names[step] = (f'not set aside ({why}): move it out of the folder '
                         'before this step is saved again')
    self._agreed([0])  # the renames are done before anyone lists
    self._manager.reload()
    return names

  def _damage_note(self, reasons: dict[int, str],
                   names: dict[int, str]) -> str:
    """'step 30 is damaged (...), set aside as 30.damaged-...' for each."""
    notes = []
    for step, reason in sorted(reasons.items(), reverse=True):
      aside = f', {names[step]}' if step in names else ''
      notes.append(f'step {step} is damaged ({reason}){aside}')
    return '; '.join(notes)

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
                     step: int | None = None, what: str = 'model',
                     train_command: str | None = None
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
    return self._restore_newest_intact(restore_step, what, step,
                                       train_command)

  def wait_until_finished(self) -> None:
    """Until the saves in flight, and their digests, are written."""
    try:
      self._manager.wait_until_finished()
    finally:
      self._join_digester()

  def check_for_errors(self) -> None:
    self._manager.check_for_errors()

  def close(self) -> None:
    try:
      self._manager.close()
    finally:
      self._join_digester()


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
                                       what=what, train_command=train_command)
  finally:
    checkpointer.close()
