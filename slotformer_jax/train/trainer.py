"""The training loop shared by both stages, readable top to bottom.

mesh -> optimiser -> restore or initialise the state -> jit the update step
-> loop: host batch -> global batch (placed on the devices one or two steps
ahead) -> update -> log / NaN check ->
checkpoint. Re-running resumes from the newest checkpoint, and the data
stream resumes at the same step (batches are a function of the step).

Failures stop the loop at once with one line: a non-finite loss or updated
state (never saved; the message names the last good checkpoint), a failed
checkpoint save. SIGTERM (how SLURM and TPU pods preempt) and SIGINT (Ctrl-C)
save a checkpoint at the current step and raise `Preempted`; the rerun
resumes bit-exact. With several processes, a signal to any of them stops all
after the same step: one small all-gather agrees on it every
`stop_check_every` steps of the stage's config (default 1) and after the
last step, so a signal is acted on at most `stop_check_every - 1` steps late.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import dataclasses
import functools
import json
import logging
import math
import os
import signal
import threading
import time
from typing import Any
import warnings

import jax
from jax.sharding import Mesh
import ml_collections
import numpy as np
import optax
import tqdm

from slotformer_jax.errors import UserError
from slotformer_jax.files import append_line_atomic
from slotformer_jax.train import optim
from slotformer_jax.runtime import processes
from slotformer_jax.runtime import sharding
from slotformer_jax.runtime.checkpoint import Checkpointer
from slotformer_jax.runtime.checkpoint import abstract_like
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.summaries import Summaries
from slotformer_jax.train.steps import LossFn
from slotformer_jax.train.steps import train_step

logger = logging.getLogger(__name__)

# XLA:CPU cannot reuse donated buffers and says so on every call.
warnings.filterwarnings('ignore', message='Some donated buffers were not usable')


@dataclasses.dataclass(frozen=True)
class Stage:
  """What differs between training SAVi and training SlotFormer.

  Attributes:
    name: 'savi' or 'slotformer'; also the sub-folder of the workdir.
    directory: where checkpoints and the training log go.
    config: the stage's config section (batch_size, num_train_steps,
      learning_rate, min_lr_fraction, warmup_fraction, grad_clip,
      log_every, checkpoint_every, stop_check_every; config/defaults.py).
    loss_fn: (params, batch, frozen_params, rng) -> (loss, metrics).
    init_params: rng -> params.
    batches: start_step -> iterator of this host's batches.
    frozen_params: parameters used but not trained (SAVi's decoder).
    logging: the root config's `logging` section (TensorBoard; None: off).
    images: (params on the host, this step's host batch) -> {name: uint8
      [H, W, 3] labelled picture}, written to TensorBoard every
      `logging.image_every` steps; None: scalars only.
  """

  name: str
  directory: str
  config: ml_collections.ConfigDict
  loss_fn: LossFn
  init_params: Callable[[jax.Array], Any]
  batches: Callable[[int], Iterator[dict[str, np.ndarray]]]
  frozen_params: Any = None
  logging: ml_collections.ConfigDict | None = None
  images: Callable[[Any, dict[str, np.ndarray]],
                   dict[str, np.ndarray]] | None = None


class Preempted(UserError):
  """SIGTERM or SIGINT arrived; the state of the current step was saved."""

  def __init__(self, message: str, signal_number: int = signal.SIGTERM):
    super().__init__(message)
    self.signal = int(signal_number)


class Diverged(UserError, FloatingPointError):
  """The loss or the updated parameters became non-finite."""


_STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
# Batches handed to the devices ahead of the step that uses them
# (`sharding.prefetch_to_device`): the one of the next step while this one
# runs, and one more to absorb an uneven reader.
DEVICE_PREFETCH = 2


class _TermFlag:
  """Notes SIGTERM / SIGINT instead of dying, while installed (main thread
  only). `received`: the signal's number (SIGTERM wins), 0 while none.

  A signal ignored when training starts stays ignored (a job started with
  `nohup ... &` from a script ignores SIGINT; Python itself then installs
  no KeyboardInterrupt handler), and every handler is put back as it was.
  """

  def __init__(self):
    self.received = 0
    self._previous = {}

  def __enter__(self) -> _TermFlag:
    if threading.current_thread() is threading.main_thread():
      for signum in _STOP_SIGNALS:
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


def checkpointer_for(stage_directory: str, **kwargs) -> Checkpointer:
  return Checkpointer(os.path.join(stage_directory, 'checkpoints'), **kwargs)


def abstract_train_state(init_params: Callable[[jax.Array], Any],
                         stage_config: ml_collections.ConfigDict,
                         mesh: Mesh) -> TrainState:
  """Shapes (replicated) of the stage's TrainState, for restoring."""
  optimizer, _ = optim.make_optimizer(stage_config)
  shapes = jax.eval_shape(
      lambda: TrainState.create(init_params(jax.random.key(0)), optimizer))
  return abstract_like(shapes, sharding.replicated_sharding(mesh))


def jit_update(stage: Stage, mesh: Mesh,
               optimizer: optax.GradientTransformation, seed: int
               ) -> Callable[..., tuple[TrainState, dict[str, jax.Array]]]:
  """The jitted update `fit` runs: (state, global batch, frozen params) ->
  (state, metrics), batch split on 'data', the rest replicated, the state
  donated. benchmarks/tpu_compile.py compiles this same function."""
  replicated = sharding.replicated_sharding(mesh)
  return jax.jit(
      functools.partial(train_step, loss_fn=stage.loss_fn,
                        optimizer=optimizer, seed=seed),
      in_shardings=(replicated, sharding.batch_sharding(mesh), replicated),
      out_shardings=(replicated, replicated),
      donate_argnums=(0,))


def fit(stage: Stage, *, mesh: Mesh, seed: int) -> TrainState:
  """Trains `stage` to `config.num_train_steps`, resuming if possible."""
  config = stage.config
  num_steps = config.num_train_steps
  is_lead_host = jax.process_index() == 0
  replicated = sharding.replicated_sharding(mesh)
  optimizer, schedule = optim.make_optimizer(config)

  checkpointer = checkpointer_for(stage.directory)
  if checkpointer.latest_step() is not None:
    state = checkpointer.restore(
        abstract_train_state(stage.init_params, config, mesh))
    logger.info('%s: resumed from step %d', stage.name, int(state.step))
  else:
    init_rng = jax.random.key(seed)
    state = jax.jit(
        lambda: TrainState.create(stage.init_params(init_rng), optimizer),
        out_shardings=replicated)()
  start_step = int(state.step)
  if start_step >= num_steps:
    logger.info('%s: already trained (%d steps)', stage.name, start_step)
    checkpointer.close()
    return state

  num_params = sum(x.size for x in jax.tree.leaves(state.params))
  logger.info('%s: %s parameters, training steps %d -> %d on %d devices',
               stage.name, f'{num_params:,}', start_step, num_steps,
               mesh.devices.size)
  if jax.process_count() > 1:
    sharding.check_host_rows(mesh)
  update = jit_update(stage, mesh, optimizer, seed)
  stop_check_every = config.stop_check_every
  frozen_params = sharding.replicate(stage.frozen_params, mesh)

  log_path = os.path.join(stage.directory, 'train_log.jsonl')
  summaries = Summaries(stage.directory, stage.logging, is_lead_host)
  # The next batches go to the devices while the current step runs.
  batches = sharding.prefetch_to_device(stage.batches(start_step), mesh,
                                        size=DEVICE_PREFETCH)
  last_log_time, last_log_step = time.time(), start_step
  failed = False
  try:
    with tqdm.tqdm(total=num_steps, initial=start_step, desc=stage.name,
                   disable=not is_lead_host, dynamic_ncols=True) as progress, \
         _TermFlag() as term:
      for step in range(start_step, num_steps):
        host_batch, batch = next(batches)
        state, metrics = update(state, batch, frozen_params)
        progress.update(1)
        done = step + 1
        stop_signal, signalled = _stop_signal(term, done, num_steps,
                                              stop_check_every)
        preempted = stop_signal != 0
        should_save = (done % config.checkpoint_every == 0
                       or done == num_steps or preempted)
        should_log = done % config.log_every == 0 or done == num_steps
        if should_log or should_save:
          metrics = {k: float(v) for k, v in sharding.to_host(metrics).items()}
          # Never checkpoint a diverged state: the loss is the one before
          # the update, param_norm is of the updated parameters.
          if not (math.isfinite(metrics['loss'])
                  and math.isfinite(metrics['param_norm'])):
            failed = True
            raise _diverged(stage.name, metrics, done, checkpointer)
        if should_log:
          now = time.time()
          metrics['learning_rate'] = float(schedule(step))
          metrics['steps_per_second'] = (done - last_log_step) / max(
              now - last_log_time, 1e-9)
          last_log_time, last_log_step = now, done
          progress.set_postfix(loss=f'{metrics["loss"]:.4g}')
          logger.info('%s step %d: %s', stage.name, done, ', '.join(
              f'{k}={v:.4g}' for k, v in sorted(metrics.items())))
          if is_lead_host:
            append_line_atomic(log_path, json.dumps({'step': done, **metrics}))
          summaries.scalars(done, metrics)
        if stage.images is not None and summaries.wants_images(done):
          summaries.images(done, stage.images(
              _host_copy(state.params), host_batch))
        if should_save:
          failed = True  # until the save is handed over without error
          checkpointer.save(done, state, force=done == num_steps or preempted)
          failed = False
        if preempted:
          checkpointer.wait_until_finished()
          by = signal.Signals(stop_signal).name
          if jax.process_count() > 1:
            by += ' to process ' + ', '.join(map(str, signalled))
          raise Preempted(
              f'{stage.name}: stopped by {by} after step {done}; its '
              'checkpoint is saved. Re-run the same command to resume.',
              stop_signal)
  finally:
    # Stops the reader (its thread or worker processes) at once.
    batches.close()
    # Also on an exception or Ctrl-C: finish the save in flight so the next
    # run resumes from it (after a failed save, report that one failure).
    try:
      checkpointer.wait_until_finished()
    except Exception as error:  # pylint: disable=broad-except
      if not failed:
        raise UserError(
            f'{stage.name}: saving a checkpoint to {checkpointer.directory} '
            f'failed ({type(error).__name__}: '
            f'{str(error).strip().splitlines()[0][:300] if str(error).strip() else ""}).'
            ' Free disk space and re-run: it resumes from the last saved '
            f'step ({checkpointer.last_saved_step()}).') from None
    finally:
      checkpointer.close()
      summaries.close()
  return state


def _host_copy(params: Any) -> Any:
  """This host's copy of replicated parameters, as numpy (no collective)."""
  return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), params)


def agrees_after(done: int, num_steps: int, every: int) -> bool:
  """Whether several processes agree on a stop after update `done` (1-based):
  every `every` updates and after the last one."""
  return done % every == 0 or done == num_steps


def _stop_signal(term: _TermFlag, done: int, num_steps: int,
                 every: int = 1) -> tuple[int, list[int]]:
  """(signal to save and stop on after update `done` or 0, the processes
  that received it). Several processes must agree on the step: each notes
  its own signals, and an all-gather after the updates of `agrees_after`
  (every process calls it after the same one) makes the answer the same
  everywhere; between them a signal waits, since a collective per step is a
  host sync per step on an accelerator. One process acts on its own signal
  at once. Not orbax's preemption sync: it relies on jax's own SIGTERM
  handler, which ours replaces."""
  if jax.process_count() > 1:
    if not agrees_after(done, num_steps, every):
      return 0, []
    return processes.agreed_signal(term.received)
  return term.received, [jax.process_index()] if term.received else []


def _diverged(name: str, metrics: dict[str, float], step: int,
              checkpointer: Checkpointer) -> Diverged:
  checkpointer.wait_until_finished()
  steps = checkpointer.all_steps()
  if steps:
    resume = (f'the last good checkpoint is step {steps[-1]} (saved before '
              'any non-finite value); re-running resumes from it and, with '
              'the same settings, diverges again.')
  else:
    resume = 'there is no checkpoint yet.'
  if not math.isfinite(metrics['loss']):
    # Which term of the loss (recon_loss, kl, slot_loss, image_loss, ...).
    terms = sorted(k for k, v in metrics.items() if not math.isfinite(v)
                   and k not in ('loss', 'grad_norm', 'param_norm'))
    what = (f'the loss became {metrics["loss"]} at step {step}'
            + (f' (non-finite: {", ".join(terms)})' if terms else ''))
  else:
    what = (f'the parameters became non-finite in update {step} (norm '
            f'{metrics["param_norm"]}, loss before it {metrics["loss"]:.4g})')
  return Diverged(
      f'{name}: {what}; nothing non-finite was saved and {resume} Lower the '
      'learning rate (a new --workdir, or --allow_config_change) or check '
      'the data.')
