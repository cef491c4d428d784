"""The training loop, one program read top to bottom.

`fit(stage, mesh=..., seed=...)` trains one model: its `Program`
(`one_seed`: the state replicated, the batch split on 'data', the update
jitted with the state donated) -> restore the newest checkpoint or
initialise -> loop: the next batch (already on the devices) -> update -> at
log and save steps fetch the metrics, stopping on a non-finite one -> log ->
pictures -> save -> stop on a signal. Re-running resumes from the newest
checkpoint and the data stream at the same step (batches are a function of
the step). `train(stage, program)` is the same loop for another program:
the K-seed wrapper hands it K models stacked into one state, their step,
their batches and their per-model checks and log lines.

Failures stop the loop at once with one line: a non-finite loss or updated
state (never saved; the message names the last good checkpoint), a failed
checkpoint save. SIGTERM / SIGINT save the current step and raise
`runtime.preemption.Preempted`; the rerun resumes bit-exact.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import dataclasses
import functools
import logging
import math
import os
from typing import Any
import warnings

import jax
from jax.sharding import Mesh
from jax.sharding import NamedSharding
import ml_collections
import numpy as np
import optax

from slotformer_jax.errors import brief
from slotformer_jax.errors import UserError
from slotformer_jax.runtime import sharding
from slotformer_jax.runtime.checkpoint import Checkpointer
from slotformer_jax.runtime.checkpoint import CheckpointSaveError
from slotformer_jax.runtime.checkpoint import abstract_like
from slotformer_jax.runtime.in_flight import StepsInFlight
from slotformer_jax.runtime.preemption import Preemption
from slotformer_jax.train import optim
from slotformer_jax.train.metrics_writer import Line
from slotformer_jax.train.metrics_writer import MetricsWriter
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.steps import LossFn
from slotformer_jax.train.steps import train_step

logger = logging.getLogger(__name__)

# XLA:CPU cannot reuse donated buffers and says so on every call.
warnings.filterwarnings('ignore', message='Some donated buffers were not usable')

# Batches handed to the devices ahead of the step that uses them
# (`sharding.prefetch_to_device`): the one of the next step while this one
# runs, and one more to absorb an uneven reader.
DEVICE_PREFETCH = 2

HostBatch = dict[str, np.ndarray]


class Diverged(UserError, FloatingPointError):
  """The loss or the updated parameters became non-finite."""


@dataclasses.dataclass(frozen=True)
class Stage:
  """What one trained model is: its loss, initialisation, data, optimiser.

  Attributes:
    name: its name in the log ('savi', 'slotformer', ...).
    directory: where checkpoints/ and train_log.jsonl go.
    config: its section: batch_size, num_train_steps, log_every,
      checkpoint_every, stop_check_every and the schedule's fields
      (config/defaults.py, `optim.make_optimizer`).
    loss_fn: (params, batch, frozen_params, rng) -> (loss, metrics).
    init_params: rng -> params.
    batches: start_step -> iterator of this host's batches.
    frozen_params: parameters used but not trained (SAVi's decoder in L_I).
    logging: the root config's `logging` section (TensorBoard; None: off).
    images: (params on the host, this step's host batch) -> {name: uint8
      [H, W, 3] labelled picture}, written to TensorBoard every
      `logging.image_every` steps; None: scalars only.
    optimizer: (transformation, its learning-rate schedule); None:
      `optim.make_optimizer(config)`.
    rng_stream: None: update t draws with fold_in(key(seed), t); n: with
      fold_in(fold_in(key(seed), n), t) (the readout heads' dropout).
    after_update: (step, params, metrics on the devices) -> None, called
      after every update (the readouts score an epoch on validation).
  """

  name: str
  directory: str
  config: ml_collections.ConfigDict
  loss_fn: LossFn
  init_params: Callable[[jax.Array], Any]
  batches: Callable[[int], Iterator[HostBatch]]
  frozen_params: Any = None
  logging: ml_collections.ConfigDict | None = None
  images: Callable[[Any, HostBatch], dict[str, np.ndarray]] | None = None
  optimizer: tuple[optax.GradientTransformation, optax.Schedule] | None = None
  rng_stream: int | None = None
  after_update: Callable[[int, Any, dict[str, jax.Array]], None] | None = None

  def optimizer_and_schedule(
      self) -> tuple[optax.GradientTransformation, optax.Schedule]:
    if self.optimizer is not None:
      return self.optimizer
    return optim.make_optimizer(self.config)


@dataclasses.dataclass(frozen=True)
class Program:
  """How `train` runs a stage on its devices: `one_seed` (one model), or
  K models in one program (the K-seed wrapper).

  Attributes:
    mesh: its devices.
    init: () -> the initial state, placed.
    abstract_state: () -> the state's shapes and placement (what a
      checkpoint is restored into).
    update: jitted (state, global batch, frozen params) -> (state,
      metrics), the state donated.
    batches: start_step -> this host's batches.
    batch_sharding: where a host batch goes (`sharding.to_global_batch`).
    frozen_params: the stage's frozen parameters, placed on
      `frozen_sharding` by `train`.
    lines: (metrics on the host, step, checkpointer) -> that step's log
      lines (`metrics_writer.Line`); raises `Diverged` on a non-finite
      value, before anything non-finite is saved.
    pictures: (params on the host, host batch) -> what `Stage.images`
      draws.
    copies: the models trained at once (the parameter count is per model).
    describe: what the start line adds after the devices.
    check_resume: (whether checkpoints exist) -> None, before a restore:
      raises when they were trained as another program.
  """

  mesh: Mesh
  init: Callable[[], Any]
  abstract_state: Callable[[], Any]
  update: Callable[..., tuple[Any, dict[str, jax.Array]]]
  batches: Callable[[int], Iterator[HostBatch]]
  batch_sharding: NamedSharding
  frozen_params: Any
  frozen_sharding: NamedSharding
  lines: Callable[[dict[str, np.ndarray], int, Checkpointer],
                  Sequence[Line]]
  pictures: Callable[[Any, HostBatch], tuple[Any, HostBatch]] = (
      lambda params, batch: (params, batch))
  copies: int = 1
  describe: str = ''
  check_resume: Callable[[bool], None] = lambda resuming: None


def fit(stage: Stage, *, mesh: Mesh, seed: int) -> TrainState:
  """Trains one model of `stage` on `mesh` to `config.num_train_steps`,
  resuming if possible; `seed` draws its initialisation and step RNG."""
  return train(stage, one_seed(stage, mesh, seed))


def train(stage: Stage, program: Program) -> Any:
  """Trains `stage` with `program` to `config.num_train_steps`, resuming
  from its newest checkpoint; returns the state."""
  config, name, mesh = stage.config, stage.name, program.mesh
  num_steps = config.num_train_steps
  _, schedule = stage.optimizer_and_schedule()
  checkpointer = checkpointer_for(stage.directory)
  resuming = checkpointer.latest_step() is not None
  program.check_resume(resuming)
  state = (checkpointer.restore(program.abstract_state()) if resuming
           else program.init())
  start_step = step_of(state)
  if resuming:
    logger.info('%s: resumed from step %d', name, start_step)
  if start_step >= num_steps:
    logger.info('%s: already trained (%d steps)', name, start_step)
    checkpointer.close()
    return state
  num_params = sum(x.size for x in jax.tree.leaves(state.params))
  logger.info('%s: %s parameters, training steps %d -> %d on %d devices%s',
              name, f'{num_params // program.copies:,}', start_step,
              num_steps, mesh.devices.size, program.describe)
  if jax.process_count() > 1:
    sharding.check_host_rows(mesh)
  frozen_params = jax.device_put(program.frozen_params,
                                 program.frozen_sharding)
  # The next batches go to the devices while the current step runs.
  batches = sharding.prefetch_to_device(
      program.batches(start_step), mesh, size=DEVICE_PREFETCH,
      sharding=program.batch_sharding)
  in_flight = StepsInFlight()
  # Preemption first: a signal while the last step is saved, logged or the
  # reader closed is still noted, and stops the run once it is saved.
  with Preemption(num_steps, config.stop_check_every,
                  name=name) as preemption, \
       _Finishing(name, checkpointer, batches), \
       MetricsWriter(name, stage.directory, stage.logging,
                     start_step=start_step, num_steps=num_steps) as writer:
    for step in range(start_step, num_steps):
      host_batch, batch = next(batches)
      if step == start_step:  # otherwise minutes without a line on a CPU
        logger.info('%s: compiling the update step (the first step takes '
                    'longer)', name)
      state, metrics = program.update(state, batch, frozen_params)
      # A signal is then acted on with at most MAX_STEPS_AHEAD updates
      # left to compute, not every update the host had queued.
      in_flight.dispatched(metrics)
      writer.advance()
      done = step + 1
      stop = preemption.stops_after(done)
      log = done % config.log_every == 0 or done == num_steps
      save = done % config.checkpoint_every == 0 or done == num_steps or stop
      if log or save:  # checked before anything is saved
        lines = _lines_after(program, metrics, done, checkpointer,
                             resumed_from=start_step if resuming else None)
        resuming = False  # one check has passed since the resume
      if log:
        writer.write(done, lines, float(schedule(step)))
      if stage.images is not None and writer.wants_images(done):
        writer.images(done, stage.images(*program.pictures(
            host_copy(state.params), host_batch)))
      if stage.after_update is not None:
        stage.after_update(done, state.params, metrics)
      if save:
        checkpointer.save(done, state, force=done == num_steps or stop)
      if stop:
        checkpointer.wait_until_finished()
        raise preemption.stopped(name, done)
  return state


def one_seed(stage: Stage, mesh: Mesh, seed: int) -> Program:
  """One model of `stage` on `mesh` (state replicated, batch split on
  'data'); `seed` draws its initialisation and step RNG."""
  optimizer, _ = stage.optimizer_and_schedule()
  replicated = sharding.replicated_sharding(mesh)
  init_rng = jax.random.key(seed)

  def init() -> TrainState:
    return TrainState.create(stage.init_params(init_rng), optimizer)

  return Program(
      mesh=mesh, init=jax.jit(init, out_shardings=replicated),
      abstract_state=lambda: abstract_like(jax.eval_shape(init), replicated),
      update=jit_update(stage, mesh, optimizer, seed),
      batches=stage.batches, batch_sharding=sharding.batch_sharding(mesh),
      frozen_params=stage.frozen_params, frozen_sharding=replicated,
      lines=functools.partial(_checked_lines, stage.name))


def jit_update(stage: Stage, mesh: Mesh,
               optimizer: optax.GradientTransformation, seed: int
               ) -> Callable[..., tuple[TrainState, dict[str, jax.Array]]]:
  """The one-model update `fit` runs: (state, global batch, frozen params)
  -> (state, metrics), batch split on 'data', the rest replicated, the
  state donated. benchmarks/tpu_compile.py compiles this same function."""
  replicated = sharding.replicated_sharding(mesh)
  return jax.jit(
      functools.partial(train_step, loss_fn=stage.loss_fn,
                        optimizer=optimizer, seed=seed,
                        rng_stream=stage.rng_stream),
      in_shardings=(replicated, sharding.batch_sharding(mesh), replicated),
      out_shardings=(replicated, replicated),
      donate_argnums=(0,))


def _lines_after(program: Program, metrics: dict[str, jax.Array], done: int,
                 checkpointer: Checkpointer, resumed_from: int | None
                 ) -> Sequence[Line]:
  """`program.lines` of update `done`; a divergence at the first check
  after resuming from step `resumed_from` names that checkpoint as a
  suspect (a step restored unchecked, or damaged, diverges at once)."""
  try:
    return program.lines(sharding.to_host(metrics), done, checkpointer)
  except Diverged as error:
    if resumed_from is None:
      raise
    raise Diverged(
        f'{error} It came right after resuming from step {resumed_from}, '
        'so that checkpoint is a suspect too: move '
        f'{os.path.join(checkpointer.directory, str(resumed_from))} out of '
        'the folder and re-run to resume from the step before it.'
    ) from None


def _checked_lines(name: str, metrics: dict[str, np.ndarray], step: int,
                   checkpointer: Checkpointer) -> list[Line]:
  """The one line of a step's metrics; `Diverged` when the loss (the one
  before the update) or param_norm (of the updated parameters) is not
  finite."""
  metrics = {k: float(v) for k, v in metrics.items()}
  if not (math.isfinite(metrics['loss'])
          and math.isfinite(metrics['param_norm'])):
    raise _diverged(name, metrics, step, checkpointer)
  return [({}, metrics)]


class _Finishing:
  """Leaving the loop, also on an error or Ctrl-C: stops the reader (its
  thread or worker processes) at once, finishes the save in flight so that
  the next run resumes from it, closes the checkpoints. A failed save is
  then the error, unless the loop stopped on a failed save or a divergence
  already (that one error is reported)."""

  def __init__(self, name: str, checkpointer: Checkpointer,
               batches: Iterator[Any]):
    self.name = name
    self.checkpointer = checkpointer
    self.batches = batches

  def __enter__(self) -> _Finishing:
    return self

  def __exit__(self, kind, error, traceback) -> None:
    self.batches.close()
    try:
      self.checkpointer.wait_until_finished()
    except Exception as save_error:  # pylint: disable=broad-except
      if not isinstance(error, (CheckpointSaveError, Diverged)):
        raise UserError(
            f'{self.name}: saving a checkpoint to '
            f'{self.checkpointer.directory} failed ({brief(save_error)}).'
            ' Free disk space and re-run: it resumes from the last saved '
            f'step ({self.checkpointer.last_saved_step()}).') from None
    finally:
      self.checkpointer.close()


def checkpointer_for(stage_directory: str, **kwargs) -> Checkpointer:
  return Checkpointer(os.path.join(stage_directory, 'checkpoints'), **kwargs)


def abstract_train_state(init_params: Callable[[jax.Array], Any],
                         stage_config: ml_collections.ConfigDict,
                         mesh: Mesh) -> TrainState:
  """Shapes (replicated on `mesh`) of a stage's TrainState, for restoring."""
  optimizer, _ = optim.make_optimizer(stage_config)
  shapes = jax.eval_shape(
      lambda: TrainState.create(init_params(jax.random.key(0)), optimizer))
  return abstract_like(shapes, sharding.replicated_sharding(mesh))


def step_of(state: TrainState) -> int:
  """The step of a state (of the first model when it stacks several: they
  share it), read from this host's first shard: no collective."""
  return int(np.asarray(state.step.addressable_data(0)).reshape(-1)[0])


def host_copy(params: Any) -> Any:
  """This host's copy of replicated parameters, as numpy (no collective)."""
  return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), params)


def _diverged(name: str, metrics: dict[str, float], step: int,
             checkpointer: Checkpointer) -> Diverged:
  """The one line of a model whose loss or parameters became non-finite
  in update `step`; it names the last (good) checkpoint."""
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
