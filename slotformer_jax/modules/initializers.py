"""PyTorch's default initialisation, applied to this project's parameter trees.

The official models are trained from PyTorch's defaults, which differ from
flax's (lecun-normal kernels, zero biases, orthogonal recurrent kernels):
  Linear / Conv2d   kernel and bias U(-b, b), b = 1 / sqrt(fan_in)
                    (kaiming-uniform with a = sqrt(5) gives exactly this b);
  ConvTranspose2d   the same with fan_in = C_out * K * K (PyTorch computes
                    the fan from dimension 1 of its [C_in, C_out, K, K]
                    weight);
  GRU / LSTM        every weight and bias U(-b, b), b = 1 / sqrt(hidden);
                    where PyTorch adds two biases (b_ih + b_hh) that flax
                    keeps as one, the flax bias is a sum of two draws;
  MultiheadAttention  query / key / value kernels xavier-uniform over the
                    packed [3D, D] in-projection (b = sqrt(6 / (4D))), their
                    biases 0; the output kernel as a Linear, its bias 0;
  LayerNorm         scale 1, bias 0 (as flax).
Learned initial slots keep their N(0, 1) draw (also the official one).
Every other kernel is re-drawn, including zero-initialised ones of
non-official variants (SlotFormer's `residual` refinement).

`pytorch_default_init` rewrites a parameter tree by the module names used in
slotformer_jax/modules: rules are chosen from the path of each parameter,
so it applies to SAVi, its decoder and SlotFormer alike.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

FLAX = 'flax'
PYTORCH = 'pytorch'
INITIALIZATIONS = (FLAX, PYTORCH)

# flax GRUCell / OptimizedLSTMCell biases that stand for PyTorch's
# b_ih + b_hh (GRU: the reset and update gates; LSTM: every gate).
_SUMMED_RECURRENT_BIASES = {'gru': ('ir', 'iz'),
                            'lstm': ('hi', 'hf', 'hg', 'ho')}
_ATTENTION_PROJECTIONS = ('query', 'key', 'value')


def _names(path) -> tuple[str, ...]:
  return tuple(str(getattr(entry, 'key', entry)) for entry in path)


def _uniform(rng, shape, bound):
  return jax.random.uniform(rng, shape, jnp.float32, -bound, bound)


def _recurrent_hidden_size(names, params) -> int:
  """Hidden size of the GRU / LSTM cell at `names` (its gate width)."""
  return next(iter(_layer(names, params).values()))['kernel'].shape[-1]


def _initial_value(names: tuple[str, ...], shape: tuple[int, ...],
                   rng: jax.Array, params: Any) -> jax.Array | None:
  """PyTorch's initial value of one parameter, or None to keep it."""
  leaf, parent = names[-1], names[:-1]
  module = parent[-1] if parent else ''
  # LayerNorm (flax's only 'scale'), or a parameter outside any layer.
  if leaf == 'scale':
    return jnp.ones(shape, jnp.float32)
  if leaf not in ('kernel', 'bias'):
    return None
  if len(parent) >= 2 and parent[-2] in _SUMMED_RECURRENT_BIASES:
    cell = parent[-2]
    bound = 1.0 / np.sqrt(_recurrent_hidden_size(parent[:-1], params))
    if leaf == 'bias' and module in _SUMMED_RECURRENT_BIASES[cell]:
      first, second = jax.random.split(rng)
      return _uniform(first, shape, bound) + _uniform(second, shape, bound)
    return _uniform(rng, shape, bound)
  if len(parent) >= 2 and parent[-2] == 'attention':
    # nn.MultiHeadDotProductAttention: kernels [D, H, D/H] / [H, D/H, D].
    if leaf == 'bias':
      return jnp.zeros(shape, jnp.float32)
    if module in _ATTENTION_PROJECTIONS:
      dim = shape[0]
      return _uniform(rng, shape, np.sqrt(6.0 / (dim + 3 * dim)))
    if module == 'out':
      return _uniform(rng, shape, 1.0 / np.sqrt(np.prod(shape[:-1])))
  if leaf == 'bias':
    layer = _layer(parent, params)
    if 'scale' in layer:  # LayerNorm
      return jnp.zeros(shape, jnp.float32)
    kernel_shape = layer['kernel'].shape
    return _uniform(rng, shape, 1.0 / np.sqrt(
        _fan_in(kernel_shape, transposed=module.startswith('deconv_'))))
  return _uniform(rng, shape, 1.0 / np.sqrt(
      _fan_in(shape, transposed=module.startswith('deconv_'))))


def _layer(parent, params) -> dict[str, Any]:
  layer = params
  for name in parent:
    layer = layer[name]
  return layer


def _fan_in(kernel_shape: tuple[int, ...], transposed: bool) -> int:
  """PyTorch's fan_in of a flax kernel ([in, out] or [K, K, in, out]).

  The decoder's 'deconv_*' layers are PyTorch ConvTranspose2d layers, whose
  fan_in is computed from their *output* channels.
  """
  receptive = int(np.prod(kernel_shape[:-2]))
  channels = kernel_shape[-1] if transposed else kernel_shape[-2]
  return receptive * channels


def pytorch_default_init(params: Any, rng: jax.Array) -> Any:
  """A copy of `params` drawn from PyTorch's default initialisation.

  Args:
    params: a flax parameter tree of slotformer_jax modules.
    rng: PRNG key.

  Returns:
    a tree of the same structure, shapes and dtypes.
  """
  leaves, treedef = jax.tree_util.tree_flatten_with_path(params)
  keys = jax.random.split(rng, len(leaves))
  new_leaves = []
  for (path, value), key in zip(leaves, keys):
    names = _names(path)
    new = _initial_value(names, tuple(value.shape), key, params)
    new_leaves.append(value if new is None else new.astype(value.dtype))
  return jax.tree_util.tree_unflatten(treedef, new_leaves)


def initialize(params: Any, rng: jax.Array, kind: str) -> Any:
  """`params` as initialised by flax ('flax') or re-drawn as PyTorch's."""
  if kind == FLAX:
    return params
  if kind == PYTORCH:
    return pytorch_default_init(params, rng)
  raise ValueError(f'init must be one of {INITIALIZATIONS}, got {kind!r}')
