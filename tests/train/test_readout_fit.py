"""The readout fit (stages/readout_fit.py) through the shared trainer: it
learns a separable task, selects on validation, keeps the readout protocol
(the order, schedule, init and dropout keys of the loop it replaced) and
resumes to the same selection."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from slotformer_jax.modules import readouts
from slotformer_jax.stages import readout_fit
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


def test_fit_learns_and_keeps_the_best_validation_epoch(tmp_path):
  train, val = _contact_like(256, 0), _contact_like(128, 1)
  model = readouts.PhysionReadout(features=32, pairs='both_orders')
  val_scores = []

  def select(params):
    probs = readout.predict(model, params, val[0])
    val_scores.append(readout.best_threshold(probs, val[1])[1])
    return val_scores[-1]

  params, log = readout_fit.fit_readout(
      str(tmp_path), 'readout', model, train, select,
      readout.FitConfig(epochs=8, batch_size=32, learning_rate=3e-3), seed=0)
  assert log['scores'] == val_scores
  assert log['best_epoch'] == int(np.argmax(val_scores))
  probs = readout.predict(model, params, val[0])
  assert readout.best_threshold(probs, val[1])[1] == max(val_scores)
  assert max(val_scores) > 0.8
  assert log['losses'][-1] < log['losses'][0]
  # The trainer's files: its checkpoints, one log line per epoch; the
  # epochs' record and the chosen parameters.
  lines = (tmp_path / 'train_log.jsonl').read_text().splitlines()
  assert [json.loads(line)['step'] for line in lines] == list(
      range(8, 65, 8))
  records = [json.loads(line) for line in
             (tmp_path / 'epochs.jsonl').read_text().splitlines()]
  assert [r['score'] for r in records] == val_scores
  assert (tmp_path / 'params.msgpack').exists()
  assert (tmp_path / 'checkpoints').is_dir()


def _reference_fit(model, train, select, fit_config, seed):
  """The readout loop the trainer replaced (a plain jitted Adam step over
  each epoch's permutation), as the reference of the protocol."""
  features, labels = train
  rng = np.random.default_rng(seed)
  batch_size = min(fit_config.batch_size, len(features))
  steps_per_epoch = len(features) // batch_size
  optimizer, _ = readout.make_optimizer(fit_config, steps_per_epoch)
  params = model.init(jax.random.key(seed),
                      jnp.asarray(features[:1]))['params']
  opt_state = optimizer.init(params)
  dropout_key = jax.random.fold_in(jax.random.key(seed), 1)

  @jax.jit
  def step(params, opt_state, x, y, index):
    def loss_fn(p):
      return readout.readout_bce(model.apply(
          {'params': p}, x, deterministic=False,
          rngs={'dropout': jax.random.fold_in(dropout_key, index)}), y)
    loss, grads = jax.value_and_grad(loss_fn)(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss

  scores, losses, best = [], [], (-np.inf, None, -1)
  for epoch in range(fit_config.epochs):
    order = rng.permutation(len(features))
    epoch_losses = []
    for i in range(steps_per_epoch):
      index = order[i * batch_size:(i + 1) * batch_size]
      params, opt_state, loss = step(params, opt_state,
                                     jnp.asarray(features[index]),
                                     jnp.asarray(labels[index]),
                                     epoch * steps_per_epoch + i)
      epoch_losses.append(float(loss))
    scores.append(float(select(params)))
    losses.append(float(np.mean(epoch_losses)))
    if scores[-1] > best[0]:
      best = (scores[-1], jax.tree.map(np.asarray, params), epoch)
  return best[1], {'scores': scores, 'losses': losses, 'best_epoch': best[2]}


def _dropout_head(rate=0.3):
  return readouts.PhyreReadout(selected_steps=(0, 2), embed_dim=8,
                               num_layers=1, num_heads=2, mlp_size=16,
                               dropout_rate=rate)


def test_fit_keeps_the_readout_protocol(tmp_path):
  """The same initialisation, batches, schedule (with warm-up) and dropout
  keys as the reference loop: the same epochs are chosen and the
  parameters agree to float32 rounding (the trainer's step is another
  program: it also computes the gradient and parameter norms)."""
  x, y = _contact_like(70, 3)  # 70 % 16: an epoch leaves 6 unused
  val = _contact_like(32, 4)
  model = _dropout_head()
  config = readout.FitConfig(epochs=4, batch_size=16, learning_rate=3e-3,
                             warmup_fraction=0.25)

  def select(params):
    return float(-np.mean((readout.predict(model, params, val[0])
                           - val[1]) ** 2))

  params, log = readout_fit.fit_readout(str(tmp_path), 'readout', model,
                                        (x, y), select, config, seed=7)
  expected, expected_log = _reference_fit(model, (x, y), select, config, 7)
  assert log['best_epoch'] == expected_log['best_epoch']
  np.testing.assert_allclose(log['losses'], expected_log['losses'],
                             rtol=1e-5)
  np.testing.assert_allclose(log['scores'], expected_log['scores'],
                             rtol=1e-4, atol=1e-6)
  # The attention's key bias adds the same logit to every key, which softmax
  # ignores: its gradient is zero but for rounding, and Adam scales that
  # noise up to a step, so its values follow the compiler's rounding (they
  # differ at 1e-5 between XLA:CPU's two emitters). Every other leaf agrees.
  def compare(path, a, b):
    if jax.tree_util.keystr(path).endswith("['attention']['key']['bias']"):
      return
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6,
                               err_msg=jax.tree_util.keystr(path))

  jax.tree_util.tree_map_with_path(compare, params, expected)


def test_fit_trains_with_the_heads_dropout(tmp_path):
  """The PHYRE readout with dropout_rate > 0 (the official 0.1) is trained
  with dropout (other losses than without it, from the same seed and
  batches) and predicts deterministically."""
  x, y = _contact_like(64, 2)
  config = readout.FitConfig(epochs=2, batch_size=16, learning_rate=1e-3)
  logs = {}
  for rate in (0.0, 0.3):
    model = _dropout_head(rate)
    params, logs[rate] = readout_fit.fit_readout(
        str(tmp_path / str(rate)), 'readout', model, (x, y), lambda p: 0.0,
        config, seed=0)
    np.testing.assert_array_equal(readout.predict(model, params, x),
                                  readout.predict(model, params, x))
  assert logs[0.0]['losses'][0] != logs[0.3]['losses'][0]


class _Stop(Exception):
  pass


def test_an_interrupted_fit_resumes_to_the_same_selection(tmp_path):
  """Killed while scoring epoch 2 (its checkpoint not yet saved), the rerun
  resumes from epoch 1's and ends with the parameters (epoch 1's, the
  best: read back), scores and losses of an uninterrupted fit; a finished
  fit is not trained again."""
  x, y = _contact_like(64, 5)
  val = _contact_like(32, 6)
  model = _dropout_head(0.1)
  config = readout.FitConfig(epochs=5, batch_size=16, learning_rate=3e-3)
  calls = []

  def select(params, stop_at=None):
    calls.append(1)
    if stop_at is not None and len(calls) == stop_at:
      raise _Stop()
    accuracy = np.mean((readout.predict(model, params, val[0]) > 0.5)
                       == val[1])
    return float(accuracy) + float(len(calls) == 2)

  whole, whole_log = readout_fit.fit_readout(
      str(tmp_path / 'a'), 'readout', model, (x, y), select, config, 1)
  calls.clear()
  with pytest.raises(_Stop):
    readout_fit.fit_readout(str(tmp_path / 'b'), 'readout', model, (x, y),
                            lambda p: select(p, stop_at=3), config, 1)
  calls.clear()
  calls.append(1)  # epochs 0 and 1 were scored before: the rerun's first
  calls.append(1)  # call is epoch 2's (len(calls) == 3, never 2 again)
  resumed, resumed_log = readout_fit.fit_readout(
      str(tmp_path / 'b'), 'readout', model, (x, y), select, config, 1)
  assert len(calls) == 2 + 3  # epochs 2, 3, 4 scored after the resume
  assert resumed_log == whole_log
  assert whole_log['best_epoch'] == 1  # the bonus of the second call
  jax.tree.map(np.testing.assert_array_equal, resumed, whole)
  calls.clear()
  again, again_log = readout_fit.fit_readout(
      str(tmp_path / 'b'), 'readout', model, (x, y), select, config, 1)
  assert not calls and again_log == whole_log
  jax.tree.map(np.testing.assert_array_equal, again, whole)
