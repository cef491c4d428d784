r"""Compiles the SAVi decoder's forward + backward for a TPU slice, in both
kernel forms, on a machine without a TPU, and prints what XLA:TPU reports.

  pip install -e '.[tpu]'    # jax[tpu] at the installed jax: brings libtpu
  python benchmarks/tpu_kernels.py [--topologies=v5e:2x2,v4:2x2x1]
      [--configs=obj3d,clevrer] [--dtypes=float32,bfloat16] [--json=out.json]

The workload is the decoder part of a SAVi training step at the paper's
size (configs/obj3d.py, configs/clevrer.py: global batch 64 clips of 6
frames, 6 / 7 slots of 128, 64x64 frames decoded from 8x8 by four 5x5
transposed convolutions of 64 channels): slots [64, 6, N, 128] -> decoded
frames, mean squared error against a target, gradients with respect to the
decoder parameters and the slots. The batch is sharded over every chip of
the slice (`NamedSharding` over a one-axis `Mesh`), parameters replicated.

Each row is one ahead-of-time compile (`jax.jit(...).lower(...).compile()`
over the compile-only devices of `jax.experimental.topologies`) of:

  cpu          the CPU forms (phase-split transposed convolutions, kernel
               gradients through a materialised x @ I);
  accelerator  the plain input-dilated / stride-1 `lax.conv_general_dilated`
               with XLA's own gradients;
  auto         the default (`kernels='auto'`, `jax.lax.platform_dependent`):
               on a TPU lowering it must be the accelerator form, and the
               script checks that its costs equal that row's.

Per chip: FLOPs and bytes accessed (`cost_analysis()`), HBM = arguments +
outputs + temporaries - aliased (`memory_analysis()`), compile seconds.
Without libtpu (no `jax[tpu]` install) it prints why and exits 0 having
compiled nothing. The process runs jax on CPU (JAX_PLATFORMS=cpu unless
set); only the compile targets the TPU.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..'))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'configs'))

# The compile-only TPU devices need no TPU backend; keep jax's own on CPU so
# libtpu does not look for chips on this machine.
os.environ.setdefault('JAX_PLATFORMS', 'cpu')

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh  # noqa: E402
from jax.sharding import NamedSharding  # noqa: E402
from jax.sharding import PartitionSpec  # noqa: E402

import clevrer  # noqa: E402  (configs/clevrer.py)
import obj3d  # noqa: E402  (configs/obj3d.py)
from slotformer_jax import files  # noqa: E402
from slotformer_jax.modules import platform  # noqa: E402
from slotformer_jax.runtime import precision  # noqa: E402
from slotformer_jax.slot_models.savi import build_decoder

CONFIGS = {'obj3d': obj3d.get_config, 'clevrer': clevrer.get_config}
FORMS = (platform.CPU, platform.ACCELERATOR, platform.AUTO)


def libtpu_missing() -> str | None:
  """Why no TPU compile is possible here, or None."""
  if importlib.util.find_spec('libtpu') is None:
    return ("libtpu is not installed (pip install -e '.[tpu]' installs "
            f'jax[tpu]=={jax.__version__})')
  return None


def tpu_devices(topology: str) -> list:
  from jax.experimental import topologies
  return list(topologies.get_topology_desc(topology_name=topology,
                                           platform='tpu').devices)


def decoder_step(config, kernels: str, dtype: str):
  """(loss_and_grads, params, slots, target): the decoder forward +
  backward of one SAVi step at the config's global batch, abstract."""
  decoder = build_decoder(
      config.savi.decoder, tuple(config.data.resolution)).clone(
          kernels=kernels)
  savi = config.savi
  height, width = config.data.resolution
  slots = jax.ShapeDtypeStruct(
      (savi.batch_size, savi.clip_length, savi.num_slots, savi.slot_size),
      jnp.float32)
  target = jax.ShapeDtypeStruct(
      (savi.batch_size, savi.clip_length, height, width, 3), jnp.float32)
  params = jax.eval_shape(decoder.init, jax.random.key(0), slots)

  def loss(params, slots, target):
    recon = decoder.apply(params, slots).recon
    return jnp.mean((recon.astype(jnp.float32) - target) ** 2)

  # As `config.compute_dtype` does it: float32 parameters and slots cast to
  # the compute dtype, module inputs too, gradients back in float32.
  loss = precision.with_compute_dtype(loss, dtype)
  return jax.value_and_grad(loss, argnums=(0, 1)), params, slots, target


def compile_row(config, kernels: str, dtype: str, devices: list) -> dict:
  fn, params, slots, target = decoder_step(config, kernels, dtype)
  mesh = Mesh(np.array(devices), ('data',))
  replicated = NamedSharding(mesh, PartitionSpec())
  batch = NamedSharding(mesh, PartitionSpec('data'))
  params_sharding = jax.tree.map(lambda _: replicated, params)

  def placed(tree, sharding):
    return jax.tree.map(
        lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
        tree, sharding)

  jitted = jax.jit(fn, in_shardings=(params_sharding, batch, batch),
                   out_shardings=(replicated, (params_sharding, batch)))
  start = time.perf_counter()
  compiled = jitted.lower(placed(params, params_sharding),
                          placed(slots, batch), placed(target, batch)).compile()
  seconds = time.perf_counter() - start
  cost = compiled.cost_analysis()
  if isinstance(cost, (list, tuple)):  # older jax: one dict per program
    cost = cost[0]
  memory = compiled.memory_analysis()
  hbm = (memory.argument_size_in_bytes + memory.output_size_in_bytes
         + memory.temp_size_in_bytes - memory.alias_size_in_bytes)
  return dict(kernels=kernels, dtype=dtype, flops=float(cost['flops']),
              bytes_accessed=float(cost['bytes accessed']),
              hbm_bytes=int(hbm), temp_bytes=int(memory.temp_size_in_bytes),
              argument_bytes=int(memory.argument_size_in_bytes),
              compile_seconds=seconds)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--topologies', default='v5e:2x2,v4:2x2x1')
  parser.add_argument('--configs', default='obj3d,clevrer')
  parser.add_argument('--dtypes', default='float32,bfloat16')
  parser.add_argument('--json', default='')
  args = parser.parse_args(argv)
  configs = args.configs.split(',')
  for name in configs:
    if name not in CONFIGS:
      print(f'error: --configs: unknown {name!r}, choose from '
            f'{sorted(CONFIGS)}', file=sys.stderr)
      return 2
  dtypes = args.dtypes.split(',')
  for dtype in dtypes:
    if dtype not in precision.COMPUTE_DTYPES:
      print(f'error: --dtypes: unknown {dtype!r}, choose from '
            f'{precision.COMPUTE_DTYPES}', file=sys.stderr)
      return 2
  why = libtpu_missing()
  if why:
    print(f'tpu_kernels: nothing compiled: {why}')
    return 0

  rows, mismatches = [], []
  print('topology  chips  config   dtype     kernels      GFLOP/chip  '
        'GB accessed/chip  HBM GiB/chip  compile s')
  for topology in args.topologies.split(','):
    try:
      devices = tpu_devices(topology)
    except Exception as error:  # libtpu's own message names the problem
      print(f'error: --topologies: {topology!r}: {error}', file=sys.stderr)
      return 2
    for name in configs:
      config = CONFIGS[name]()
      for dtype in dtypes:
        by_form = {}
        for kernels in FORMS:
          row = compile_row(config, kernels, dtype, devices)
          row.update(topology=topology, chips=len(devices), config=name,
                     device_kind=devices[0].device_kind)
          by_form[kernels] = row
          rows.append(row)
          print(f'{topology:9s} {len(devices):5d}  {name:8s} {dtype:9s} '
                f'{kernels:11s} {row["flops"] / 1e9:11.1f}  '
                f'{row["bytes_accessed"] / 1e9:16.2f}  '
                f'{row["hbm_bytes"] / 2**30:12.2f}  '
                f'{row["compile_seconds"]:9.1f}', flush=True)
        auto, plain = by_form[platform.AUTO], by_form[platform.ACCELERATOR]
        if (auto['flops'], auto['bytes_accessed']) != (
            plain['flops'], plain['bytes_accessed']):
          mismatches.append(f'{topology} {name} {dtype}')
  if args.json:
    files.write_json_atomic(args.json, rows)
  if mismatches:
    print("error: kernels='auto' did not compile to the accelerator form "
          f"for a TPU: {', '.join(mismatches)}", file=sys.stderr)
    return 1
  print("kernels='auto' compiled to the accelerator form on every TPU row.")
  return 0


if __name__ == '__main__':
  sys.exit(main())
