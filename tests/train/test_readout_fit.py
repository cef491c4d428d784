"""The readout fitting loop: learns a separable task, selects on validation."""

from __future__ import annotations

import numpy as np

from slotformer_jax.modules import readouts
from slotformer_jax.tasks import readout


def _contact_like(num, seed):
  """Label 1 iff some slot of some frame has a large first feature (an
  'event' a max over pairs and frames can find)."""
  rng = np.random.default_rng(seed)
  x = rng.normal(size=(num, 3, 3, 4)).astype(np.float32)
  y = np.arange(num) % 2
  for i in np.flatnonzero(y):
    x[i, rng.integers(3), rng.integers(3), 0] += 8.0
  return x, y.astype(np.float32)


def test_best_threshold():
  probs = np.array([0.2, 0.4, 0.6, 0.8])
  labels = np.array([0, 0, 1, 1])
  assert readout.best_threshold(probs, labels) == (0.5, 1.0)
  # 0.3 and 0.5 both get 3/4 on these; the tie goes to 0.5.
  assert readout.best_threshold(np.array([0.2, 0.4, 0.45, 0.8]),
                                labels) == (0.5, 0.75)


def test_fit_learns_and_keeps_the_best_validation_epoch():
  train, val = _contact_like(256, 0), _contact_like(128, 1)
  model = readouts.PhysionReadout(features=32, pairs='both_orders')
  val_scores = []

  def select(params):
    probs = readout.predict(model, params, val[0])
    val_scores.append(readout.best_threshold(probs, val[1])[1])
    return val_scores[-1]

  params, log = readout.fit(
      model, train, select,
      readout.FitConfig(epochs=8, batch_size=32, learning_rate=3e-3), seed=0)
  assert log['scores'] == val_scores
  assert log['best_epoch'] == int(np.argmax(val_scores))
  probs = readout.predict(model, params, val[0])
  assert readout.best_threshold(probs, val[1])[1] == max(val_scores)
  assert max(val_scores) > 0.8
  assert log['losses'][-1] < log['losses'][0]


def test_fit_trains_with_the_heads_dropout():
  """The PHYRE readout with dropout_rate > 0 (the official 0.1) is trained
  with dropout (other losses than without it, from the same seed and
  batches) and predicts deterministically."""
  x, y = _contact_like(64, 2)
  config = readout.FitConfig(epochs=2, batch_size=16, learning_rate=1e-3)
  logs = {}
  for rate in (0.0, 0.3):
    model = readouts.PhyreReadout(selected_steps=(0, 2), embed_dim=8,
                                  num_layers=1, num_heads=2, mlp_size=16,
                                  dropout_rate=rate)
    params, logs[rate] = readout.fit(model, (x, y), lambda p: 0.0, config,
                                     seed=0)
    np.testing.assert_array_equal(readout.predict(model, params, x),
                                  readout.predict(model, params, x))
  assert logs[0.0]['losses'][0] != logs[0.3]['losses'][0]
