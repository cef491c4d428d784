"""Stopping a training loop on SIGTERM (how SLURM and TPU pods preempt) or
SIGINT (Ctrl-C): the signal is noted, the loop saves the current step and
raises `Preempted`; the rerun resumes from it.

With several processes a signal to any of them stops all after the same
step: one small all-gather (`processes.agreed_signal`) agrees on it every
`every` updates and after the last, so a signal is acted on at most
`every - 1` updates late; one noted after the last check (during the last
save) stops the run once that save is done. The trainer keeps at most
`in_flight.MAX_STEPS_AHEAD` updates queued on the devices, so the save
that follows a signal waits for at most that many more. Not orbax's
preemption sync: that relies on jax's own SIGTERM handler, which ours
replaces (`processes.initialize` turns it off).
"""

from __future__ import annotations

import signal
import threading

import jax

from slotformer_jax.errors import UserError
from slotformer_jax.runtime import processes

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Preempted(UserError):
  """SIGTERM or SIGINT arrived; the state of the current step was saved."""

  def __init__(self, message: str, signal_number: int = signal.SIGTERM):
    super().__init__(message)
    self.signal = int(signal_number)


class StopSignals:
  """Notes SIGTERM / SIGINT instead of dying, while installed (main thread
  only). `received`: the signal's number (SIGTERM wins), 0 while none.

  A signal ignored when training starts stays ignored (a job started with
  `nohup ... &` from a script ignores SIGINT; Python itself then installs
  no KeyboardInterrupt handler), and every handler is put back as it was.
  """

  def __init__(self):
    self.received = 0
    self._previous = {}

  def __enter__(self) -> StopSignals:
    if threading.current_thread() is threading.main_thread():
      for signum in STOP_SIGNALS:
        if signal.getsignal(signum) is signal.SIG_IGN:
          continue
        self._previous[signum] = signal.signal(signum, self._note)
    return self

  def _note(self, signum, frame) -> None:
    del frame
    self.received = max(self.received, int(signum))

  def __exit__(self, *exc) -> None:
    for signum, previous in self._previous.items():
      # None: a handler not set from Python; the default is what it did.
      signal.signal(signum, signal.SIG_DFL if previous is None else previous)


def agrees_after(done: int, num_steps: int, every: int) -> bool:
  """Whether several processes agree on a stop after update `done` (1-based):
  every `every` updates and after the last one."""
  return done % every == 0 or done == num_steps


def stop_signal(flag: StopSignals, done: int, num_steps: int,
                every: int = 1) -> tuple[int, list[int]]:
  """(signal to save and stop on after update `done` or 0, the processes
  that received it). Several processes: each notes its own signals, and an
  all-gather after the updates of `agrees_after` (every process calls it
  after the same one) makes the answer the same everywhere; between them a
  signal waits, since a collective per step is a host sync per step on an
  accelerator. One process acts on its own signal at once."""
  if jax.process_count() > 1:
    if not agrees_after(done, num_steps, every):
      return 0, []
    return processes.agreed_signal(flag.received)
  return flag.received, [jax.process_index()] if flag.received else []


class Preemption:
  """The stop signals of one training loop `name` of `num_steps` updates,
  agreed every `every` updates (`stop_signal`); a context manager.

  A signal noted after the loop's last check (while its last step is saved
  or logged, or its reader closed) is not dropped: leaving the block
  normally then raises `Preempted` (its last step is saved by then), so the
  run stops instead of going on to the next stage.
  """

  def __init__(self, num_steps: int, every: int = 1, name: str = 'training'):
    self.num_steps = num_steps
    self.every = every
    self.name = name
    self._flag = StopSignals()
    self._signal = 0
    self._signalled: list[int] = []
    self._acted = False

  def __enter__(self) -> Preemption:
    self._flag.__enter__()
    return self

  def __exit__(self, kind, error, traceback) -> None:
    self._flag.__exit__(kind, error, traceback)
    if kind is not None or self._acted:
      return
    # Every process leaves the loop after the same last step: one more
    # agreement (several processes), on the signals noted since.
    self._signal, self._signalled = stop_signal(self._flag, self.num_steps,
                                                self.num_steps)
    if self._signal:
      raise self.stopped(self.name, self.num_steps, last=True)

  def stops_after(self, done: int) -> bool:
    """Whether to save and stop after update `done`."""
    self._signal, self._signalled = stop_signal(self._flag, done,
                                                self.num_steps, self.every)
    return self._signal != 0

  def stopped(self, name: str, done: int, last: bool = False) -> Preempted:
    """The error to raise once update `done` of `name` is saved (`last`:
    its last update, the signal came while it was saved)."""
    self._acted = True
    by = signal.Signals(self._signal).name
    if jax.process_count() > 1:
      by += ' to process ' + ', '.join(map(str, self._signalled))
    after = f'its last step, {done}' if last else f'step {done}'
    return Preempted(f'{name}: stopped by {by} after {after}; its '
                     'checkpoint is saved. Re-run the same command to '
                     'resume.', self._signal)
