"""Several seeds trained at once, in one program: the one place that turns
the one-model program (`trainer.one_seed`) into a K-seed one.

K TrainStates stacked on a leading axis (`SeedsState`) and one jitted step
that runs the K one-seed steps (`seeds_train_step`), vmapped on a (seed,
data) mesh when the devices allow (`seed_mesh`), checkpointed and resumed
as one state; each seed's divergence is checked, and its metrics logged, on
its own line.
Seed s draws what a one-seed run with seed s draws: its initialisation and
step RNG. Its data: the stream of one `Stage` every seed shares, or its own
`Stage` (its own data or order, and frozen parameters), stacked [K, ...].
Seed k of a K-seed run trains as the one-seed run with seed k (to float32
rounding: the batched program may round differently). `fit` of one seed is
the one-seed program.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
import dataclasses
import functools
import logging
import os
from typing import Any

from flax import struct
import jax
import jax.numpy as jnp
from jax.sharding import Mesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec
import ml_collections
import numpy as np
import optax

from slotformer_jax.config.sections import several_seeds
from slotformer_jax.errors import ConfigError
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic
from slotformer_jax.modules import platform
from slotformer_jax.runtime import sharding
from slotformer_jax.runtime.checkpoint import Checkpointer
from slotformer_jax.runtime.checkpoint import abstract_like
from slotformer_jax.train import trainer
from slotformer_jax.train.metrics_writer import Line
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.steps import Batch
from slotformer_jax.train.steps import LossFn
from slotformer_jax.train.steps import Metrics
from slotformer_jax.train.steps import train_step
from slotformer_jax.train.trainer import Diverged
from slotformer_jax.train.trainer import Stage

logger = logging.getLogger(__name__)

SEED_AXIS = 'seed'
DATA_ORDERS = ('shared', 'per_seed')
ON_DIVERGENCE = ('stop', 'continue')
SEED_LOOPS = ('auto', 'vmap', 'unroll')
SEEDS_FILE = 'seeds.json'


@dataclasses.dataclass(frozen=True)
class Seeds:
  """The seeds of a training stage (config.seeds and its choices).

  Attributes:
    values: the seeds, distinct ints; seed k's state is index k of the
      stacked state. One value: the one-seed program.
    data_order: 'shared' (every seed reads the batches of the one-seed
      run's order) or 'per_seed' (each seed draws its own order).
    on_divergence: a seed whose loss or parameters become non-finite:
      'stop' the run (nothing non-finite saved), or 'continue' with the
      others (the seed keeps its last finite state and is named once).
    seed_axis: split the stacked state of the vmapped loop on a 'seed'
      mesh axis beside 'data' when the devices allow (`seed_mesh`: each
      process's devices split into K groups, e.g. 4 seeds x 2 data on 8
      devices); otherwise, with False, or unrolled, the seeds are
      replicated on every device and only the batch is split.
    loop: how the program runs the K steps (`seeds_train_step`): 'vmap'
      (one batched step), 'unroll' (the one-seed step written K times into
      the program) or 'auto': 'unroll' on CPU (the one-seed kernels, faster
      there; and XLA:CPU partitions some vmapped convolutions split over
      devices wrongly, `loop_on`), 'vmap' on accelerators.
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

  @classmethod
  def of_config(cls, config: ml_collections.ConfigDict) -> Seeds:
    """The run's seeds: config.seeds when it names several, else
    config.seed."""
    return cls(several_seeds(config) or (config.seed,),
               data_order=config.seed_data_order,
               on_divergence=config.on_seed_divergence,
               seed_axis=config.seed_axis, loop=config.seed_loop)

  def map(self, seed_of: Callable[[int], int]) -> Seeds:
    """These seeds as a stage draws with them (e.g. seed + 1: the
    dynamics' own stream)."""
    return dataclasses.replace(self, values=tuple(map(seed_of, self.values)))

  def loop_on(self, mesh: Mesh) -> str:
    """'vmap' or 'unroll' for a program on `mesh` (see `loop`). A program
    for an accelerator always batches the seeds unless told 'unroll'.

    On CPU 'auto' unrolls, also on several devices (the seeds then
    replicated, `program`): vmapped and split, XLA:CPU (jaxlib 0.10.2)
    turns the dVAE's 1x1 output convolution into a grouped convolution it
    then partitions into an invalid one (3 output features for 2 groups:
    the first step fails), and the transposed convolution of SAVi's decoder
    computes another loss unless its accelerator form is used
    (`seeds_update`)."""
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


def fit(stages: Sequence[Stage], *, mesh: Mesh, seeds: Seeds) -> Any:
  """Trains `seeds` in one program, resumably: `stages` holds one Stage per
  seed (its data and frozen parameters, stacked), or one every seed shares.
  Returns the TrainState of one seed, else the SeedsState (seed k's:
  `.seed(k)`). Resuming with other seeds is one line (`check_seeds_file`).
  """
  if len(stages) not in (1, len(seeds.values)):
    raise ValueError(f'{len(stages)} stages for {len(seeds.values)} seeds: '
                     'one stage or one per seed')
  stage = stages[0]
  built = (program(stages, mesh, seeds) if seeds.several
           else trainer.one_seed(stage, mesh, seeds.values[0]))
  return trainer.train(stage, dataclasses.replace(
      built, check_resume=functools.partial(check_seeds_file,
                                            stage.directory, seeds)))


def program(stages: Sequence[Stage], mesh: Mesh, seeds: Seeds
            ) -> trainer.Program:
  """The K-seed program of `stages` (see `fit`) on `mesh`, or, vmapped,
  on its (seed, data) form (`seed_mesh`, with `seeds.seed_axis`)."""
  stage = stages[0]
  count = len(seeds.values)
  loop = seeds.loop_on(mesh)
  # Only the vmapped loop splits the seeds: the unrolled one indexes seed
  # k's slice, which split XLA moves between the devices in every step
  # (docs/seeds.md, "Devices").
  if seeds.seed_axis and loop == 'vmap':
    mesh = seed_mesh(mesh, count)
  optimizer, _ = stage.optimizer_and_schedule()
  own_data = len(stages) > 1  # stacked [K, B, ...] batches
  replicated = sharding.replicated_sharding(mesh)
  stacked = seed_sharding(mesh)
  batched = (seed_batch_sharding(mesh) if own_data
             else sharding.batch_sharding(mesh))
  frozen_sharding = stacked if own_data else replicated
  frozen = stage.frozen_params
  if own_data and frozen is not None:
    frozen = jax.tree.map(lambda *xs: jnp.stack(xs),
                          *[s.frozen_params for s in stages])

  def init() -> SeedsState:
    # The one-seed initialiser in a loop over the seeds' keys: seed k draws
    # what the one-seed init with seed k draws, in one program compiled
    # once, not K times. A loop, not vmap: batched, flax's orthogonal
    # recurrent kernels (GRU, LSTM) take a batched QR, whose LAPACK kernel
    # (jaxlib 0.10.2) blocks XLA:CPU's thread pool waiting for work queued
    # on that same pool; with the program replicated on several CPU devices
    # every pool thread waited and the init hung (docs/seeds.md).
    keys = jax.vmap(jax.random.key)(jnp.asarray(seeds.values, jnp.int32))
    return SeedsState.from_stacked(jax.lax.map(
        lambda key: TrainState.create(stage.init_params(key), optimizer),
        keys))

  update = seeds_update(stage.loss_fn, optimizer, seeds.values, own_data,
                        split=SEED_AXIS in mesh.axis_names,
                        per_seed_frozen=own_data, loop=loop,
                        rng_stream=stage.rng_stream)
  return trainer.Program(
      mesh=mesh, init=jax.jit(init, out_shardings=stacked),
      abstract_state=lambda: abstract_state(stage.init_params, optimizer,
                                            mesh, count),
      update=jax.jit(update, in_shardings=(stacked, batched, frozen_sharding),
                     out_shardings=(stacked, replicated), donate_argnums=(0,),
                     compiler_options=compiler_options(mesh, loop)),
      batches=(functools.partial(_stacked_batches, stages) if own_data
               else stage.batches),
      batch_sharding=batched, frozen_params=frozen,
      frozen_sharding=frozen_sharding,
      lines=_SeedLines(stage.name, seeds),
      # The first seed's pictures.
      pictures=lambda params, batch: (
          jax.tree.map(lambda x: x[0], params),
          jax.tree.map(lambda x: x[0], batch) if own_data else batch),
      copies=count,
      describe=(f', seeds {list(seeds.values)} in one program (mesh '
                f'{dict(mesh.shape)}, {seeds.data_order} data order)'))


@struct.dataclass
class SeedsState(TrainState):
  """The TrainStates of K seeds stacked on a leading axis (step: int32 [K],
  every leaf of params / opt_state [K, ...]), checkpointed as one state.

  diverged_at: int32 [K]; 0 while seed k trains, else the update in which
  its loss or parameters became non-finite (its parameters and optimiser
  state stay those from before that update).
  """

  diverged_at: jax.Array

  @classmethod
  def from_stacked(cls, state: TrainState) -> SeedsState:
    """The SeedsState of a TrainState whose leaves are already [K, ...]."""
    return cls(step=state.step, params=state.params,
               opt_state=state.opt_state,
               diverged_at=jnp.zeros(state.step.shape, jnp.int32))

  @classmethod
  def stack(cls, states: list[TrainState]) -> SeedsState:
    return cls.from_stacked(
        jax.tree.map(lambda *xs: jnp.stack(xs), *states))

  def train_state(self) -> TrainState:
    """The stacked TrainState without `diverged_at`."""
    return TrainState(step=self.step, params=self.params,
                      opt_state=self.opt_state)

  def seed(self, index: int) -> TrainState:
    """Seed `index`'s TrainState (as the one-seed run would hold it)."""
    return jax.tree.map(lambda x: x[index], self.train_state())


def abstract_state(init_params: Callable[[jax.Array], Any],
                   optimizer: optax.GradientTransformation, mesh: Mesh,
                   count: int) -> SeedsState:
  """Shapes of the SeedsState of `count` seeds ([count, ...] leaves),
  placed as `program` places it on `mesh`, for restoring."""
  shapes = jax.eval_shape(
      lambda: TrainState.create(init_params(jax.random.key(0)), optimizer))
  stacked = jax.tree.map(
      lambda x: jax.ShapeDtypeStruct((count, *x.shape), x.dtype), shapes)
  return abstract_like(
      SeedsState(step=stacked.step, params=stacked.params,
                 opt_state=stacked.opt_state,
                 diverged_at=jax.ShapeDtypeStruct((count,), np.int32)),
      seed_sharding(mesh))


def seeds_train_step(state: SeedsState, batch: Batch, frozen_params: Any,
                     seeds: jax.Array, *, loss_fn: LossFn,
                     optimizer: optax.GradientTransformation,
                     per_seed_batches: bool = False,
                     per_seed_frozen: bool = False, loop: str = 'vmap',
                     rng_stream: int | None = None
                     ) -> tuple[SeedsState, Metrics]:
  """`train_step` of K seeds at once, in one program.

  `loop`: 'vmap' batches the K steps into one (wider kernels: what fills an
  accelerator); 'unroll' writes the one-seed step K times into the program
  (the one-seed kernels, what suits XLA:CPU; K times the compile time).
  `jax.lax.map` (a loop in the program) ran 2.8-5.4x slower than K
  one-seed steps on XLA:CPU, so it is not offered.

  Args:
    state: K TrainStates stacked ([K, ...] leaves).
    batch: one batch every seed sees ([B, ...]), or with `per_seed_batches`
      one per seed ([K, B, ...]).
    frozen_params: shared by every seed, or with `per_seed_frozen` one
      tree per seed ([K, ...] leaves; seed k's SlotFormer decodes L_I with
      stage-1 seed k's decoder).
    seeds: int32 [K]; seed k's step RNG is train_step's for seeds[k].

  Returns:
    (state, metrics [K] each). A seed whose loss or updated parameters are
    non-finite keeps its state from before the update, and `diverged_at`
    records the update (an already diverged seed stays as it is).
  """
  def one(train_state, seed, seed_batch, seed_frozen):
    return train_step(train_state, seed_batch, seed_frozen,
                      loss_fn=loss_fn, optimizer=optimizer, seed=seed,
                      rng_stream=rng_stream)

  def pick(tree, k, per_seed):
    return jax.tree.map(lambda x: x[k], tree) if per_seed else tree

  if loop == 'vmap':
    new, metrics = jax.vmap(one, in_axes=(
        0, 0, 0 if per_seed_batches else None,
        0 if per_seed_frozen else None)
    )(state.train_state(), seeds, batch, frozen_params)
  elif loop == 'unroll':
    stacked = state.train_state()
    outs = [one(pick(stacked, k, True), seeds[k],
                pick(batch, k, per_seed_batches),
                pick(frozen_params, k, per_seed_frozen))
            for k in range(seeds.shape[0])]
    new, metrics = jax.tree.map(lambda *xs: jnp.stack(xs), *outs)
  else:
    raise ValueError(f"loop must be 'vmap' or 'unroll', got {loop!r}")
  training = state.diverged_at == 0
  keep = training & jnp.isfinite(metrics['loss']) & jnp.isfinite(
      metrics['param_norm'])

  def select(updated, old):
    return jnp.where(keep.reshape((-1,) + (1,) * (updated.ndim - 1)),
                     updated, old)

  return SeedsState(
      step=new.step,
      params=jax.tree.map(select, new.params, state.params),
      opt_state=jax.tree.map(select, new.opt_state, state.opt_state),
      diverged_at=jnp.where(training & ~keep, new.step, state.diverged_at),
  ), metrics


def seeds_update(loss_fn: LossFn, optimizer: optax.GradientTransformation,
                 seeds: tuple[int, ...], per_seed_batches: bool = False,
                 split: bool = False, per_seed_frozen: bool = False,
                 loop: str = 'vmap', rng_stream: int | None = None
                 ) -> Callable[..., tuple[SeedsState, dict[str, jax.Array]]]:
  """The K-seed update as `program` jits it: (SeedsState, batch, frozen
  params) -> (SeedsState, metrics [K] with `diverged_at`); `split`: the
  state is split on a 'seed' mesh axis; `per_seed_frozen`: the frozen
  parameters are stacked [K, ...], one tree per seed; `loop`: 'vmap' or
  'unroll' (`seeds_train_step`)."""
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
          loop=loop, rng_stream=rng_stream)
    return state, dict(metrics, diverged_at=state.diverged_at)

  return update


# XLA:CPU (jaxlib 0.10.2) crashes (SIGSEGV) running the vmapped gradient of
# SAVi's loss when its YNNPACK reduce or elementwise fusions are on; with
# only the dot fusion (which the project's default flags leave on, see
# runtime/xla_flags.py) it runs. Set for the vmapped several-seed step only,
# so the one-seed program and the 'unroll' loop are compiled as before.
_CPU_SEEDS_OPTIONS = {
    'xla_cpu_experimental_ynn_fusion_type': 'LIBRARY_FUSION_TYPE_DOT'}


def compiler_options(mesh: Mesh, loop: str = 'vmap'
                     ) -> dict[str, str] | None:
  """The XLA options of the K-seed step with `loop` on `mesh`."""
  if mesh.devices.flat[0].platform == 'cpu' and loop == 'vmap':
    return dict(_CPU_SEEDS_OPTIONS)
  return None


def seed_mesh(mesh: Mesh, num_seeds: int,
              local_devices: int | None = None) -> Mesh:
  """`mesh`'s devices as a (seed, data) grid for training `num_seeds` seeds
  at once (e.g. 4 seeds x 2 data on 8 devices), or `mesh` itself (the seeds
  then replicated on every device, only the batch split) when there is one
  seed or the devices of a process do not split into `num_seeds` groups.

  The seeds of one 'data' row sit on one process (device [s, d] is device
  d * K + s of `mesh`), so each process still holds a contiguous block of
  batch rows (`sharding.check_host_rows`). `local_devices`: the devices of
  one process (default `jax.local_device_count()`; an ahead-of-time
  compile for a TPU slice from a CPU host passes the slice's own).
  """
  devices = mesh.devices.reshape(-1)
  if local_devices is None:
    local_devices = jax.local_device_count()
  if (num_seeds <= 1 or mesh.axis_names != (sharding.DATA_AXIS,)
      or local_devices % num_seeds
      or len(devices) % num_seeds):
    return mesh
  return Mesh(devices.reshape(-1, num_seeds).T,
              (SEED_AXIS, sharding.DATA_AXIS))


def seed_sharding(mesh: Mesh) -> NamedSharding:
  """A stacked [K, ...] tree split on 'seed' (replicated without one)."""
  if SEED_AXIS in mesh.axis_names:
    return NamedSharding(mesh, PartitionSpec(SEED_AXIS))
  return sharding.replicated_sharding(mesh)


def seed_batch_sharding(mesh: Mesh) -> NamedSharding:
  """A [K, B, ...] batch (one per seed): K on 'seed' (when the mesh has
  it), B on 'data'."""
  seed_axis = SEED_AXIS if SEED_AXIS in mesh.axis_names else None
  return NamedSharding(mesh, PartitionSpec(seed_axis, sharding.DATA_AXIS))


def check_seeds_file(directory: str, seeds: Seeds, resuming: bool) -> None:
  """Records the seeds of a several-seed stage in `seeds.json`; resuming
  with other seeds (or a one-seed checkpoint with several) is one line."""
  path = os.path.join(directory, SEEDS_FILE)
  current = seeds.plain() if seeds.several else None
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


def _stacked_batches(stages: Sequence[Stage], start_step: int
                     ) -> Iterator[dict[str, np.ndarray]]:
  """Seed k's batch (from `stages[k]`) at index k of [K, B, ...]."""
  streams = [stage.batches(start_step) for stage in stages]
  try:
    for batches in zip(*streams):
      yield jax.tree.map(lambda *xs: np.stack(xs), *batches)
  finally:
    for stream in streams:  # reader threads or worker processes
      close = getattr(stream, 'close', None)
      if close is not None:
        close()


class _SeedLines:
  """`Program.lines` of K seeds: one line per seed still training, after
  naming each newly diverged seed in one line: a warning ('continue'), or
  `Diverged` ('stop', or when no seed is left). Metrics: [K] each, with
  `diverged_at`."""

  def __init__(self, name: str, seeds: Seeds):
    self.name = name
    self.seeds = seeds
    self.reported: set[int] = set()  # diverged seeds already named

  def __call__(self, metrics: dict[str, np.ndarray], step: int,
               checkpointer: Checkpointer) -> list[Line]:
    del step
    metrics = dict(metrics)
    diverged_at = metrics.pop('diverged_at')
    values = self.seeds.values
    lines = []
    for index, seed in enumerate(values):
      update = int(diverged_at[index])
      if update and seed not in self.reported:
        self.reported.add(seed)
        lines.append(f'{self.name}: seed {seed} diverged in update {update} '
                     '(its loss or parameters became non-finite)')
    training = [i for i in range(len(values)) if not diverged_at[i]]
    if lines and (self.seeds.on_divergence == 'stop' or not training):
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
    return [({'seed': values[i]}, {k: float(v[i]) for k, v in metrics.items()})
            for i in training]
