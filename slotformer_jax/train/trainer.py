"""The training loop shared by both stages, readable top to bottom.

mesh -> optimiser -> restore or initialise the state -> jit the update step
-> loop: host batch -> global batch (placed on the devices one or two steps
ahead) -> update -> log / NaN check ->
checkpoint. Re-running resumes from the newest checkpoint, and the data
stream resumes at the same step (batches are a function of the step).

Several seeds (`Seeds`, config.seeds): K TrainStates stacked on a leading
axis (`SeedsState`) and one jitted step vmapped over it
(`steps.seeds_train_step`), on a (seed, data) mesh when the devices allow
(`sharding.seed_mesh`), checkpointed and resumed as one state. Seed s drives
what a one-seed run with `seed=s` draws from it: the initialisation and the
step RNG (dropout, slot noise, samples); the data order is the stage's own
stream, shared by every seed (the default), or `batches_for_seed(s, step)`
per seed. A stage whose seeds read their own data (SlotFormer seed k on the
slots of stage-1 seed k) gives `seed_batches` (and per-seed frozen
parameters): the seeds then always train on stacked batches. Seed k of a
K-seed run with a shared order trains as the one-seed run with seed k (to
float32 rounding: the vmapped program may round differently). With one seed, nothing of this is used: the step, the state
and its checkpoints are the one-seed ones.

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
import contextlib
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

from slotformer_jax.errors import brief
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import UserError
from slotformer_jax.files import append_line_atomic
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic
from slotformer_jax.modules import platform
from slotformer_jax.train import optim
from slotformer_jax.runtime import processes
from slotformer_jax.runtime import sharding
from slotformer_jax.runtime.checkpoint import Checkpointer
from slotformer_jax.runtime.checkpoint import abstract_like
from slotformer_jax.train.state import SeedsState
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.summaries import Summaries
from slotformer_jax.train.steps import LossFn
from slotformer_jax.train.steps import seeds_train_step
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
      `logging.image_every` steps; None: scalars only (several seeds: the
      first seed's pictures).
    batches_for_seed: (seed, start_step) -> iterator of this host's batches
      drawn with that seed; only for several seeds with a per-seed data
      order (None: the stage has no per-seed order).
    seed_batches: (index k of the seeds, start_step) -> iterator of this
      host's batches of seed k's own data, in the data order the stage was
      built for (SlotFormer seed k reads the slots of stage-1 seed k). Set:
      several seeds always train on stacked [K, B, ...] batches drawn from
      it, whatever `Seeds.data_order` (which the stage's builder applied);
      None: every seed reads the same data (`batches` / `batches_for_seed`).
    seed_frozen_params: `frozen_params` holds one tree per seed, stacked
      [K, ...] (SlotFormer seed k's L_I decoder is stage-1 seed k's);
      False: one tree shared by every seed. Several seeds only.
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
  batches_for_seed: Callable[[int, int],
                             Iterator[dict[str, np.ndarray]]] | None = None
  seed_batches: Callable[[int, int],
                         Iterator[dict[str, np.ndarray]]] | None = None
  seed_frozen_params: bool = False


DATA_ORDERS = ('shared', 'per_seed')
ON_DIVERGENCE = ('stop', 'continue')
SEED_LOOPS = ('auto', 'vmap', 'unroll')


@dataclasses.dataclass(frozen=True)
class Seeds:
  """K seeds trained in one program (config.seeds and its two choices).

  Attributes:
    values: the seeds, distinct ints; seed k's state is index k of the
      stacked state.
    data_order: 'shared' (every seed sees the stage's batches; the one-seed
      run's order) or 'per_seed' (`Stage.batches_for_seed`).
    on_divergence: a seed whose loss or parameters become non-finite:
      'stop' the run (nothing non-finite saved), or 'continue' with the
      others (the seed keeps its last finite state and is named once).
    seed_axis: split the stacked state on a 'seed' mesh axis beside
      'data' when the devices allow (`sharding.seed_mesh`: each process's
      devices split into K groups, e.g. 4 seeds x 2 data on 8 devices);
      otherwise, or with False, the seeds are replicated on every device
      and only the batch is split.
    loop: how the program runs the K steps (`steps.seeds_train_step`):
      'vmap' (one batched step), 'unroll' (the one-seed step written K times
      into the program) or 'auto': 'unroll' on CPU (the one-seed kernels,
      faster there; and XLA:CPU partitions some vmapped convolutions split
      over devices wrongly, `loop_on`), 'vmap' on accelerators.
  """

  values: tuple[int, ...]
  data_order: str = 'shared'
  on_divergence: str = 'stop'
  seed_axis: bool = True
  loop: str = 'auto'

  def __post_init__(self):
    if not self.values or len(set(self.values)) != len(self.values):
      raise ConfigError(f'seeds must be distinct ints, got {self.values}')
    if self.data_order not in DATA_ORDERS:
      raise ConfigError(f'seed data order {self.data_order!r}: one of '
                        f'{DATA_ORDERS}')
    if self.on_divergence not in ON_DIVERGENCE:
      raise ConfigError(f'on seed divergence {self.on_divergence!r}: one of '
                        f'{ON_DIVERGENCE}')
    if self.loop not in SEED_LOOPS:
      raise ConfigError(f'seed loop {self.loop!r}: one of {SEED_LOOPS}')

  def loop_on(self, mesh: Mesh) -> str:
    """'vmap' or 'unroll' for a program on `mesh` (see `loop`). A program
    for an accelerator always batches the seeds unless told 'unroll'.

    On CPU 'auto' unrolls, also with the seeds split on a 'seed' axis:
    vmapped and split, XLA:CPU (jaxlib 0.10.2) turns the dVAE's 1x1
    output convolution into a grouped convolution it then partitions into
    an invalid one (3 output features for 2 groups: the first step fails),
    and the transposed convolution of SAVi's decoder computes another loss
    unless its accelerator form is used (`seeds_update`)."""
    if self.loop != 'auto':
      return self.loop
    on_cpu = mesh.devices.flat[0].platform == 'cpu'
    return 'unroll' if on_cpu else 'vmap'

  @property
  def several(self) -> bool:
    return len(self.values) > 1

  def stream_seeds(self, shared: int) -> tuple[int, ...]:
    """Each seed's data-order seed: `shared` (the run's stream) for every
    seed, or each seed's own value ('per_seed')."""
    if self.data_order == 'per_seed':
      return self.values
    return (shared,) * len(self.values)

  def plain(self) -> dict[str, Any]:
    return {'seeds': list(self.values), 'data_order': self.data_order}


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
                         mesh: Mesh, num_seeds: int = 1) -> TrainState:
  """Shapes (replicated) of the stage's TrainState, for restoring; with
  several seeds those of the SeedsState ([num_seeds, ...] leaves, split on
  `mesh`'s 'seed' axis when it has one)."""
  optimizer, _ = optim.make_optimizer(stage_config)
  shapes = jax.eval_shape(
      lambda: TrainState.create(init_params(jax.random.key(0)), optimizer))
  if num_seeds == 1:
    return abstract_like(shapes, sharding.replicated_sharding(mesh))
  stacked = jax.tree.map(
      lambda x: jax.ShapeDtypeStruct((num_seeds, *x.shape), x.dtype), shapes)
  return abstract_like(
      SeedsState(step=stacked.step, params=stacked.params,
                 opt_state=stacked.opt_state,
                 diverged_at=jax.ShapeDtypeStruct((num_seeds,), np.int32)),
      sharding.seed_sharding(mesh))


def jit_update(stage: Stage, mesh: Mesh,
               optimizer: optax.GradientTransformation, seed: int,
               seeds: Seeds | None = None
               ) -> Callable[..., tuple[TrainState, dict[str, jax.Array]]]:
  """The jitted update `fit` runs: (state, global batch, frozen params) ->
  (state, metrics), batch split on 'data', the rest replicated, the state
  donated. benchmarks/tpu_compile.py compiles this same function.

  Several `seeds`: the SeedsState split on `mesh`'s 'seed' axis (when it
  has one), the step vmapped over it (`steps.seeds_train_step`), metrics
  [K] (with `diverged_at`) replicated; `seed` is then unused."""
  replicated = sharding.replicated_sharding(mesh)
  if seeds is None or not seeds.several:
    return jax.jit(
        functools.partial(train_step, loss_fn=stage.loss_fn,
                          optimizer=optimizer, seed=seed),
        in_shardings=(replicated, sharding.batch_sharding(mesh), replicated),
        out_shardings=(replicated, replicated),
        donate_argnums=(0,))
  per_seed = stacked_batches(stage, seeds)
  loop = seeds.loop_on(mesh)
  update = seeds_update(stage.loss_fn, optimizer, seeds.values, per_seed,
                        split=sharding.SEED_AXIS in mesh.axis_names,
                        per_seed_frozen=stage.seed_frozen_params, loop=loop)
  batch_sharding = (sharding.seed_batch_sharding(mesh) if per_seed
                    else sharding.batch_sharding(mesh))
  return jax.jit(
      update,
      in_shardings=(sharding.seed_sharding(mesh), batch_sharding,
                    frozen_sharding(stage, mesh, seeds)),
      out_shardings=(sharding.seed_sharding(mesh), replicated),
      donate_argnums=(0,),
      compiler_options=_seeds_compiler_options(mesh, loop))


def stacked_batches(stage: Stage, seeds: Seeds | None) -> bool:
  """Whether several `seeds` train on stacked [K, B, ...] batches: each
  seed reads its own data (`Stage.seed_batches`) or draws its own order."""
  return seeds is not None and seeds.several and (
      stage.seed_batches is not None or seeds.data_order == 'per_seed')


def frozen_sharding(stage: Stage, mesh: Mesh, seeds: Seeds | None):
  """The frozen parameters' placement: one tree per seed on the seed axis
  (`Stage.seed_frozen_params`), else replicated."""
  if seeds is not None and seeds.several and stage.seed_frozen_params:
    return sharding.seed_sharding(mesh)
  return sharding.replicated_sharding(mesh)


# XLA:CPU (jaxlib 0.10.2) crashes (SIGSEGV) running the vmapped gradient of
# SAVi's loss when its YNNPACK reduce or elementwise fusions are on; with
# only the dot fusion (which the project's default flags leave on, see
# runtime/xla_flags.py) it runs. Set for the vmapped several-seed step only,
# so the one-seed program and the 'unroll' loop are compiled as before.
_CPU_SEEDS_OPTIONS = {
    'xla_cpu_experimental_ynn_fusion_type': 'LIBRARY_FUSION_TYPE_DOT'}


def _seeds_compiler_options(mesh: Mesh, loop: str = 'vmap'
                            ) -> dict[str, str] | None:
  if mesh.devices.flat[0].platform == 'cpu' and loop == 'vmap':
    return dict(_CPU_SEEDS_OPTIONS)
  return None


def seeds_update(loss_fn: LossFn, optimizer: optax.GradientTransformation,
                 seeds: tuple[int, ...], per_seed_batches: bool = False,
                 split: bool = False, per_seed_frozen: bool = False,
                 loop: str = 'vmap'
                 ) -> Callable[..., tuple[SeedsState, dict[str, jax.Array]]]:
  """The several-seed update as `jit_update` jits it: (SeedsState, batch,
  frozen params) -> (SeedsState, metrics [K] with `diverged_at`); `split`:
  the state is split on a 'seed' mesh axis; `per_seed_frozen`: the frozen
  parameters are stacked [K, ...], one tree per seed; `loop`: 'vmap' or
  'unroll' (`steps.seeds_train_step`)."""
  values = np.asarray(seeds, np.int32)

  def update(state, batch, frozen_params):
    # Split on 'seed': the accelerator form of the transposed convolution
    # (modules/platform.py); its CPU form, vmapped over the seeds and split
    # over devices, computes another loss (0.479 vs 0.460 on the tiny SAVi
    # of tests/train/test_seeds.py). Unsplit the CPU form is right and on
    # CPU faster.
    with (platform.forms(platform.ACCELERATOR, (platform.CONV_TRANSPOSE,))
          if split and loop == 'vmap' else contextlib.nullcontext()):
      state, metrics = seeds_train_step(
          state, batch, frozen_params, jax.numpy.asarray(values),
          loss_fn=loss_fn, optimizer=optimizer,
          per_seed_batches=per_seed_batches, per_seed_frozen=per_seed_frozen,
          loop=loop)
    return state, dict(metrics, diverged_at=state.diverged_at)

  return update


def _init_state(stage: Stage, mesh: Mesh,
                optimizer: optax.GradientTransformation, seed: int,
                seeds: Seeds | None) -> TrainState:
  """The initial state: the one-seed program, or K of them in one program
  whose states are stacked (each seed's init as the one-seed run's)."""
  if seeds is None or not seeds.several:
    init_rng = jax.random.key(seed)
    return jax.jit(
        lambda: TrainState.create(stage.init_params(init_rng), optimizer),
        out_shardings=sharding.replicated_sharding(mesh))()
  return jax.jit(
      lambda: SeedsState.stack([
          TrainState.create(stage.init_params(jax.random.key(s)), optimizer)
          for s in seeds.values]),
      out_shardings=sharding.seed_sharding(mesh))()


_SEEDS_FILE = 'seeds.json'


def _check_seeds_file(directory: str, seeds: Seeds | None,
                      resuming: bool) -> None:
  """Records the seeds of a several-seed stage in `seeds.json`; resuming
  with other seeds (or a one-seed checkpoint with several) is one line."""
  path = os.path.join(directory, _SEEDS_FILE)
  current = seeds.plain() if seeds is not None and seeds.several else None
  saved = (read_json(path, fix=f'Delete {directory} to retrain.')
           if os.path.exists(path) else None)
  if resuming and saved != current:
    def name(entry):
      return 'one seed' if entry is None else (
          f'seeds {entry["seeds"]} ({entry["data_order"]} data order)')
    raise ConfigError(
        f'the checkpoints in {directory} were trained with {name(saved)}, '
        f'the config asks for {name(current)}; use a new --workdir (or the '
        'same seeds), or delete the folder to retrain.')
  if jax.process_index() == 0:
    if current is not None:
      os.makedirs(directory, exist_ok=True)
      write_json_atomic(path, current)
    elif saved is not None:  # a several-seed start with no checkpoint
      os.remove(path)


def _stacked_batches(seeds: Seeds, stage: Stage, start_step: int
                     ) -> Iterator[dict[str, np.ndarray]]:
  """Seed k's batch at index k of [K, B, ...]: from its own data
  (`Stage.seed_batches`), or drawn with seed k (per-seed data order)."""
  if stage.seed_batches is not None:
    streams = [stage.seed_batches(k, start_step)
               for k in range(len(seeds.values))]
  elif stage.batches_for_seed is None:
    raise ConfigError(f'{stage.name}: a per-seed data order is not '
                      'available for this stage; use the shared order')
  else:
    streams = [stage.batches_for_seed(s, start_step) for s in seeds.values]
  try:
    for batches in zip(*streams):
      yield jax.tree.map(lambda *xs: np.stack(xs), *batches)
  finally:
    for stream in streams:  # reader threads or worker processes
      close = getattr(stream, 'close', None)
      if close is not None:
        close()


def fit(stage: Stage, *, mesh: Mesh, seed: int,
        seeds: Seeds | None = None) -> TrainState:
  """Trains `stage` to `config.num_train_steps`, resuming if possible.

  `seeds` with several values: trains them at once and returns the
  SeedsState (seed k's TrainState: `.seed(k)`); with one value it is `seed`.
  """
  config = stage.config
  num_steps = config.num_train_steps
  is_lead_host = jax.process_index() == 0
  if seeds is not None and not seeds.several:
    seed, seeds = seeds.values[0], None
  num_seeds = len(seeds.values) if seeds is not None else 1
  if seeds is not None and seeds.seed_axis:
    mesh = sharding.seed_mesh(mesh, num_seeds)
  optimizer, schedule = optim.make_optimizer(config)

  checkpointer = checkpointer_for(stage.directory)
  resuming = checkpointer.latest_step() is not None
  _check_seeds_file(stage.directory, seeds, resuming)
  if resuming:
    state = checkpointer.restore(
        abstract_train_state(stage.init_params, config, mesh, num_seeds))
    logger.info('%s: resumed from step %d', stage.name, _step_of(state))
  else:
    state = _init_state(stage, mesh, optimizer, seed, seeds)
  start_step = _step_of(state)
  if start_step >= num_steps:
    logger.info('%s: already trained (%d steps)', stage.name, start_step)
    checkpointer.close()
    return state

  num_params = sum(x.size for x in jax.tree.leaves(state.params)
                   ) // num_seeds
  logger.info('%s: %s parameters, training steps %d -> %d on %d devices%s',
               stage.name, f'{num_params:,}', start_step, num_steps,
               mesh.devices.size,
               '' if seeds is None else
               f', seeds {list(seeds.values)} in one program (mesh '
               f'{dict(mesh.shape)}, {seeds.data_order} data order)')
  if jax.process_count() > 1:
    sharding.check_host_rows(mesh)
  update = (jit_update(stage, mesh, optimizer, seed) if seeds is None
            else jit_update(stage, mesh, optimizer, seed, seeds=seeds))
  per_seed = stacked_batches(stage, seeds)
  reported: set[int] = set()  # diverged seeds already named
  stop_check_every = config.stop_check_every
  frozen_params = jax.device_put(stage.frozen_params,
                                 frozen_sharding(stage, mesh, seeds))

  log_path = os.path.join(stage.directory, 'train_log.jsonl')
  summaries = Summaries(stage.directory, stage.logging, is_lead_host)
  # The next batches go to the devices while the current step runs.
  batches = sharding.prefetch_to_device(
      _stacked_batches(seeds, stage, start_step) if per_seed
      else stage.batches(start_step), mesh, size=DEVICE_PREFETCH,
      per_seed=per_seed)
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
        if (should_log or should_save) and seeds is None:
          metrics = {k: float(v) for k, v in sharding.to_host(metrics).items()}
          # Never checkpoint a diverged state: the loss is the one before
          # the update, param_norm is of the updated parameters.
          if not (math.isfinite(metrics['loss'])
                  and math.isfinite(metrics['param_norm'])):
            failed = True
            raise _diverged(stage.name, metrics, done, checkpointer)
          per_seed_metrics = {None: metrics}
        elif should_log or should_save:
          try:
            per_seed_metrics = _check_seeds(stage.name, seeds,
                                            sharding.to_host(metrics),
                                            reported, checkpointer)
          except Diverged:
            failed = True
            raise
        if should_log:
          now = time.time()
          shared = {'learning_rate': float(schedule(step)),
                    'steps_per_second': (done - last_log_step) / max(
                        now - last_log_time, 1e-9)}
          last_log_time, last_log_step = now, done
          for seed_value, metrics in per_seed_metrics.items():
            metrics.update(shared)
            label = ('' if seed_value is None else f' seed {seed_value}')
            progress.set_postfix(loss=f'{metrics["loss"]:.4g}')
            logger.info('%s%s step %d: %s', stage.name, label, done,
                        ', '.join(f'{k}={v:.4g}'
                                  for k, v in sorted(metrics.items())))
            seed_field = {} if seed_value is None else {'seed': seed_value}
            if is_lead_host:
              append_line_atomic(log_path, json.dumps(
                  {'step': done, **seed_field, **metrics}))
            summaries.scalars(done, metrics if seed_value is None else {
                f'{k}/seed_{seed_value}': v for k, v in metrics.items()})
        if stage.images is not None and summaries.wants_images(done):
          params = _host_copy(state.params)
          if seeds is not None:
            params = jax.tree.map(lambda x: x[0], params)
          summaries.images(done, stage.images(
              params, jax.tree.map(lambda x: x[0], host_batch)
              if per_seed else host_batch))
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
            f'failed ({brief(error)}).'
            ' Free disk space and re-run: it resumes from the last saved '
            f'step ({checkpointer.last_saved_step()}).') from None
    finally:
      checkpointer.close()
      summaries.close()
  return state


def _step_of(state: TrainState) -> int:
  """The step of a TrainState, or of a SeedsState (every seed's is the same;
  read from this host's first shard, no collective)."""
  return int(np.asarray(state.step.addressable_data(0)).reshape(-1)[0])


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


def _check_seeds(name: str, seeds: Seeds, metrics: dict[str, np.ndarray],
                 reported: set[int], checkpointer: Checkpointer
                 ) -> dict[int, dict[str, float]]:
  """{seed: its metrics} of the seeds still training, after naming each
  newly diverged seed in one line: a warning ('continue'), or `Diverged`
  ('stop', or when no seed is left).

  `metrics`: the vmapped step's ([K] each, with `diverged_at`).
  """
  diverged_at = metrics.pop('diverged_at')
  lines = []
  for index, seed in enumerate(seeds.values):
    update = int(diverged_at[index])
    if update and seed not in reported:
      reported.add(seed)
      lines.append(f'{name}: seed {seed} diverged in update {update} (its '
                   'loss or parameters became non-finite)')
  training = [i for i in range(len(seeds.values)) if not diverged_at[i]]
  if lines and (seeds.on_divergence == 'stop' or not training):
    checkpointer.wait_until_finished()
    steps = checkpointer.all_steps()
    resume = (f'the last checkpoint is step {steps[-1]}' if steps
              else 'there is no checkpoint yet')
    why = ('no seed is left' if not training else
           "config.on_seed_divergence='stop'; 'continue' goes on with the "
           'others')
    raise Diverged('; '.join(lines) + f'; stopped ({why}); nothing '
                   f'non-finite was saved and {resume}. Lower the learning '
                   'rate or check the data.')
  for line in lines:
    logger.warning('%s; it keeps its parameters from before that update, '
                   'the other seeds go on', line)
  return {seeds.values[i]: {k: float(v[i]) for k, v in metrics.items()}
          for i in training}


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
