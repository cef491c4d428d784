"""inference.param_shapes remembers a module's shapes per input shapes."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax import inference


class _Unhashable(nn.Module):
  features: list  # a list field: the module cannot be hashed

  @nn.compact
  def __call__(self, x):
    return nn.Dense(self.features[0])(x)


def test_shapes_follow_the_module_fields_and_the_input_shapes(monkeypatch):
  traced = []
  real = jax.eval_shape
  monkeypatch.setattr(inference.jax, 'eval_shape',
                      lambda f, *a: traced.append(1) or real(f, *a))
  x = np.zeros((2, 5), np.float32)
  first = inference.param_shapes(nn.Dense(3), x)
  assert first['kernel'].shape == (5, 3)
  # An equal module (a new object) and inputs of the same shape: remembered.
  assert inference.param_shapes(nn.Dense(3), np.ones((2, 5), np.float32)) \
      is first
  assert len(traced) == 1
  # Another field, input shape or dtype: traced again.
  assert inference.param_shapes(nn.Dense(4), x)['kernel'].shape == (5, 4)
  assert inference.param_shapes(nn.Dense(3), jnp.zeros((2, 6)))[
      'kernel'].shape == (6, 3)
  assert inference.param_shapes(nn.Dense(3), x.astype(np.float16))[
      'kernel'].dtype == jnp.float32
  assert len(traced) == 4


def test_an_unhashable_module_is_traced_every_time():
  x = np.zeros((2, 5), np.float32)
  before = len(inference._SHAPES_CACHE)  # pylint: disable=protected-access
  for _ in range(2):
    shapes = inference.param_shapes(_Unhashable([3]), x)
    assert shapes['Dense_0']['kernel'].shape == (5, 3)
  assert len(inference._SHAPES_CACHE) == before  # pylint: disable=protected-access
