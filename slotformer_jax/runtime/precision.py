"""`config.compute_dtype`: bfloat16 compute with float32 parameters.

The parameters and the optimiser state stay float32 (the update, Adam's
moments and the checkpoint are unchanged); inside the loss / inference
function the float inputs (parameters, frozen parameters, slots) are cast
to the compute dtype, so every matmul and convolution runs in it, and the
results come back as float32. The gradient of the cast is a cast, so the
gradients arrive float32 too. This is mixed precision without loss scaling:
bfloat16 has float32's exponent range (unlike the official code's fp16 AMP).

Values the functions or modules create themselves in float32 (frames mapped
from uint8 to [-1, 1], coordinate grids, noise) would promote the
computation back to float32, so the wrapper also casts the float arguments
of every flax module call (`nn.intercept_methods`): no module needs to know
about the compute dtype.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

FLOAT32 = 'float32'
BFLOAT16 = 'bfloat16'
COMPUTE_DTYPES = (FLOAT32, BFLOAT16)


def check_compute_dtype(name: str) -> None:
  if name not in COMPUTE_DTYPES:
    raise ValueError(f'compute_dtype must be one of {COMPUTE_DTYPES}, '
                     f'got {name!r}')


def cast_floats(tree: Any, dtype: Any) -> Any:
  """Casts the floating-point leaves of `tree` (others, e.g. uint8 frames,
  integer ids and PRNG keys, are left alone)."""

  def cast(x):
    if (isinstance(x, (jax.Array, np.ndarray))
        and jnp.issubdtype(x.dtype, jnp.floating)):
      return jnp.asarray(x).astype(dtype)
    return x

  return jax.tree.map(cast, tree)


def with_compute_dtype(fn: Callable[..., Any], compute_dtype: str
                       ) -> Callable[..., Any]:
  """`fn` computing in `compute_dtype`, float32 in and out.

  Every float argument is cast to the compute dtype before `fn`, every
  float result back to float32 after it. 'float32' returns `fn` itself, so
  the default path is unchanged.
  """
  check_compute_dtype(compute_dtype)
  if compute_dtype == FLOAT32:
    return fn
  dtype = jnp.dtype(compute_dtype)

  def cast_module_inputs(next_fun, args, kwargs, context):
    # Modules also build float32 values of their own (coordinate grids,
    # noise); casting at every module call keeps the whole model in `dtype`.
    if context.method_name == '__call__':
      args, kwargs = cast_floats((args, kwargs), dtype)
    return next_fun(*args, **kwargs)

  def wrapped(*args, **kwargs):
    args, kwargs = cast_floats((args, kwargs), dtype)
    with nn.intercept_methods(cast_module_inputs):
      out = fn(*args, **kwargs)
    return cast_floats(out, jnp.float32)

  wrapped.__name__ = getattr(fn, '__name__', 'fn')
  wrapped.__doc__ = getattr(fn, '__doc__', None)
  return wrapped
