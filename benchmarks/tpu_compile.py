r"""Compiles the project's real jitted steps for TPU slices, on a machine
without a TPU, and reports per chip what XLA:TPU says they need.

  pip install -e '.[tpu]'    # jax[tpu] at the installed jax: brings libtpu
  python benchmarks/tpu_compile.py [--topologies=v5e:2x4,v4:2x2x1,v5e:16x16]
      [--configs=obj3d,clevrer,phyre,physion] [--steps=savi,slotformer,...]
      [--dtypes=float32,bfloat16] [--largest_batch] [--seeds=1,4]
      [--json=out.json]

Each row is one ahead-of-time compile (`.lower(...).compile()` over the
compile-only devices of `jax.experimental.topologies`) of a step the
project runs, built by the project's own code:

  savi / dvae / steve  the stage-1 train step: the `Stage` of the slot
                       model's part (`stages.stage1.part_stage`), jitted by
                       `trainer.jit_update`
                       (what `trainer.fit` runs: batch on 'data', state and
                       frozen parameters replicated, the state donated);
  slotformer           the dynamics train step of `stages.dynamics.
                       dynamics_stage` (L_S + lambda L_I through the frozen
                       SAVi decoder where the config has lambda > 0), same
                       jit;
  eval_rollout         `evaluation.evaluate.make_rollout_evaluator`: the
                       SlotFormer rollout + decoding + per-step metrics of
                       one evaluation batch, without LPIPS (its VGG weights
                       are a download) and without the object metrics;
  aloe                 (clevrer: configs/clevrer_vqa.py) Aloe's train step,
                       the `Stage` of `stages.vqa.aloe_stage`, same jit, on
                       a stand-in vocabulary of STANDIN_WORDS question words
                       and CLEVRER's answers (the real one is read from the
                       questions at run time); the batch is built by
                       `tasks.vqa.QuestionBatches.batch` itself;
  readout              (physion: configs/physion_contact.py, phyre:
                       configs/phyre.py:planning; synthetic_contact:tiny and
                       synthetic_phyre:tiny too) the readout head's step
                       that `stages.readout_fit.fit_readout` runs through
                       the trainer (`trainer.jit_update` of its `Stage`), on
                       the 'rollout' condition's features (the longest). It
                       trains on one chip.

The global batch is the config's (the paper's). A slice whose chip count
does not divide it (a 256-chip pod slice and batch 64) compiles at one
sample per chip instead, and the row says so. Per chip: HBM = arguments +
outputs + temporaries - aliased (`memory_analysis()`) against the chip's
HBM, FLOPs and bytes accessed (`cost_analysis()`), the roofline floor
max(FLOPs / peak, bytes / HBM bandwidth) and the compile seconds.
`--largest_batch` also finds the largest per-chip batch that fits, by
compiles only: from the paper batch's row it grows the batch (a line
through the two largest batches that fit predicts the next) until one does
not fit, then bisects between the largest that fits and the smallest that
does not until they are within `--largest_batch_tolerance` (10 %) of each
other or `--largest_batch_compiles` (8) are spent. HBM is not monotonic in
the batch near the limit (XLA:TPU's layouts change), so the answer is "this
batch compiles within the chip's HBM and that one does not": a batch
between them may fit too.

`--seeds=K,...` (default 1) compiles each train step (savi, dvae, steve,
slotformer) once per K: K = 1 is the one-seed row above; K > 1 is the
program `train.seeds.fit` runs for `config.seeds` of K seeds
(`Seeds.of_config`, as the pipeline builds it: the default shared data
order, `seed_axis`, `seed_loop='auto'`, vmapped on a TPU): the update and
the abstract `SeedsState` of `train.seeds.program`, on `seeds.seed_mesh`
of the slice (4 seeds x 2 data on 8 chips; the seeds replicated on every
chip when a host's chips do not split into K groups). Stage 1's first
part (savi, dvae) reads the shared [B, ...] batch; STEVE and SlotFormer
train K one-seed stages, one per seed (`stages.fit.fit_chains`): stacked
[K, B, ...] batches (each seed its own tokens or slots) and, for
SlotFormer with L_I, [K, ...] frozen decoder parameters, both split on
'seed'. What the pipeline refuses with several seeds
(`stages.task.seeds_problems`) and what runs one seed at a time
(eval_rollout: each seed's one-seed program; aloe and readout take one
seed) is a 'not built' row. HBM, FLOPs and bytes
are per chip as above, for all K seeds; `floor_per_seed_seconds` = floor / K.
`seed_mesh` splits the seeds only when one host's chips split into K
groups; the host is the topology's (compile-only v5e:2x4: 2 processes of 4
chips), or `--host_chips=N` chips (a single 8-chip v5litepod-8 VM: 8).

Exit status 1 when a step does not fit its chip's HBM at the paper's batch
or does not compile.
Without libtpu it prints why and exits 0. jax itself runs on CPU
(JAX_PLATFORMS=cpu unless set); only the compile targets the TPU.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib.util
import os
import re
import sys
import time
from typing import Any

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..'))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'configs'))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

os.environ.setdefault('JAX_PLATFORMS', 'cpu')
# Compile-only: no chip is opened, so libtpu's one-process-per-host lock
# (/tmp/libtpu_lockfile) need not stop a second compile job.
os.environ.setdefault('ALLOW_MULTIPLE_LIBTPU_LOAD', '1')

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh  # noqa: E402
from jax.sharding import NamedSharding  # noqa: E402

from slotformer_jax import files  # noqa: E402
from slotformer_jax.stages import task as task_lib
from slotformer_jax import slot_models  # noqa: E402
from slotformer_jax import dynamics as dynamics_lib  # noqa: E402
from slotformer_jax.data import vqa as vqa_data  # noqa: E402
from slotformer_jax.evaluation import evaluate  # noqa: E402
from slotformer_jax.evaluation import rollout_metrics  # noqa: E402
from slotformer_jax.run import Run  # noqa: E402
from slotformer_jax.slot_models import chain  # noqa: E402
from slotformer_jax.stages import dynamics  # noqa: E402
from slotformer_jax.slot_models.steve import build_steve  # noqa: E402
from slotformer_jax.stages import readout_fit  # noqa: E402
from slotformer_jax.stages import stage1  # noqa: E402
from slotformer_jax.stages import vqa as vqa_stages  # noqa: E402
from slotformer_jax.tasks import contact  # noqa: E402
from slotformer_jax.tasks import phyre_planning  # noqa: E402
from slotformer_jax.tasks import phyre_rendered  # noqa: E402
from slotformer_jax.tasks import readout as readout_lib  # noqa: E402
from slotformer_jax.tasks import vqa as vqa_task  # noqa: E402
from slotformer_jax.train import optim  # noqa: E402
from slotformer_jax.train import seeds as seeds_lib  # noqa: E402
from slotformer_jax.runtime import precision  # noqa: E402
from slotformer_jax.runtime import sharding  # noqa: E402
from slotformer_jax.train import trainer  # noqa: E402
from slotformer_jax.train.state import TrainState  # noqa: E402
from tpu_chips import CHIPS  # noqa: E402  (the spec-sheet peaks)

SLOTFORMER = 'slotformer'  # the dynamics model's registered name

GiB = 2**30


# The config's stage section of each step's batch size.
SECTIONS = {'savi': 'savi', 'dvae': 'dvae', 'steve': 'steve',
            'slotformer': 'slotformer', 'eval_rollout': 'evaluation',
            'aloe': 'vqa', 'readout': 'readout'}
DEFAULT_CONFIGS = ('obj3d', 'clevrer', 'phyre', 'physion')
DEFAULT_STEPS = ('savi', 'dvae', 'steve', 'slotformer', 'eval_rollout',
                 'aloe', 'readout')
# The downstream step of a video config, and the config that runs it.
DOWNSTREAM = {'clevrer': ('aloe', 'clevrer_vqa'),
              'physion': ('readout', 'physion_contact'),
              'phyre': ('readout', 'phyre:planning'),
              'synthetic_vqa': ('aloe', 'synthetic_vqa'),
              'synthetic_contact:tiny': ('readout', 'synthetic_contact:tiny'),
              'synthetic_phyre:tiny': ('readout', 'synthetic_phyre:tiny')}
# Steps whose losses are not wrapped in `precision.with_compute_dtype`.
FLOAT32_ONLY = ('aloe', 'readout')
# Aloe's question vocabulary is read from the questions at run time; its
# size only changes the word-embedding table (STANDIN_WORDS x word_dim).
STANDIN_WORDS = 100
NOWHERE = '/nonexistent/tpu_compile'  # stages only name their directories


def libtpu_missing() -> str | None:
  if importlib.util.find_spec('libtpu') is None:
    return ("libtpu is not installed (pip install -e '.[tpu]' installs "
            f'jax[tpu]=={jax.__version__})')
  return None


def tpu_devices(topology: str) -> list:
  from jax.experimental import topologies  # pylint: disable=g-import-not-at-top
  kwargs = {}
  if topology.startswith('v4'):
    kwargs['chip_config_name'] = 'megacore'  # one device per chip
  return list(topologies.get_topology_desc(
      topology_name=topology, platform='tpu', **kwargs).devices)


def load_config(name: str):
  """configs/<file>.py's get_config(); 'file:variant' passes the variant."""
  file_name, _, variant = name.partition(':')
  module = importlib.import_module(file_name)
  return module.get_config(variant) if variant else module.get_config()


def steps_of(config, name: str = '') -> tuple[str, ...]:
  """The train / evaluation steps a config's pipeline runs (+ the
  downstream step of `name`, run by its DOWNSTREAM config)."""
  first = (('dvae', 'steve') if config.slot_model == 'steve' else ('savi',))
  downstream = (DOWNSTREAM[name][0],) if name in DOWNSTREAM else ()
  return first + ('slotformer', 'eval_rollout') + downstream


def config_of(name: str, step: str) -> str:
  """The config that runs `step` of video config `name`."""
  if name in DOWNSTREAM and DOWNSTREAM[name][0] == step:
    return DOWNSTREAM[name][1]
  return name


def batch_of(config, step: str) -> int:
  """The global batch of `step` (Aloe: open + multiple-choice questions)."""
  if step == 'aloe':
    return config.vqa.open_batch_size + config.vqa.choice_batch_size
  return config[SECTIONS[step]].batch_size


def _place(tree: Any, sharding_: NamedSharding) -> Any:
  return jax.tree.map(
      lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding_),
      tree)


def batch_spec(config, step: str, batch_size: int) -> dict[str, Any]:
  """Shapes and dtypes of one global batch as the data pipeline yields it
  (tests/train/test_tpu_compile.py checks SAVi's against the pipeline)."""
  frame = (*config.data.resolution, 3)
  u8 = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.uint8)
  f32 = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float32)
  if step == 'aloe':
    return aloe_batch_spec(config, batch_size)
  if step == 'readout':
    _, frames = readout_model(config)
    num_slots, slot_size = slot_models.get(config).slot_shape
    return {'features': f32(batch_size, frames, num_slots, slot_size),
            'labels': f32(batch_size)}
  if step == 'savi':
    return savi_batch_spec(config, batch_size)
  if step == 'dvae':
    return {'video': u8(batch_size, 1, *frame),
            'gumbel_temperature': f32(batch_size)}
  if step == 'steve':
    height, width = build_steve(
        config.steve, tuple(config.data.resolution),
        config.dvae.vocab_size).token_grid
    length = config.steve.clip_length
    return {'video': u8(batch_size, length, *frame),
            'tokens': jax.ShapeDtypeStruct((batch_size, length,
                                            height * width), jnp.uint16)}
  num_slots, slot_size = slot_models.get(config).slot_shape
  dyn = config.slotformer
  if step == 'slotformer':
    length = dyn.burn_in + dyn.rollout
    spec = {'slots': f32(batch_size, length, num_slots, slot_size)}
    if dyn.image_loss_weight > 0:
      # L_I's stream reads the rollout's frames only (`Run.slots`
      # video_from=burn_in; the loss takes the last `rollout` frames):
      # the fields of the slot model's targets (`image_loss_fields`).
      spec.update(target_fields_spec(config, batch_size, dyn.rollout))
    return spec
  length = dyn.burn_in + config.evaluation.rollout_steps
  return {'slots': f32(batch_size, length, num_slots, slot_size),
          'video': u8(batch_size, length, *frame)}


def target_fields_spec(config, batch_size: int, length: int
                       ) -> dict[str, Any]:
  """The batch fields of the slot model's targets over `length` frames
  (slotformer_jax/targets.py's contract: the frames uint8, flow and depth
  float32 [B, T, H, W, C])."""
  slot_model = slot_models.get(config)
  resolution = tuple(config.data.resolution)
  spec = {}
  for target in getattr(slot_model, 'targets', ()):
    dtype = jnp.uint8 if target.field == 'video' else jnp.float32
    spec[target.field] = jax.ShapeDtypeStruct(
        (batch_size, length, *resolution, target.channels), dtype)
  return spec or {'video': jax.ShapeDtypeStruct(
      (batch_size, length, *resolution, 3), jnp.uint8)}


def savi_batch_spec(config, batch_size: int) -> dict[str, Any]:
  """SAVi's training batch after the input pipeline (and SAVi++'s crop):
  the frames, its targets' fields and, conditional, the clip's boxes
  float32 [B, T, O, 4] (O = data.max_instances, the rows the datasets
  store)."""
  savi = config.savi
  spec = {'video': jax.ShapeDtypeStruct(
      (batch_size, savi.clip_length, *config.data.resolution, 3), jnp.uint8)}
  spec.update(target_fields_spec(config, batch_size, savi.clip_length))
  if slot_models.get(config).conditioning_fields:
    spec['boxes'] = jax.ShapeDtypeStruct(
        (batch_size, savi.clip_length, config.data.max_instances, 4),
        jnp.float32)
  return spec


def aloe_batch_spec(config, batch_size: int) -> dict[str, Any]:
  """One Aloe batch of `batch_size` questions (half open, half multiple
  choice), made by `QuestionBatches.batch` from two stand-in questions."""
  vqa = config.vqa
  length = vqa.max_question_len + vqa.max_choice_len
  choices = vqa.max_choices
  questions = [
      vqa_data.EncodedQuestion(
          0, 'video', 0, 0, '', np.zeros((1, length), np.int32),
          np.zeros((1, length), bool), answer=0),
      vqa_data.EncodedQuestion(
          0, 'video', 1, 1, '', np.zeros((choices, length), np.int32),
          np.zeros((choices, length), bool),
          choice_ids=np.arange(choices, dtype=np.int32),
          choice_labels=np.zeros(choices, np.int32))]
  frames = vqa.video_length + vqa.rollout_frames
  slots = np.zeros((frames, *slot_models.get(config).slot_shape), np.float32)
  batches = vqa_task.QuestionBatches(
      questions, lambda name: slots, video_length=vqa.video_length,
      num_frames=vqa.num_frames, stride=vqa.frame_stride,
      max_choices=choices)
  batch = batches.batch([0], [0], np.zeros(2, np.int64), batch_size // 2,
                        batch_size // 2)
  return {k: jax.ShapeDtypeStruct(v.shape, v.dtype) for k, v in batch.items()}


def standin_vocabulary() -> vqa_data.Vocabulary:
  return vqa_data.Vocabulary(
      vqa_data.make_vocabulary(f'w{i}' for i in range(STANDIN_WORDS - 1)),
      vqa_data.make_vocabulary(vqa_data.CLEVRER_ANSWERS))


def readout_model(config) -> tuple[Any, int]:
  """(the readout head of `config`'s task, frames per example of its
  'rollout' condition)."""
  if config.task == 'contact':
    # The whole clip, cut to readout.video_len when set (the embedded
    # data's videos have data.num_frames).
    frames = config.readout.video_len or config.data.get('num_frames')
    if not frames:
      raise ValueError('neither readout.video_len nor data.num_frames is '
                       'set: the frames per example are only known from '
                       'the data')
    slot_size = slot_models.get(config).slot_shape[1]
    return contact.build_readout(config.readout, slot_size), int(frames)
  if config.task == 'planning' and config.data.name == 'phyre':
    frames = len(phyre_rendered.selected_steps(config.readout))
    return phyre_rendered.build_classifier(
        config.readout, phyre_rendered.ROLLOUT, frames), frames
  if config.task == 'planning':  # features [1 + rollout_steps, ...]
    return (phyre_planning.build_classifier(config.readout,
                                            phyre_planning.ROLLOUT),
            1 + config.readout.rollout_steps)
  raise ValueError(f'no readout step for task {config.task!r}')


def readout_fit_config(config) -> readout_lib.FitConfig:
  if config.task == 'contact':
    return contact.fit_config(config.readout)
  r = config.readout  # as stages/planning/rendered.py builds it
  return readout_lib.FitConfig(epochs=r.epochs, batch_size=r.batch_size,
                               learning_rate=r.learning_rate,
                               warmup_fraction=r.warmup_fraction)


def readout_program(config, mesh: Mesh) -> tuple[Any, tuple]:
  """The readout head's jitted train step (`trainer.jit_update` of the
  `Stage` `readout_fit.fit_readout` trains) on one chip (the first of
  `mesh`), as the readouts train on the first device of each process."""
  one_chip = Mesh(np.array(mesh.devices.flat[:1]), (sharding.DATA_AXIS,))
  model, _ = readout_model(config)
  batch = batch_spec(config, 'readout', config.readout.batch_size)
  optimizer, _ = readout_lib.make_optimizer(readout_fit_config(config),
                                            steps_per_epoch=100)
  stage = trainer.Stage(
      name='readout', directory=NOWHERE, config=config.readout,
      loss_fn=functools.partial(readout_lib.readout_loss, model=model),
      init_params=None, batches=None, optimizer=(optimizer, None),
      rng_stream=readout_fit.DROPOUT_STREAM)
  example = jnp.zeros((1, *batch['features'].shape[1:]), jnp.float32)
  params = jax.eval_shape(
      lambda key: model.init(key, example)['params'], jax.random.key(0))
  state = jax.eval_shape(lambda: TrainState.create(params, optimizer))
  step = trainer.jit_update(stage, one_chip, optimizer, seed=0)
  return step, (_place(state, sharding.replicated_sharding(one_chip)),
                _place(batch, sharding.batch_sharding(one_chip)), None)


def slot_param_shapes(slot_model) -> Any:
  """{part: parameter shapes} of every part (`Loaded.params`' layout)."""
  return {part.name: chain.param_shapes(part) for part in slot_model.parts}


def step_program(config, step: str, mesh: Mesh,
                 num_seeds: int = 1) -> tuple[Any, tuple]:
  """(the jitted step `step` of `config` for `mesh`, its abstract arguments
  placed on `mesh`): what the trainer / the evaluation run, unexecuted;
  `num_seeds` > 1: the train step of that many seeds (`seeds_program`)."""
  if num_seeds > 1:
    return seeds_program(config, step, mesh, num_seeds)
  if step == 'readout':
    return readout_program(config, mesh)
  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  slot_model = Run.create(config, NOWHERE, mesh).slot_model
  batch = _place(batch_spec(config, step, batch_of(config, step)), batched)
  if step == 'eval_rollout':
    names = tuple(name for name in config.evaluation.metrics
                  if rollout_metrics.get(name).needs == rollout_metrics.FRAMES
                  and name != 'lpips')
    run = evaluate.make_rollout_evaluator(
        config.evaluation, mesh, names,
        {SLOTFORMER: dynamics_lib.build(config.slotformer, SLOTFORMER)},
        slot_model, burn_in=config.slotformer.burn_in,
        num_true=evaluate.num_true_ids(config.data.max_instances),
        compute_dtype=config.compute_dtype)
    # Only its parameter shapes are read (no stage is built: its batch need
    # not split over this slice, e.g. 256 chips and a batch of 128).
    dynamics_params = {SLOTFORMER: _place(dynamics_lib.param_shapes(
        config.slotformer, SLOTFORMER, slot_model.slot_shape), replicated)}
    return run, (dynamics_params,
                 _place(slot_param_shapes(slot_model), replicated), batch,
                 None)
  stage = train_stage(config, step, mesh)
  optimizer, _ = optim.make_optimizer(stage.config)
  update = trainer.jit_update(stage, mesh, optimizer, config.seed)
  state = trainer.abstract_train_state(stage.init_params, stage.config, mesh)
  frozen = (None if stage.frozen_params is None
            else _place(stage.frozen_params, replicated))
  return update, (state, batch, frozen)


SEEDED_STEPS = ('savi', 'dvae', 'steve', 'slotformer')
# The pipeline stage (mode) that trains each step.
STAGE_OF_STEP = {'savi': 'train_savi', 'dvae': 'train_dvae',
                 'steve': 'train_steve', 'slotformer': 'train_slotformer'}


def several_seeds_refused(config, step: str, num_seeds: int) -> str | None:
  """Why `step` of `config` has no K-seed program (None: it has one)."""
  if step not in SEEDED_STEPS:
    return (f'the {step} step runs one seed at a time (evaluation: each '
            "seed's one-seed program; the tasks take one seed; "
            'docs/seeds.md)')
  problems = task_lib.seeds_problems(with_seeds(config, num_seeds),
                                   [STAGE_OF_STEP[step]])
  return '; '.join(problems) or None


def with_seeds(config, num_seeds: int):
  """`config` with config.seeds = (0, ..., K - 1)."""
  config = config.copy_and_resolve_references()
  config.seeds = tuple(range(num_seeds))
  return config


# --host_chips: chips per host to assume instead of the topology's own
# (compile-only v5e:2x4 is 2 processes of 4 chips; a v5litepod-8 VM has 8).
HOST_CHIPS = {'value': 0}


def local_device_count(mesh: Mesh) -> int:
  """The devices of one host of `mesh`'s slice (compile-only TPU devices
  carry their host's process index; this CPU process's count is not the
  slice's), or --host_chips."""
  if HOST_CHIPS['value']:
    return HOST_CHIPS['value']
  first = mesh.devices.flat[0].process_index
  return sum(d.process_index == first for d in mesh.devices.flat)


def seeds_mesh(config, step: str, mesh: Mesh, num_seeds: int
               ) -> tuple[seeds_lib.Seeds, Mesh]:
  """(the `Seeds` the pipeline trains `step` with, the mesh `seeds.fit`
  makes of `mesh` for them)."""
  # Stage 1 draws with the seeds, the dynamics with seed + 1
  # (stage1.train_part, dynamics.dynamics_seed).
  seeds = seeds_lib.Seeds.of_config(with_seeds(config, num_seeds))
  if step == 'slotformer':
    seeds = seeds.map(dynamics.dynamics_seed)
  if seeds.seed_axis:
    mesh = seeds_lib.seed_mesh(mesh, num_seeds, local_device_count(mesh))
  return seeds, mesh


def seeds_program(config, step: str, mesh: Mesh, num_seeds: int
                  ) -> tuple[Any, tuple]:
  """The K-seed train step `seeds.fit` jits for `config.seeds` of
  `num_seeds` seeds on the slice `mesh` (a 'data' mesh, as `Run.mesh`),
  and its abstract arguments: the SeedsState, the batch (stacked per seed
  for STEVE and SlotFormer), the frozen parameters (per seed for
  SlotFormer)."""
  seeds, seed_mesh = seeds_mesh(config, step, mesh, num_seeds)
  stage = train_stage(config, step, mesh)
  frozen = stage.frozen_params  # shapes: stacked here, placed below
  stages = [stage]
  if step in ('steve', 'slotformer'):
    # fit.fit_chains: K one-seed stages (each seed's tokens or slots and
    # decoder; the same shapes).
    stages = [dataclasses.replace(stage, frozen_params=None)] * num_seeds
    if frozen is not None:
      frozen = jax.tree.map(
          lambda x: jax.ShapeDtypeStruct((num_seeds, *x.shape), x.dtype),
          frozen)
  # The (seed, data) mesh is made above, for the slice's hosts.
  program = seeds_lib.program(stages, seed_mesh,
                              dataclasses.replace(seeds, seed_axis=False))
  spec = batch_spec(config, step, batch_of(config, step))
  if len(stages) > 1:
    spec = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct((num_seeds, *x.shape), x.dtype), spec)
  return program.update, (
      program.abstract_state(), _place(spec, program.batch_sharding),
      None if frozen is None else _place(frozen, program.frozen_sharding))


def train_stage(config, step: str, mesh: Mesh) -> trainer.Stage:
  """The trainer's `Stage` of train step `step` (no data source: only its
  `batches` would read one)."""
  slot_model = Run.create(config, NOWHERE, mesh).slot_model
  if step in ('savi', 'dvae', 'steve'):
    return stage1.part_stage(slot_model.part(step), NOWHERE, mesh, None,
                             seed=config.seed)
  if step == 'aloe':
    return vqa_stages.aloe_stage(config.vqa, NOWHERE, standin_vocabulary(),
                                 slot_model.slot_shape, None)
  return dynamics.dynamics_stage(
      config.slotformer, SLOTFORMER, NOWHERE, mesh, slot_model,
      slot_param_shapes(slot_model), None, seed=config.seed + 1,
      compute_dtype=config.compute_dtype)


def lowered_step(config, step: str, mesh: Mesh, num_seeds: int = 1):
  """The jitted step `step` of `config` lowered for `mesh`'s devices."""
  run, args = step_program(config, step, mesh, num_seeds)
  return run.lower(*args)


def with_batch(config, step: str, global_batch: int):
  config = config.copy_and_resolve_references()
  if step == 'aloe':  # half open, half multiple-choice questions
    config.vqa.open_batch_size = config.vqa.choice_batch_size = (
        global_batch // 2)
  else:
    config[SECTIONS[step]].batch_size = global_batch
  return config


def chips_of(step: str, mesh: Mesh) -> int:
  """Chips the step runs on (the readout's loop: one)."""
  return 1 if step == 'readout' else mesh.devices.size


def batch_unit(step: str) -> int:
  """Aloe's batch is open + multiple-choice questions, in equal numbers."""
  return 2 if step == 'aloe' else 1


def compile_row(config, step: str, mesh: Mesh,
                num_seeds: int = 1) -> dict[str, Any]:
  start = time.perf_counter()
  compiled = lowered_step(config, step, mesh, num_seeds).compile()
  seconds = time.perf_counter() - start
  cost = compiled.cost_analysis()
  if isinstance(cost, (list, tuple)):
    cost = cost[0]
  memory = compiled.memory_analysis()
  hbm = (memory.argument_size_in_bytes + memory.output_size_in_bytes
         + memory.temp_size_in_bytes - memory.alias_size_in_bytes)
  return dict(flops=float(cost['flops']),
              bytes_accessed=float(cost['bytes accessed']),
              hbm_bytes=int(hbm),
              argument_bytes=int(memory.argument_size_in_bytes),
              output_bytes=int(memory.output_size_in_bytes),
              temp_bytes=int(memory.temp_size_in_bytes),
              alias_bytes=int(memory.alias_size_in_bytes),
              compile_seconds=seconds)


def _hbm_or_required(config, step: str, mesh: Mesh, chip: dict) -> int:
  """HBM per chip of the step; when XLA:TPU refuses it at compile
  (RESOURCE_EXHAUSTED: "... HLO temporaries (31.44G) exceeds available HBM
  (15.75G)"), what it said was required (at least the chip's HBM + 1)."""
  try:
    return compile_row(config, step, mesh)['hbm_bytes']
  except Exception as error:  # pylint: disable=broad-except
    if 'RESOURCE_EXHAUSTED' not in str(error):
      raise
    found = re.search(r'temporaries \(([0-9.]+)G\)', str(error))
    required = int(float(found.group(1)) * GiB) if found else 2 * chip['hbm']
    return max(required, chip['hbm'] + 1)


def largest_batch(config, step: str, mesh: Mesh, chip: dict, log, *,
                  known: dict[int, int], tolerance: float = 0.1,
                  max_compiles: int = 8, limit: int = 1 << 16
                  ) -> dict[str, Any]:
  """The largest per-chip batch whose step compiles within the chip's HBM.

  `known`: {per-chip batch: HBM bytes} already compiled (the paper
  batch's row). Grows the batch while it fits (a line through the two
  largest fitting batches, or HBM proportional to the batch from one,
  predicts the largest; at least +25 % per compile), then bisects between
  the largest batch that fits and the smallest that does not until they
  are within `tolerance` of each other or `max_compiles` are spent.
  Returns largest_per_chip (the largest that fitted, 0 if none did),
  smallest_not_fitting (None if none was found: the search ran out or hit
  `limit`), and every compile's HBM (`tried`).
  """
  chips, unit = chips_of(step, mesh), batch_unit(step)
  tried = dict(known)
  fits = lambda b: tried[b] <= chip['hbm']

  def compile_at(per_chip: int) -> None:
    tried[per_chip] = _hbm_or_required(
        with_batch(config, step, per_chip * chips), step, mesh, chip)
    log(f'    largest-batch search: {per_chip}/chip -> '
        f'{tried[per_chip] / GiB:.2f} GiB'
        f'{"" if fits(per_chip) else " (does not fit)"}')

  compiles = 0
  while compiles < max_compiles:
    fitting = sorted(b for b in tried if fits(b))
    above = sorted(b for b in tried if not fits(b)
                   and (not fitting or b > fitting[-1]))
    low = fitting[-1] if fitting else 0
    high = above[0] if above else None
    if high is not None and (high - low <= unit
                             or high <= low * (1 + tolerance)):
      break
    if high is None:
      if low >= limit:
        break
      if not fitting:  # nothing known fits: start at one example per chip
        guess = unit
      elif len(fitting) >= 2:
        (b1, b2) = fitting[-2:]
        slope = (tried[b2] - tried[b1]) / (b2 - b1)
        guess = (b2 + (chip['hbm'] - tried[b2]) / slope if slope > 0
                 else 2 * b2)
      else:
        guess = low * chip['hbm'] / max(tried[low], 1)
      guess = int(max(guess, low * 1.25, low + unit))
      guess = min(guess, limit)
    else:
      guess = (low + high) // 2
    guess = max(unit, guess // unit * unit)
    if guess in tried:
      break
    compile_at(guess)
    compiles += 1
  fitting = sorted(b for b in tried if fits(b))
  low = fitting[-1] if fitting else 0
  above = sorted(b for b in tried if not fits(b) and b > low)
  return dict(largest_per_chip=low,
              smallest_not_fitting=above[0] if above else None,
              search_compiles=compiles,
              tried={str(b): tried[b] for b in sorted(tried)})


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--topologies', default='v5e:2x4,v4:2x2x1,v5e:16x16')
  parser.add_argument('--configs', default=','.join(DEFAULT_CONFIGS))
  parser.add_argument('--steps', default=','.join(DEFAULT_STEPS))
  parser.add_argument('--dtypes', default='float32,bfloat16')
  parser.add_argument('--largest_batch', action='store_true')
  parser.add_argument('--largest_batch_tolerance', type=float, default=0.1)
  parser.add_argument('--largest_batch_compiles', type=int, default=8)
  parser.add_argument('--seeds', default='1',
                      help='K,...: compile each train step for K seeds '
                      'in one program (config.seeds); 1: one seed')
  parser.add_argument('--host_chips', type=int, default=0,
                      help='chips per host for the seed mesh (default: the '
                      "topology's devices per process index)")
  parser.add_argument('--config_overrides', default='',
                      help='name=value,... applied to every config (tests)')
  parser.add_argument('--json', default='')
  args = parser.parse_args(argv)
  configs = [c for c in args.configs.split(',') if c]
  for name in configs:
    if importlib.util.find_spec(name.partition(':')[0]) is None:
      print(f'error: --configs: no configs/{name}.py', file=sys.stderr)
      return 2
  wanted_steps = args.steps.split(',')
  for step in wanted_steps:
    if step not in DEFAULT_STEPS:
      print(f'error: --steps: unknown {step!r}, choose from '
            f'{list(DEFAULT_STEPS)}', file=sys.stderr)
      return 2
  try:
    seed_counts = [int(k) for k in args.seeds.split(',') if k]
  except ValueError:
    seed_counts = []
  if not seed_counts or min(seed_counts) < 1:
    print(f'error: --seeds: comma-separated counts >= 1, got '
          f'{args.seeds!r}', file=sys.stderr)
    return 2
  HOST_CHIPS['value'] = args.host_chips
  dtypes = args.dtypes.split(',')
  for dtype in dtypes:
    if dtype not in precision.COMPUTE_DTYPES:
      print(f'error: --dtypes: unknown {dtype!r}, choose from '
            f'{precision.COMPUTE_DTYPES}', file=sys.stderr)
      return 2
  why = libtpu_missing()
  if why:
    print(f'tpu_compile: nothing compiled: {why}')
    return 0

  rows, not_fitting, failed = [], [], []
  log = lambda line: print(line, flush=True)
  log('topology   config          step          dtype     K  '
      'batch(/chip)  fits  HBM GiB/chip  GFLOP/chip  GB/chip  floor ms  '
      'compile s')
  for topology in args.topologies.split(','):
    try:
      devices = tpu_devices(topology)
    except Exception as error:  # pylint: disable=broad-except
      print(f'error: --topologies: {topology!r}: {error}', file=sys.stderr)
      return 2
    chip = CHIPS.get(devices[0].device_kind)
    if chip is None:
      print(f'error: --topologies: {topology!r}: no spec-sheet numbers for '
            f'{devices[0].device_kind!r} in CHIPS', file=sys.stderr)
      return 2
    mesh = Mesh(np.array(devices), (sharding.DATA_AXIS,))
    for name in configs:
      for dtype in dtypes:
        config = configured(name, dtype, args.config_overrides)
        for step in steps_of(config, name):
          if step not in wanted_steps:
            continue
          step_config = config_of(name, step)
          for num_seeds in seed_counts:
            row = one_row(configured(step_config, dtype,
                                     args.config_overrides),
                          step_config, step, dtype, topology, mesh, chip,
                          args, log, num_seeds=num_seeds)
            rows.append(row)
            label = (f'{topology} {step_config} {step} {dtype}'
                     + (f' {num_seeds} seeds' if num_seeds > 1 else ''))
            if row['status'] == 'compile failed':
              failed.append(f'{label} ({row["why"]})')
            elif num_seeds == 1 and (row['status'] == 'does not fit' or (
                row['status'] == 'compiled' and not row['fits']
                and 'note' not in row)):
              # (K seeds that do not fit answer "how many fit": no error.)
              not_fitting.append(label)
            if args.json:  # after every row: partial results survive
              files.write_json_atomic(args.json, rows)
  if args.json:
    files.write_json_atomic(args.json, rows)
  if failed:
    print('error: did not compile: ' + '; '.join(failed), file=sys.stderr)
  if not_fitting:
    print('error: does not fit its chip at the paper batch: '
          + '; '.join(not_fitting), file=sys.stderr)
  return 1 if failed or not_fitting else 0


def configured(name: str, dtype: str, overrides: str):
  """configs/<name>.py's config with `overrides` (section.field=value,...)
  and `compute_dtype`."""
  config = load_config(name)
  for override in filter(None, overrides.split(',')):
    key, value = override.split('=', 1)
    section, field = key.rsplit('.', 1)
    target = config
    for part in section.split('.'):
      target = target[part]
    target[field] = type(target[field])(value)
  config.compute_dtype = dtype
  return config


def one_row(config, name: str, step: str, dtype: str, topology: str,
            mesh: Mesh, chip: dict, args, log, num_seeds: int = 1
            ) -> dict[str, Any]:
  """Compiles `step` of `config` at its paper batch for `mesh` (and
  searches the largest batch when asked; one seed only): the table's row;
  `num_seeds` > 1: the train step of that many seeds in one program."""
  chips = chips_of(step, mesh)
  row = dict(topology=topology, chips=chips, config=name, step=step,
             dtype=dtype, device_kind=mesh.devices.flat[0].device_kind,
             chip_hbm=chip['hbm'], seeds=num_seeds)
  head = f'{topology:10s} {name:15s} {step:13s} {dtype:9s} {num_seeds:2d}'
  data_shards = chips
  if num_seeds > 1:
    refused = several_seeds_refused(config, step, num_seeds)
    if refused:
      row.update(status='not built', why=refused)
      log(f'{head} not built: {refused}')
      return row
    seeds, seed_mesh = seeds_mesh(config, step, mesh, num_seeds)
    row['mesh'] = dict(seed_mesh.shape)
    row['host_chips'] = local_device_count(mesh)
    row['seed_loop'] = seeds.loop_on(seed_mesh)
    data_shards = seed_mesh.shape[sharding.DATA_AXIS]
  if step == 'readout':
    row['note'] = "the readout's loop is not sharded: one chip"
  paper_batch = batch_of(config, step)
  row['paper_batch'] = paper_batch
  unit = batch_unit(step)
  if paper_batch % (data_shards * unit):
    row['note'] = (f'paper batch {paper_batch} does not split over '
                   f'{data_shards} data shards: compiled at {unit} per '
                   'shard')
    global_batch = data_shards * unit
  else:
    global_batch = paper_batch
  row['batch'] = global_batch
  try:
    if step in FLOAT32_ONLY and dtype != precision.FLOAT32:
      raise ValueError(
          f'the {step} step computes in float32 whatever '
          'config.compute_dtype says (it applies to the slot model and '
          'dynamics steps): the same program as the float32 row')
    Run.create(config, NOWHERE, jax.sharding.Mesh(
        np.array(jax.devices()[:1]), ('data',)))  # refuses a compute dtype
    if step == 'readout':
      readout_model(config)
  except Exception as error:  # pylint: disable=broad-except
    row.update(status='not built', why=str(error))
    log(f'{head} not built: {error}')
    return row
  try:
    row.update(compile_row(with_batch(config, step, global_batch), step,
                           mesh, num_seeds))
  except Exception as error:  # pylint: disable=broad-except
    # XLA's own message says why (e.g. out of memory at compile).
    why = str(error).strip().splitlines()[0][:300]
    row.update(status='does not fit' if 'RESOURCE_EXHAUSTED' in why
               else 'compile failed', why=why)
    log(f'{head} {row["status"]}: {why}')
    return row
  row['fits'] = row['hbm_bytes'] <= chip['hbm']
  row['floor_seconds'] = max(row['flops'] / chip['peak_flops'],
                             row['bytes_accessed'] / chip['hbm_bandwidth'])
  row['floor_per_seed_seconds'] = row['floor_seconds'] / num_seeds
  row['status'] = 'compiled'
  if args.largest_batch and num_seeds == 1:
    row.update(largest_batch(
        config, step, mesh, chip, log,
        known={global_batch // chips: row['hbm_bytes']},
        tolerance=args.largest_batch_tolerance,
        max_compiles=args.largest_batch_compiles))
  log(f'{head} {global_batch:5d}({global_batch // data_shards:3d})  '
      f'{"yes" if row["fits"] else "NO":4s}  '
      f'{row["hbm_bytes"] / GiB:12.2f}  {row["flops"] / 1e9:10.1f}  '
      f'{row["bytes_accessed"] / 1e9:7.2f}  '
      f'{row["floor_seconds"] * 1e3:8.2f}  {row["compile_seconds"]:9.1f}'
      + (f'  largest {row["largest_per_chip"]}/chip (not '
         f'{row["smallest_not_fitting"]})' if 'largest_per_chip' in row
         else '')
      + (f'  mesh {row["mesh"]} {row["seed_loop"]}, per seed '
         f'{row["floor_per_seed_seconds"] * 1e3:.2f} ms' if 'mesh' in row
         else '')
      + (f'  ({row["note"]})' if 'note' in row else ''))
  return row


if __name__ == '__main__':
  sys.exit(main())
