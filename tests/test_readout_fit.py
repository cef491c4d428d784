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
