r"""On CPU: the CPU forms against the accelerator forms of the layers that
have both (`slotformer_jax.modules.platform`), time and difference.

  python benchmarks/kernel_forms_cpu.py [--repeats=20] [--cases=decoder,slotformer]

Cases (shapes as `benchmarks/step_time.py`):
  decoder     CLEVRER SAVi decoder forward + backward (parameters and
              slots), 168 slot images 64x64: phase-split transposed
              convolutions and x @ I kernel gradients vs the plain
              `lax.conv_general_dilated`;
  slotformer  OBJ3D SlotFormer, batch 32, 6 burn-in + 10 rolled-out frames,
              gradient of the squared error of the rollout: flax's explicit
              attention vs `jax.nn.dot_product_attention`.

Both forms are compiled in one process and called alternately; prints the
median seconds of each and the largest |difference| of the outputs and
gradients between them. The default (`kernels='auto'`) is the CPU form on
CPU; this is what keeps it so.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..'))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'configs'))

from slotformer_jax.runtime import xla_flags  # noqa: E402  (imports no jax)

ADDED_FLAGS = xla_flags.apply_fast_cpu_flags()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import clevrer  # noqa: E402  (configs/clevrer.py)
import obj3d  # noqa: E402  (configs/obj3d.py)
from slotformer_jax.modules import platform  # noqa: E402
from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax.slot_models.savi import build_decoder

FORMS = (platform.CPU, platform.ACCELERATOR)


def decoder_case(num_images: int = 4 * 6):
  """{form: jitted () -> (loss, grads)} of the CLEVRER decoder."""
  config = clevrer.get_config()
  rng = np.random.default_rng(0)
  slots = jnp.asarray(rng.normal(size=(
      num_images, config.savi.num_slots, config.savi.slot_size)), jnp.float32)
  base = build_decoder(config.savi.decoder,
                              tuple(config.data.resolution))
  params = base.init(jax.random.key(0), slots[:1])['params']
  runs = {}
  for form in FORMS:
    decoder = base.clone(kernels=form)

    def loss(params, slots, decoder=decoder):
      recon = decoder.apply({'params': params}, slots).recon
      return jnp.mean(jnp.square(recon))

    grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    runs[form] = lambda grad=grad: grad(params, slots)
  return runs


def slotformer_case(batch_size: int = 32):
  config = obj3d.get_config()
  dyn = config.slotformer
  rng = np.random.default_rng(0)
  slots = jnp.asarray(rng.normal(size=(
      batch_size, dyn.burn_in + dyn.rollout, config.savi.num_slots,
      config.savi.slot_size)), jnp.float32)
  burn_in, future = slots[:, :dyn.burn_in], slots[:, dyn.burn_in:]
  base = dynamics_lib.build(config.slotformer, 'slotformer')
  params = base.init(jax.random.key(0), burn_in[:1], dyn.rollout)['params']
  runs = {}
  for form in FORMS:
    model = base.clone(kernels=form)

    def loss(params, model=model):
      predicted = model.apply({'params': params}, burn_in, dyn.rollout)
      return jnp.mean(jnp.square(predicted - future))

    grad = jax.jit(jax.value_and_grad(loss))
    runs[form] = lambda grad=grad: grad(params)
  return runs


CASES = {'decoder': decoder_case, 'slotformer': slotformer_case}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--repeats', type=int, default=20)
  parser.add_argument('--cases', default=','.join(CASES))
  args = parser.parse_args(argv)
  for name in args.cases.split(','):
    if name not in CASES:
      print(f'error: --cases: unknown {name!r}, choose from {sorted(CASES)}',
            file=sys.stderr)
      return 2
  print(f'jax {jax.__version__}, fast XLA:CPU flags added: '
        f'{ADDED_FLAGS or "none"}')
  for name in args.cases.split(','):
    runs = CASES[name]()
    results = {form: jax.block_until_ready(run()) for form, run in
               runs.items()}  # compile + warm-up
    times = {form: [] for form in runs}
    for _ in range(args.repeats):
      for form, run in runs.items():
        start = time.perf_counter()
        jax.block_until_ready(run())
        times[form].append(time.perf_counter() - start)
    difference = max(jax.tree.leaves(jax.tree.map(
        lambda a, b: float(jnp.max(jnp.abs(a - b))),
        results[platform.CPU], results[platform.ACCELERATOR])))
    scale = max(jax.tree.leaves(jax.tree.map(
        lambda a: float(jnp.max(jnp.abs(a))), results[platform.CPU])))
    medians = {form: float(np.median(t)) for form, t in times.items()}
    print(f'{name}: cpu form {medians[platform.CPU]:.3f} s, accelerator '
          f'form {medians[platform.ACCELERATOR]:.3f} s (median of '
          f'{args.repeats}, alternated); max |difference| of loss and '
          f'gradients {difference:.2e} (largest |value| {scale:.2e})',
          flush=True)
  return 0


if __name__ == '__main__':
  sys.exit(main())
