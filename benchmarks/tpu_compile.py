r"""Compiles the project's real jitted steps for TPU slices, on a machine
without a TPU, and reports per chip what XLA:TPU says they need.

  pip install -e '.[tpu]'    # jax[tpu] at the installed jax: brings libtpu
  python benchmarks/tpu_compile.py [--topologies=v5e:2x4,v4:2x2x1,v5e:16x16]
      [--configs=obj3d,clevrer,phyre,physion] [--steps=savi,slotformer,...]
      [--dtypes=float32,bfloat16] [--largest_batch] [--json=out.json]

Each row is one ahead-of-time compile (`.lower(...).compile()` over the
compile-only devices of `jax.experimental.topologies`) of a step the
project runs, built by the project's own code:

  savi / dvae / steve  the stage-1 train step: the `Stage` of
                       `slot_models.savi.savi_stage` / `steve.dvae_stage` /
                       `steve.steve_stage`, jitted by `trainer.jit_update`
                       (what `trainer.fit` runs: batch on 'data', state and
                       frozen parameters replicated, the state donated);
  slotformer           the dynamics train step of `stages.dynamics.
                       dynamics_stage` (L_S + lambda L_I through the frozen
                       SAVi decoder where the config has lambda > 0), same
                       jit;
  eval_rollout         `evaluation.evaluate.make_rollout_evaluator`: the
                       SlotFormer rollout + decoding + per-step metrics of
                       one evaluation batch, without LPIPS (its VGG weights
                       are a download) and without the object metrics.

The global batch is the config's (the paper's). A slice whose chip count
does not divide it (a 256-chip pod slice and batch 64) compiles at one
sample per chip instead, and the row says so. Per chip: HBM = arguments +
outputs + temporaries - aliased (`memory_analysis()`) against the chip's
HBM, FLOPs and bytes accessed (`cost_analysis()`), the roofline floor
max(FLOPs / peak, bytes / HBM bandwidth) and the compile seconds.
`--largest_batch` also finds the largest per-chip batch that fits: HBM is
fitted linearly through compiles at 1 and 2 per chip, the predicted
largest is compiled, and stepped down until it fits.

Exit status 1 when a step does not fit its chip's HBM at the paper's batch.
Without libtpu it prints why and exits 0. jax itself runs on CPU
(JAX_PLATFORMS=cpu unless set); only the compile targets the TPU.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import sys
import time
from typing import Any

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..'))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'configs'))

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
from slotformer_jax import models  # noqa: E402
from slotformer_jax import slot_models  # noqa: E402
from slotformer_jax.evaluation import evaluate  # noqa: E402
from slotformer_jax.slot_models import savi as savi_lib  # noqa: E402
from slotformer_jax.slot_models import steve as steve_lib  # noqa: E402
from slotformer_jax.stages import dynamics  # noqa: E402
from slotformer_jax.train import optim  # noqa: E402
from slotformer_jax.train import precision  # noqa: E402
from slotformer_jax.train import sharding  # noqa: E402
from slotformer_jax.train import trainer  # noqa: E402

GiB = 2**30

# Public spec sheets (cloud.google.com/tpu/docs/v5e, /v4): HBM per chip,
# peak bf16 matmul FLOP/s per chip, HBM bandwidth per chip. No float32
# peak is published: XLA:TPU runs float32 matmuls at the default precision
# as bfloat16 passes, so the bf16 peak is the floor used for both dtypes.
CHIPS = {
    'TPU v5 lite': dict(name='v5e', hbm=16 * GiB, peak_flops=197e12,
                        hbm_bandwidth=819e9),
    'TPU v4': dict(name='v4', hbm=32 * GiB, peak_flops=275e12,
                   hbm_bandwidth=1228e9),
}

# The config's stage section of each step's batch size.
SECTIONS = {'savi': 'savi', 'dvae': 'dvae', 'steve': 'steve',
            'slotformer': 'slotformer', 'eval_rollout': 'evaluation'}
DEFAULT_CONFIGS = ('obj3d', 'clevrer', 'phyre', 'physion')
DEFAULT_STEPS = ('savi', 'dvae', 'steve', 'slotformer', 'eval_rollout')
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


def steps_of(config) -> tuple[str, ...]:
  """The train / evaluation steps a config's pipeline runs."""
  first = (('dvae', 'steve') if config.slot_model == 'steve' else ('savi',))
  return first + ('slotformer', 'eval_rollout')


def _place(tree: Any, sharding_: NamedSharding) -> Any:
  return jax.tree.map(
      lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding_),
      tree)


def batch_spec(config, step: str, batch_size: int) -> dict[str, Any]:
  """Shapes and dtypes of one global batch as the data pipeline yields it
  (tests/benchmarks/test_tpu_compile.py checks SAVi's against the pipeline)."""
  frame = (*config.data.resolution, 3)
  u8 = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.uint8)
  f32 = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float32)
  if step == 'savi':
    return {'video': u8(batch_size, config.savi.clip_length, *frame)}
  if step == 'dvae':
    return {'video': u8(batch_size, 1, *frame),
            'gumbel_temperature': f32(batch_size)}
  if step == 'steve':
    height, width = models.build_steve(config).token_grid
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
      spec['video'] = u8(batch_size, length, *frame)
    return spec
  length = dyn.burn_in + config.evaluation.rollout_steps
  return {'slots': f32(batch_size, length, num_slots, slot_size),
          'video': u8(batch_size, length, *frame)}


def slot_param_shapes(slot_model) -> Any:
  if isinstance(slot_model, steve_lib.Steve):
    return {steve_lib.NAME: slot_model.steve_param_shapes(),
            steve_lib.DVAE_NAME: slot_model.dvae_param_shapes()}
  return slot_model.param_shapes()


def step_program(config, step: str, mesh: Mesh) -> tuple[Any, tuple]:
  """(the jitted step `step` of `config` for `mesh`, its abstract arguments
  placed on `mesh`): what the trainer / the evaluation run, unexecuted."""
  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  slot_model = slot_models.get(config)
  slot_model.check_compute_dtype()
  section = SECTIONS[step]
  batch = _place(batch_spec(config, step, config[section].batch_size),
                 batched)
  if step == 'eval_rollout':
    names = tuple(name for name in config.evaluation.metrics
                  if name != 'lpips' and name not in evaluate.OBJECT_METRICS)
    run = evaluate.make_rollout_evaluator(config, mesh, names, None,
                                          (models.SLOTFORMER,), slot_model)
    dyn_stage = dynamics.dynamics_stage(
        config, NOWHERE, mesh, models.SLOTFORMER, slot_model,
        slot_param_shapes(slot_model), None)
    dynamics_params = {models.SLOTFORMER: _place(
        jax.eval_shape(dyn_stage.init_params, jax.random.key(0)),
        replicated)}
    return run, (dynamics_params,
                 _place(slot_param_shapes(slot_model), replicated), batch)
  stage = train_stage(config, step, mesh)
  optimizer, _ = optim.make_optimizer(stage.config)
  update = trainer.jit_update(stage, mesh, optimizer, config.seed)
  state = trainer.abstract_train_state(stage.init_params, stage.config, mesh)
  frozen = (None if stage.frozen_params is None
            else _place(stage.frozen_params, replicated))
  return update, (state, batch, frozen)


def train_stage(config, step: str, mesh: Mesh) -> trainer.Stage:
  """The trainer's `Stage` of train step `step` (no data source: only its
  `batches` would read one)."""
  if step == 'savi':
    return savi_lib.savi_stage(config, NOWHERE, mesh, None)
  if step == 'dvae':
    return steve_lib.dvae_stage(config, NOWHERE, mesh, None)
  if step == 'steve':
    return steve_lib.steve_stage(config, NOWHERE, mesh, None)
  slot_model = slot_models.get(config)
  return dynamics.dynamics_stage(
      config, NOWHERE, mesh, models.SLOTFORMER, slot_model,
      slot_param_shapes(slot_model), None)


def lowered_step(config, step: str, mesh: Mesh):
  """The jitted step `step` of `config` lowered for `mesh`'s devices."""
  run, args = step_program(config, step, mesh)
  return run.lower(*args)


def with_batch(config, step: str, global_batch: int):
  config = config.copy_and_resolve_references()
  config[SECTIONS[step]].batch_size = global_batch
  return config


def compile_row(config, step: str, mesh: Mesh) -> dict[str, Any]:
  start = time.perf_counter()
  compiled = lowered_step(config, step, mesh).compile()
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


def largest_batch(config, step: str, mesh: Mesh, chip: dict,
                  log) -> dict[str, Any]:
  """The largest per-chip batch whose step fits the chip's HBM: a line
  through the HBM at 1 and 2 per chip predicts it, compiles confirm it
  (stepping down, at most 6 compiles, while XLA:TPU says it does not fit)."""
  chips = mesh.devices.size
  hbm = {b: _hbm_or_required(with_batch(config, step, b * chips), step,
                             mesh, chip) for b in (1, 2)}
  slope = hbm[2] - hbm[1]
  if hbm[1] > chip['hbm']:
    return dict(largest_per_chip=0, fit_hbm=hbm)
  if slope <= 0:
    return dict(largest_per_chip=None, fit_hbm=hbm)
  guess = max(1, int((chip['hbm'] - (hbm[1] - slope)) // slope))
  tried = {}
  for _ in range(6):
    if guess <= 2:
      break
    tried[guess] = _hbm_or_required(
        with_batch(config, step, guess * chips), step, mesh, chip)
    log(f'    largest-batch search: {guess}/chip -> '
        f'{tried[guess] / GiB:.2f} GiB')
    if tried[guess] <= chip['hbm']:
      break
    guess = max(2, int(0.95 * guess * chip['hbm'] / tried[guess]))
  if guess > 2 and (guess not in tried or tried[guess] > chip['hbm']):
    return dict(largest_per_chip=None, fit_hbm=hbm, tried=tried)
  return dict(largest_per_chip=guess, fit_hbm=hbm, tried=tried,
              confirmed_hbm=tried.get(guess, hbm.get(guess)))


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--topologies', default='v5e:2x4,v4:2x2x1,v5e:16x16')
  parser.add_argument('--configs', default=','.join(DEFAULT_CONFIGS))
  parser.add_argument('--steps', default=','.join(DEFAULT_STEPS))
  parser.add_argument('--dtypes', default='float32,bfloat16')
  parser.add_argument('--largest_batch', action='store_true')
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

  rows, not_fitting = [], []
  log = lambda line: print(line, flush=True)
  log('topology   config   step          dtype     batch(/chip)  fits  '
      'HBM GiB/chip  GFLOP/chip  GB/chip  floor ms  compile s')
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
    chips = len(devices)
    for name in configs:
      base = load_config(name)
      for override in filter(None, args.config_overrides.split(',')):
        key, value = override.split('=', 1)
        section, field = key.rsplit('.', 1)
        target = base
        for part in section.split('.'):
          target = target[part]
        target[field] = type(target[field])(value)
      for dtype in dtypes:
        config = base.copy_and_resolve_references()
        config.compute_dtype = dtype
        for step in steps_of(config):
          if step not in wanted_steps:
            continue
          row = dict(topology=topology, chips=chips, config=name, step=step,
                     dtype=dtype, device_kind=devices[0].device_kind,
                     chip_hbm=chip['hbm'])
          paper_batch = config[SECTIONS[step]].batch_size
          row['paper_batch'] = paper_batch
          if paper_batch % chips:
            row['note'] = (f'paper batch {paper_batch} does not split over '
                           f'{chips} chips: compiled at 1 per chip')
            global_batch = chips
          else:
            global_batch = paper_batch
          row['batch'] = global_batch
          try:
            slot_models.get(config).check_compute_dtype()
          except Exception as error:  # pylint: disable=broad-except
            row.update(status='not built', why=str(error))
            rows.append(row)
            log(f'{topology:10s} {name:8s} {step:13s} {dtype:9s} '
                f'not built: {error}')
            continue
          try:
            row.update(compile_row(with_batch(config, step, global_batch),
                                   step, mesh))
          except Exception as error:  # pylint: disable=broad-except
            # XLA's own message says why (e.g. out of memory at compile).
            why = str(error).strip().splitlines()[0][:300]
            row.update(status='does not fit' if 'RESOURCE_EXHAUSTED' in why
                       else 'compile failed', why=why)
            rows.append(row)
            not_fitting.append(f'{topology} {name} {step} {dtype} ({why})')
            log(f'{topology:10s} {name:8s} {step:13s} {dtype:9s} '
                f'compile failed: {why}')
            continue
          row['fits'] = row['hbm_bytes'] <= chip['hbm']
          row['floor_seconds'] = max(row['flops'] / chip['peak_flops'],
                                     row['bytes_accessed']
                                     / chip['hbm_bandwidth'])
          row['status'] = 'compiled'
          if not row['fits'] and 'note' not in row:
            not_fitting.append(f'{topology} {name} {step} {dtype}')
          if args.largest_batch:
            row.update(largest_batch(config, step, mesh, chip, log))
          rows.append(row)
          log(f'{topology:10s} {name:8s} {step:13s} {dtype:9s} '
              f'{global_batch:5d}({global_batch // chips:3d})  '
              f'{"yes" if row["fits"] else "NO":4s}  '
              f'{row["hbm_bytes"] / GiB:12.2f}  {row["flops"] / 1e9:10.1f}  '
              f'{row["bytes_accessed"] / 1e9:7.2f}  '
              f'{row["floor_seconds"] * 1e3:8.2f}  '
              f'{row["compile_seconds"]:9.1f}'
              + (f'  largest {row["largest_per_chip"]}/chip'
                 if 'largest_per_chip' in row else '')
              + (f'  ({row["note"]})' if 'note' in row else ''))
          if args.json:  # after every row: partial results survive
            files.write_json_atomic(args.json, rows)
  if args.json:
    files.write_json_atomic(args.json, rows)
  if not_fitting:
    print('error: does not fit its chip at the paper batch: '
          + '; '.join(not_fitting), file=sys.stderr)
    return 1
  return 0


if __name__ == '__main__':
  sys.exit(main())
