r"""Parameter counts of this project's SAVi-S and SAVi++ next to SAVi's own.

  python benchmarks/param_counts.py

Builds this project's SAVi (`slot_models.savi.build_savi`) as
configs/movi.py's `:savis` and `:savipp` ship it (SAVi's
`configs/movi/savi_conditional_small.py` and `savi++_conditional.py`), and
counts the parameters of each part with `jax.eval_shape` (nothing is
computed). SAVi's counts are those of its own flax modules as its configs
build them (google-research/slot-attention-video at ba8f15e, built with
`jax.eval_shape` outside this repository: its package imports TensorFlow
and clu only through `savi.lib.utils`, whose five helpers the modules use
were stubbed; flax's GRUCell now needs `features`, given from the carry),
recorded below; `savi_parts_by_hand` recomputes each from the layer
definitions, and the script checks the two agree. SAVi stores each
PositionEmbedding's constant coordinate grid as a parameter (never
trained); the table counts it apart. docs/savi_plus_plus.md has the table
and what explains every difference.
"""

from __future__ import annotations

import importlib.util
import os
import sys

os.environ.setdefault('JAX_PLATFORMS', 'cpu')

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from slotformer_jax.slot_models.savi import build_savi  # noqa: E402

PARTS = ('encoder', 'initializer', 'corrector', 'predictor', 'decoder')

# SAVi's own modules, counted with jax.eval_shape (see the docstring):
# {part: (parameters, of which constant position grids)}.
SAVI_MEASURED = {
    'SAVi-S': {'encoder': (91_872, 8_192), 'initializer': (34_176, 0),
               'corrector': (123_712, 0), 'predictor': (132_480, 0),
               'decoder': (513_028, 128)},
    'SAVi++': {'encoder': (21_975_232, 512), 'initializer': (34_176, 0),
               'corrector': (213_888, 0), 'predictor': (395_776, 0),
               'decoder': (513_093, 128)},
}


def dense(n_in: int, n_out: int, bias: bool = True) -> int:
  return n_in * n_out + (n_out if bias else 0)


def conv(size: int, n_in: int, n_out: int, bias: bool = True) -> int:
  return size * size * n_in * n_out + (n_out if bias else 0)


def layer_norm(n: int) -> int:
  return 2 * n


def gru(n_in: int, hidden: int) -> int:
  """flax GRUCell: input kernels + biases of three gates, hidden kernels
  of three gates, the candidate's hidden bias."""
  return 3 * dense(n_in, hidden) + 3 * hidden * hidden + hidden


def attention(dim: int, qkv: int) -> int:
  """flax MultiHeadDotProductAttention (biased q / k / v / out)."""
  return 3 * dense(dim, qkv) + dense(qkv, dim)


def transformer_block(dim: int, qkv: int, mlp: int) -> int:
  """Self-attention, MLP (one hidden layer), two LayerNorms."""
  return (attention(dim, qkv) + dense(dim, mlp) + dense(mlp, dim)
          + 2 * layer_norm(dim))


def resnet34(channels_in: int = 3, width: int = 64) -> int:
  """3x3 convolutions without bias, GroupNorm (scale + bias), a projected
  first block in stages 2-4."""
  count = conv(3, channels_in, width, bias=False) + 2 * width
  channels = width
  for stage, blocks in enumerate((3, 4, 6, 3)):
    out = width * 2**stage
    for block in range(blocks):
      count += conv(3, channels, out, False) + conv(3, out, out, False)
      count += 4 * out
      if stage > 0 and block == 0:
        count += conv(1, channels, out, False) + 2 * out
      channels = out
  return count


def position_embedding(grid: tuple[int, int], channels: int) -> tuple[int, int]:
  """SAVi's 'linear' / 'project_add' PositionEmbedding: Dense(2 -> C) of a
  [-1, 1] grid, which it stores as a parameter [1, h, w, 2]."""
  constant = grid[0] * grid[1] * 2
  return dense(2, channels) + constant, constant


def savi_parts_by_hand(model: str) -> dict[str, tuple[int, int]]:
  """SAVi's parameters per part from its layer definitions:
  {part: (parameters, of which constant position grids)}."""
  slot, boxes_mlp = 128, dense(4, 256) + dense(256, 128)
  if model == 'SAVi-S':  # 64x64 frames
    cnn = conv(5, 3, 32) + 3 * conv(5, 32, 32)
    embedding, grid = position_embedding((64, 64), 32)
    mlp = layer_norm(32) + dense(32, 64) + dense(64, 32)
    encoder, features, qkv, mlp_size = cnn + embedding + mlp, 32, 128, 256
    decoder_first = 'stride 1 last'
    targets = (3,)
  else:  # SAVi++, 128x128 frames
    embedding, grid = position_embedding((16, 16), 512)
    mlp = layer_norm(512) + dense(512, 64) + dense(64, 512)
    encoder = (resnet34() + embedding + mlp + dense(512, 64)
               + 4 * transformer_block(64, 64, 1024))
    features, qkv, mlp_size = 64, 256, 1024
    decoder_first = 'all stride 2'
    targets = (3, 1)
  del decoder_first  # the strides do not change the count
  # Slot Attention without an MLP (mlp_size None in SAVi's configs): input
  # LayerNorm, k / v / q projections without bias, the query LayerNorm,
  # the GRU over qkv-sized updates.
  corrector = (layer_norm(features) + 2 * dense(features, qkv, False)
               + dense(slot, qkv, False) + layer_norm(slot) + gru(qkv, slot))
  predictor = transformer_block(slot, qkv, mlp_size)
  decoder_embedding, decoder_grid = position_embedding((8, 8), slot)
  decoder = (decoder_embedding + conv(5, slot, 64) + 3 * conv(5, 64, 64)
             + dense(64, 1) + sum(dense(64, c) for c in targets))
  return {'encoder': (encoder, grid), 'initializer': (boxes_mlp, 0),
          'corrector': (corrector, 0), 'predictor': (predictor, 0),
          'decoder': (decoder, decoder_grid)}


# The shipped configs of these models (configs/movi.py's variants).
VARIANTS = {'SAVi-S': 'savis', 'SAVi++': 'savipp'}


def ours(model: str):
  """This project's SAVi as configs/movi.py ships `model` (its variant in
  VARIANTS): (config.savi, resolution). No parameter depends on the number
  of slots (11 on MOVi-A, 24 on MOVi-E)."""
  spec = importlib.util.spec_from_file_location(
      'movi_config', os.path.join(ROOT, 'configs', 'movi.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  config = module.get_config(VARIANTS[model])
  return config.savi, tuple(config.data.resolution)


def count(tree) -> int:
  return sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree))


def our_parts(model: str) -> dict[str, int]:
  savi, resolution = ours(model)
  module = build_savi(savi, resolution)
  params = jax.eval_shape(
      lambda: module.init(
          {'params': jax.random.key(0), 'sample': jax.random.key(1)},
          jnp.zeros((1, 1, *resolution, 3)),
          boxes=jnp.zeros((1, savi.num_slots - 1, 4))))['params']
  frame_step = params.pop('frame_step')
  parts = {'encoder': count(params.pop('encoder')),
           'decoder': count(params.pop('decoder')),
           'corrector': count(frame_step.pop('corrector')),
           'predictor': count(frame_step.pop('predictor'))}
  if frame_step:
    raise AssertionError(f'uncounted: {list(frame_step)}')
  parts['initializer'] = count(params)  # what is left: the initialiser's
  return parts


def main() -> None:
  for model in SAVI_MEASURED:
    by_hand = savi_parts_by_hand(model)
    if by_hand != SAVI_MEASURED[model]:
      raise AssertionError(f'{model}: by hand {by_hand} != measured '
                           f'{SAVI_MEASURED[model]}')
    mine = our_parts(model)
    print(f'{model}            ours     SAVi (trained + constant grid)'
          '   ours - SAVi trained')
    totals = [0, 0, 0]
    for part in PARTS:
      theirs, grid = SAVI_MEASURED[model][part]
      trained = theirs - grid
      totals = [totals[0] + mine[part], totals[1] + trained,
                totals[2] + grid]
      print(f'  {part:<12} {mine[part]:>12,} {trained:>12,} + {grid:>6,}'
            f'   {mine[part] - trained:>+10,}')
    print(f'  {"total":<12} {totals[0]:>12,} {totals[1]:>12,} + '
          f'{totals[2]:>6,}   {totals[0] - totals[1]:>+10,}')
    print()


if __name__ == '__main__':
  main()
