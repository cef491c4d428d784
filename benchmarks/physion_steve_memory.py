r"""Host memory of STEVE at Physion's 128x128 (`configs/physion_contact.py`)
on a CPU: XLA's scratch of each program, and the max RSS of one process.

  python benchmarks/physion_steve_memory.py scratch 2x50 8x50 16x50
  SLOTFORMER_MALLOC_TUNING=<1|0> python benchmarks/physion_steve_memory.py rss

`scratch`: the temp buffers of one call (`memory_analysis()` of the
compiled program, nothing run) of extraction at each BATCHxFRAMES, of a
STEVE training step at batch 2 x clip 6 and of decoding 8 frames. `rss`:
max RSS after two STEVE training steps at batch 2 (random-free constant
parameters), then after one extraction call of 8 x 50 frames, with the
malloc settings of `runtime/host_memory.py` as $SLOTFORMER_MALLOC_TUNING
says. Results: docs/datasets.md, "Physion".
"""

import resource
import sys

from slotformer_jax.runtime import host_memory

if sys.argv[1] == 'rss':
  host_memory.keep_freed_memory()

import jax  # pylint: disable=g-import-not-at-top,wrong-import-position
import jax.numpy as jnp  # pylint: disable=g-import-not-at-top,wrong-import-position

from slotformer_jax import slot_models  # pylint: disable=g-import-not-at-top,wrong-import-position
from slotformer_jax.config.checks import load_config_file  # pylint: disable=g-import-not-at-top,wrong-import-position


def _rss(label: str) -> None:
  peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
  print(f'{label}: max RSS {peak:.2f} GiB', flush=True)


def main() -> None:
  config = load_config_file('configs/physion_contact.py')
  model = slot_models.get(config)
  shapes = {part.name: jax.eval_shape(lambda part=part: part.module.init(
      {'params': jax.random.key(0), 'sample': jax.random.key(1),
       'dropout': jax.random.key(2)}, *part.example,
      **part.example_kwargs))['params'] for part in model.parts}
  steve = next(part for part in model.parts if part.name == 'steve')
  height, width = config.data.resolution
  batch = {'video': jax.ShapeDtypeStruct((2, 6, height, width, 3), jnp.uint8),
           'tokens': jax.ShapeDtypeStruct((2, 6, 1024), jnp.int32)}
  grad = jax.jit(jax.value_and_grad(
      lambda p, b, f: steve.loss(p, b, f, jax.random.key(0)), has_aux=True))
  frozen = lambda tree: {n: v for n, v in tree.items() if n != 'steve'}
  if sys.argv[1] == 'scratch':
    gib = lambda compiled: compiled.memory_analysis().temp_size_in_bytes / 2**30
    for shape in sys.argv[2:]:
      videos, frames = (int(n) for n in shape.split('x'))
      video = jax.ShapeDtypeStruct((videos, frames, height, width, 3),
                                   jnp.uint8)
      compiled = jax.jit(model.encode).lower(shapes, video, jax.random.key(0),
                                             None).compile()
      print(f'extraction {videos} x {frames} frames: {gib(compiled):.2f} GiB')
    compiled = grad.lower(shapes['steve'], batch, frozen(shapes)).compile()
    print(f'STEVE training step 2 x 6: {gib(compiled):.2f} GiB')
    slots = jax.ShapeDtypeStruct((8, *model.slot_shape), jnp.float32)
    compiled = jax.jit(lambda p, s: model.decode(p, s).recon).lower(
        shapes, slots).compile()
    print(f'decoding 8 frames: {gib(compiled):.2f} GiB')
    return
  params = jax.tree.map(lambda s: jnp.full(s.shape, 0.01, s.dtype), shapes)
  _rss('parameters')
  real = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), batch)
  for _ in range(2):
    jax.block_until_ready(grad(params['steve'], real, frozen(params)))
  _rss('after 2 STEVE training steps')
  jax.block_until_ready(jax.jit(model.encode)(
      params, jnp.zeros((8, 50, height, width, 3), jnp.uint8),
      jax.random.key(0), None))
  _rss('after one extraction call (8 x 50 frames)')


if __name__ == '__main__':
  main()
