"""The Slot-LSTM baseline: rollout semantics and slot symmetry."""

import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax.modules.slot_lstm import SlotLSTM
from slotformer_jax.modules.slot_lstm import SlotLSTMStep

_SIZES = dict(embed_dim=16, num_layers=1, num_heads=2, mlp_size=32)


def _model_and_params(burn_in=3, num_steps=4):
  model = SlotLSTM(burn_in=burn_in, **_SIZES)
  history = jax.random.normal(jax.random.key(0), (2, burn_in, 4, 8))
  params = model.init(jax.random.key(1), history, num_steps)
  return model, params, history


def _step_by_step(params, history, num_steps, teacher=None):
  """The rollout written as a Python loop over SlotLSTMStep."""
  step = SlotLSTMStep(**_SIZES)
  step_params = {'params': params['params']['step']}
  batch, burn_in, num_slots, _ = history.shape
  zeros = jnp.zeros((batch * num_slots, _SIZES['embed_dim']))
  state, prediction = (zeros, zeros), None
  for t in range(burn_in):
    state, prediction = step.apply(step_params, state, history[:, t])
  outputs = [prediction]
  for k in range(num_steps - 1):
    fed = prediction if teacher is None else teacher[:, k]
    state, prediction = step.apply(step_params, state, fed)
    outputs.append(prediction)
  return jnp.stack(outputs, axis=1)


def test_scan_rollout_equals_python_loop():
  model, params, history = _model_and_params()
  rolled = model.apply(params, history, 4)
  assert rolled.shape == (2, 4, 4, 8)
  np.testing.assert_allclose(rolled, _step_by_step(params, history, 4),
                             rtol=1e-5, atol=1e-5)


def test_teacher_forcing_feeds_the_given_slots():
  model, params, history = _model_and_params()
  teacher = jax.random.normal(jax.random.key(5), (2, 4, 4, 8))
  rolled = model.apply(params, history, 4, teacher_slots=teacher)
  np.testing.assert_allclose(
      rolled, _step_by_step(params, history, 4, teacher), rtol=1e-5,
      atol=1e-5)
  assert not np.allclose(rolled, model.apply(params, history, 4), atol=1e-3)


def test_permutation_equivariant_over_slots():
  model, params, history = _model_and_params()
  permutation = jnp.array([3, 1, 0, 2])
  out = model.apply(params, history, 4)
  out_permuted = model.apply(params, history[:, :, permutation], 4)
  np.testing.assert_allclose(out_permuted, out[:, :, permutation], atol=1e-5)


def test_only_the_last_frame_is_not_enough():
  """Unlike a memoryless model, earlier burn-in frames change the output."""
  model, params, history = _model_and_params()
  changed = history.at[:, 0].add(1.0)
  assert not np.allclose(model.apply(params, history, 1),
                         model.apply(params, changed, 1), atol=1e-4)


def test_residual_variant_starts_as_copy_last():
  model = SlotLSTM(burn_in=3, residual=True, **_SIZES)
  history = jax.random.normal(jax.random.key(0), (2, 3, 4, 8))
  params = model.init(jax.random.key(1), history, 3)
  np.testing.assert_allclose(model.apply(params, history, 3),
                             jnp.repeat(history[:, -1:], 3, axis=1),
                             atol=1e-6)
