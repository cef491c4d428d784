"""Fitting a readout head on fixed slot features, with model selection on
validation only.

Both downstream tasks train a small head (modules/readouts.py) on slot
sequences that are computed once (observed slots, rollouts, ...). The head is
tiny, so the features live in memory and the loop is a plain jitted Adam
step over shuffled minibatches. After every epoch the head is scored on the
validation split; the epoch (checkpoint) and the decision threshold that do
best there are kept. The test split is never seen here (the official scripts
pick both on test; we do not).

Shapes: features [num_examples, time, num_slots, slot_size], labels
[num_examples] in {0, 1}.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

# The official readouts report accuracy at these thresholds; we choose one
# of them on validation.
THRESHOLDS: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)


def readout_bce(logits: jax.Array, labels: jax.Array) -> jax.Array:
  """Mean binary cross-entropy of logits [B] against labels [B] in {0, 1}."""
  return optax.sigmoid_binary_cross_entropy(
      logits, labels.astype(logits.dtype)).mean()


def accuracy_at(probabilities: np.ndarray, labels: np.ndarray,
                threshold: float) -> float:
  """Fraction of ``probabilities > threshold`` that equal ``labels``."""
  return float(((probabilities > threshold) == labels.astype(bool)).mean())


def best_threshold(probabilities: np.ndarray, labels: np.ndarray
                   ) -> tuple[float, float]:
  """(threshold, accuracy) of the best of THRESHOLDS; ties go to 0.5's side."""
  scored = [(accuracy_at(probabilities, labels, t), -abs(t - 0.5), t)
            for t in THRESHOLDS]
  accuracy, _, threshold = max(scored)
  return threshold, accuracy


@dataclasses.dataclass(frozen=True)
class FitConfig:
  """Readout optimisation (official: Adam 1e-3, cosine, 50 epochs)."""

  epochs: int = 50
  batch_size: int = 64
  learning_rate: float = 1e-3
  warmup_fraction: float = 0.0
  eval_batch_size: int = 256


def predict(model: nn.Module, params: Any, features: np.ndarray,
            batch_size: int = 256) -> np.ndarray:
  """float32 [num_examples] success / contact probabilities."""
  apply = _jitted_apply(model)
  out = [np.asarray(jax.nn.sigmoid(apply(params, jnp.asarray(
      features[i:i + batch_size])))) for i in range(0, len(features),
                                                     batch_size)]
  return np.concatenate(out).astype(np.float32)


_APPLY_CACHE: dict[int, Callable] = {}


def _jitted_apply(model: nn.Module) -> Callable:
  key = hash(model)
  if key not in _APPLY_CACHE:
    _APPLY_CACHE[key] = jax.jit(lambda p, x: model.apply({'params': p}, x))
  return _APPLY_CACHE[key]


def make_optimizer(fit_config: FitConfig, steps_per_epoch: int
                   ) -> optax.GradientTransformation:
  """Adam with the cosine schedule (after a linear warm-up when
  `fit_config.warmup_fraction` > 0) over all `fit_config.epochs`."""
  total = max(1, steps_per_epoch * fit_config.epochs)
  if fit_config.warmup_fraction == 0.0:
    return optax.adam(optax.cosine_decay_schedule(fit_config.learning_rate,
                                                  total))
  return optax.adam(optax.warmup_cosine_decay_schedule(
      0.0, fit_config.learning_rate,
      max(1, int(fit_config.warmup_fraction * total)), max(total, 2), 0.0))


def make_train_step(model: nn.Module, optimizer: optax.GradientTransformation,
                    seed: int) -> Callable:
  """The jitted step (params, opt_state, features [B, ...], labels [B],
  step index) -> (params, opt_state, loss) that `fit` runs."""
  # A head with dropout (the PHYRE readout's Transformer, officially 0.1)
  # trains with it, one key per step derived from the seed; `predict` and
  # the selection are deterministic.
  dropout = getattr(model, 'dropout_rate', 0.0) > 0
  dropout_key = jax.random.fold_in(jax.random.key(seed), 1)

  @jax.jit
  def step(params, opt_state, x, y, step_index):
    kwargs = {}
    if dropout:
      kwargs = {'deterministic': False, 'rngs': {
          'dropout': jax.random.fold_in(dropout_key, step_index)}}
    loss, grads = jax.value_and_grad(lambda p: readout_bce(
        model.apply({'params': p}, x, **kwargs), y))(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss
  return step


def fit(model: nn.Module, train: tuple[np.ndarray, np.ndarray],
        select: Callable[[Any], float], fit_config: FitConfig, seed: int
        ) -> tuple[Any, dict[str, Any]]:
  """Trains ``model`` on ``train`` and keeps the epoch ``select`` likes best.

  Args:
    model: a readout head, logits [B] from features [B, ...].
    train: (features, labels) of the readout-training split.
    select: params -> validation score (higher is better); it must only look
      at validation data.
    fit_config: optimisation settings.
    seed: initialisation and shuffling seed.

  Returns:
    (best params, log) with log = {'best_epoch', 'best_score', 'scores'
    (per epoch), 'losses' (mean training loss per epoch)}.
  """
  features, labels = train
  if len(features) != len(labels) or not len(features):
    raise ValueError(f'{len(features)} feature rows vs {len(labels)} labels')
  rng = np.random.default_rng(seed)
  batch_size = min(fit_config.batch_size, len(features))
  steps_per_epoch = len(features) // batch_size
  optimizer = make_optimizer(fit_config, steps_per_epoch)
  params = model.init(jax.random.key(seed),
                      jnp.asarray(features[:1]))['params']
  opt_state = optimizer.init(params)
  step = make_train_step(model, optimizer, seed)

  best = (-np.inf, None, -1)
  log: dict[str, Any] = {'scores': [], 'losses': []}
  for epoch in range(fit_config.epochs):
    order = rng.permutation(len(features))
    losses = []
    for i in range(steps_per_epoch):
      index = order[i * batch_size:(i + 1) * batch_size]
      params, opt_state, loss = step(params, opt_state,
                                     jnp.asarray(features[index]),
                                     jnp.asarray(labels[index]),
                                     epoch * steps_per_epoch + i)
      losses.append(float(loss))
    score = float(select(params))
    log['scores'].append(score)
    log['losses'].append(float(np.mean(losses)))
    if score > best[0]:
      best = (score, jax.tree.map(np.asarray, params), epoch)
  log['best_score'], log['best_epoch'] = best[0], best[2]
  return best[1], log
