r"""Times one real train step on the first local device (a GPU when there
is one): one case per process, so the peak memory is that case's own.

  python benchmarks/gpu_check.py --config=obj3d --step=savi \
      --dtype=bfloat16 [--per_device_batch=16] [--repeats=10] [--json=rows.jsonl]
  python benchmarks/gpu_check.py --smoke ...   # tiny config, 1 step (CPU)
  python benchmarks/gpu_check.py --fed [--reader_workers=2] ...

`--fed` also times the step fed by the real reader (train_batches with
`--reader_workers` worker processes and device prefetch, as the trainer
feeds it, on a converted OBJ3D-like fixture at the step's shapes:
benchmarks/feed_check.py) against the same step on a batch already on the
device, and says 'input-bound' (fed more than 10 % slower) or
'compute-bound'.

benchmarks/gpu_check.sh runs every case and prints the table. The step is
the one the trainer runs (`trainer.jit_update` of the stage built by
`benchmarks/tpu_compile.train_stage`), on a one-device mesh; the state is
initialised as the trainer does it, the batch (and SlotFormer's frozen SAVi
decoder) are random: the timing does not depend on the values. Reported:
median seconds per step after two warm-up steps, the device's
`memory_stats()['peak_bytes_in_use']` (None on CPU), FLOPs per step from
the compiled program's `cost_analysis()` and FLOPs / median seconds.
Nothing is downloaded.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
# tpu_compile keeps jax on CPU unless JAX_PLATFORMS is set: '' = every
# platform jax finds (the GPU).
os.environ.setdefault('JAX_PLATFORMS', '')

import tpu_compile  # noqa: E402  (benchmarks/tpu_compile.py: the builders)
import jax  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh  # noqa: E402

from slotformer_jax.train import optim  # noqa: E402
from slotformer_jax.runtime import sharding  # noqa: E402
from slotformer_jax.train.state import TrainState  # noqa: E402

# The paper (Sec. "Implementation details") trains on servers with 4 GPUs:
# the per-device batch is the config's global batch over 4.
PAPER_GPUS = 4
SMOKE_CONFIGS = {'savi': 'synthetic:tiny', 'slotformer': 'synthetic:tiny',
                 'dvae': 'synthetic:steve_tiny',
                 'steve': 'synthetic:steve_tiny'}


def _random_like(tree, rng: np.random.Generator, token_limit: int):
  def one(x):
    dtype = np.dtype(x.dtype)
    if dtype == np.uint8:
      return rng.integers(0, 256, x.shape, np.uint8)
    if dtype == np.uint16:
      return rng.integers(0, token_limit, x.shape).astype(np.uint16)
    if np.issubdtype(dtype, np.floating):
      return (0.02 * rng.normal(size=x.shape)).astype(dtype)
    return np.zeros(x.shape, dtype)
  return jax.tree.map(one, tree)


def run_case(config_name: str, step: str, dtype: str, per_device_batch,
             repeats: int, compile_only: bool = False, fed: bool = False,
             reader_workers: int = 2, fed_dir: str = '/tmp/gpu_check_feed',
             fed_repeats: int = 20) -> dict | None:
  config = tpu_compile.load_config(config_name)
  config.compute_dtype = dtype
  section = tpu_compile.SECTIONS[step]
  if per_device_batch is None:
    per_device_batch = max(1, config[section].batch_size // PAPER_GPUS)
  config[section].batch_size = per_device_batch
  device = jax.local_devices()[0]
  mesh = Mesh(np.array([device]), (sharding.DATA_AXIS,))
  stage = tpu_compile.train_stage(config, step, mesh)
  update, (abstract_state, batch, frozen) = tpu_compile.step_program(
      config, step, mesh)
  start = time.perf_counter()
  compiled = update.lower(abstract_state, batch, frozen).compile()
  compile_seconds = time.perf_counter() - start
  cost = compiled.cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) else cost
  flops = float(cost['flops'])
  if compile_only:  # fills the persistent compilation cache, if one is set
    return None

  optimizer, _ = optim.make_optimizer(stage.config)
  replicated = sharding.replicated_sharding(mesh)
  state = jax.jit(lambda: TrainState.create(
      stage.init_params(jax.random.key(config.seed)), optimizer),
                  out_shardings=replicated)()
  rng = np.random.default_rng(0)
  token_limit = config.dvae.get('vocab_size', 2) if 'dvae' in config else 2
  batch = jax.device_put(_random_like(batch, rng, token_limit),
                         sharding.batch_sharding(mesh))
  frozen = (None if frozen is None else
            jax.device_put(_random_like(frozen, rng, 2), replicated))
  times = []
  for index in range(repeats + 2):
    begin = time.perf_counter()
    state, metrics = compiled(state, batch, frozen)
    jax.block_until_ready(metrics['loss'])
    if index >= 2:  # two warm-up steps
      times.append(time.perf_counter() - begin)
  median = float(np.median(times))
  stats = device.memory_stats() or {}
  peak = stats.get('peak_bytes_in_use')
  feed = {}
  if fed:
    import feed_check  # pylint: disable=g-import-not-at-top
    feed = feed_check.time_fed_vs_resident(
        compiled, state, frozen, batch, mesh,
        frame_stride=config[section].get('frame_stride', 1),
        reader_workers=reader_workers, repeats=fed_repeats,
        workdir=Path(fed_dir))
    print(f'{config_name} {step} {dtype}: {feed["fed_ms"]:.1f} ms per step '
          f'fed by the reader ({reader_workers} worker processes, device '
          f'prefetch) vs {feed["resident_ms"]:.1f} ms on a batch already on '
          f'the device: {feed["verdict"]} (x{feed["fed_over_resident"]:.2f}; '
          f'batch {feed["batch_mib"]:.1f} MiB)', file=sys.stderr, flush=True)
  return dict(**feed, config=config_name, step=step, dtype=dtype,
              per_device_batch=per_device_batch, device=device.device_kind,
              platform=device.platform, median_seconds=median,
              steps_timed=len(times), peak_bytes=peak, flops=flops,
              tflops_per_second=flops / median / 1e12,
              compile_seconds=compile_seconds,
              loss=float(metrics['loss']))


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--config', default='obj3d')
  parser.add_argument('--step', default='savi',
                      choices=('savi', 'dvae', 'steve', 'slotformer'))
  parser.add_argument('--dtype', default='float32',
                      choices=('float32', 'bfloat16'))
  parser.add_argument('--per_device_batch', type=int, default=None)
  parser.add_argument('--repeats', type=int, default=10)
  parser.add_argument('--smoke', action='store_true',
                      help='the tiny synthetic config, 1 timed step')
  parser.add_argument('--compile_only', action='store_true',
                      help='compile (into $JAX_COMPILATION_CACHE_DIR) only')
  parser.add_argument('--json', default='', help='appends one JSON line')
  parser.add_argument('--fed', action='store_true',
                      help='also time the step fed by the real reader')
  parser.add_argument('--reader_workers', type=int, default=2,
                      help='reader worker processes for --fed')
  parser.add_argument('--fed_repeats', type=int, default=20)
  parser.add_argument('--fed_dir', default='/tmp/gpu_check_feed',
                      help='where --fed writes (and reuses) its fixture')
  args = parser.parse_args(argv)
  config_name, repeats = args.config, args.repeats
  if args.smoke:
    config_name, repeats = SMOKE_CONFIGS[args.step], 1
  try:
    row = run_case(config_name, args.step, args.dtype, args.per_device_batch,
                   repeats, args.compile_only, fed=args.fed,
                   reader_workers=args.reader_workers, fed_dir=args.fed_dir,
                   fed_repeats=(min(args.fed_repeats, 3) if args.smoke
                                else args.fed_repeats))
    if row is None:
      return 0
  except Exception as error:  # pylint: disable=broad-except
    traceback.print_exc()  # the whole story to stderr; the row gets a line
    message = str(error).strip().splitlines()[0][:300] if str(error) else ''
    row = dict(config=config_name, step=args.step, dtype=args.dtype,
               error=f'{type(error).__name__}: {message}')
    print(f'error: {config_name} {args.step} {args.dtype}: {row["error"]}',
          file=sys.stderr)
  if args.json:
    with open(args.json, 'a', encoding='utf-8') as out:
      out.write(json.dumps(row) + '\n')
  print(json.dumps(row))
  return 1 if 'error' in row else 0


if __name__ == '__main__':
  sys.exit(main())
