r"""What glibc's malloc settings (`slotformer_jax/runtime/host_memory.py`) cost
XLA's compiler: compiles small programs afresh and times them.

  SLOTFORMER_MALLOC_TUNING=<1|0|no-arena-limit> python benchmarks/malloc_compile.py \
      [--programs=20] [--dispatches=3000]

Each program is the gradient of a 12-layer tanh/softmax MLP on a 64 x 128
input, with a different constant, so none is found in jax's caches (the
persistent compilation cache is not enabled here). Then one of them is
dispatched `--dispatches` times. Prints wall, user and system seconds of
each part (`getrusage`, the whole process: XLA's threads included).

Run the settings alternately in one script and compare like with like: a
single arena (`M_ARENA_MAX=1`, the default's first setting) makes the
compiler's threads share one malloc lock, which shows on two or more
cores only (compare `taskset -c 0`). Measured numbers: docs/performance.md,
"Host memory churn".
"""

from __future__ import annotations

import argparse
import os
import resource
import time

from slotformer_jax.runtime import host_memory


def _times():
  usage = resource.getrusage(resource.RUSAGE_SELF)
  return time.perf_counter(), usage.ru_utime, usage.ru_stime


def _since(start) -> str:
  wall, user, system = (b - a for a, b in zip(start, _times()))
  return f'wall {wall:.2f} s, user {user:.2f} s, system {system:.2f} s'


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--programs', type=int, default=20)
  parser.add_argument('--dispatches', type=int, default=3000)
  args = parser.parse_args()
  # Before jax starts its threads, as main.py does.
  applied = host_memory.keep_freed_memory()
  import jax  # pylint: disable=g-import-not-at-top
  import jax.numpy as jnp  # pylint: disable=g-import-not-at-top

  def program(constant: float):
    def loss(x, w):
      for layer in range(12):
        x = jnp.tanh(x @ w + constant + layer) * 0.5
        x = jax.nn.softmax(x, axis=-1) + jnp.sin(x)
      return jnp.sum(x ** 2)
    return jax.jit(jax.grad(loss, argnums=1))

  x, w = jnp.ones((64, 128)), jnp.ones((128, 128))
  print(f'malloc settings: {host_memory.level(os.environ)}'
        f' (applied: {applied})')
  start = _times()
  for index in range(args.programs):
    program(float(index)).lower(x, w).compile()
  print(f'{args.programs} compiles: {_since(start)}')
  step = program(0.0)
  jax.block_until_ready(step(x, w))
  start = _times()
  for _ in range(args.dispatches):
    out = step(x, w)
  jax.block_until_ready(out)
  print(f'{args.dispatches} dispatches: {_since(start)}')


if __name__ == '__main__':
  main()
