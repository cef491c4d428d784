"""A readout head on fixed slot features: its loss, its training batches,
its optimiser, its predictions, and the decision thresholds.

Both downstream tasks train a small head (modules/readouts.py) on slot
sequences that are computed once (observed slots, rollouts, ...), so the
features live in memory. The heads train through the shared trainer
(stages/readout_fit.py): epochs over a shuffled training set, scored on the
validation split after each; the epoch and the decision threshold that do
best there are kept. The test split is never seen in training (the official
scripts pick both on test; we do not).

Shapes: features [num_examples, time, num_slots, slot_size], labels
[num_examples] in {0, 1}.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
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


def schedule(fit_config: FitConfig, steps_per_epoch: int) -> optax.Schedule:
  """Cosine decay over all `fit_config.epochs` (after a linear warm-up when
  `fit_config.warmup_fraction` > 0)."""
  total = max(1, steps_per_epoch * fit_config.epochs)
  if fit_config.warmup_fraction == 0.0:
    return optax.cosine_decay_schedule(fit_config.learning_rate, total)
  return optax.warmup_cosine_decay_schedule(
      0.0, fit_config.learning_rate,
      max(1, int(fit_config.warmup_fraction * total)), max(total, 2), 0.0)


def make_optimizer(fit_config: FitConfig, steps_per_epoch: int
                   ) -> tuple[optax.GradientTransformation, optax.Schedule]:
  """(Adam over `schedule`, the schedule)."""
  learning_rate = schedule(fit_config, steps_per_epoch)
  return optax.adam(learning_rate), learning_rate


def readout_loss(params: Any, batch: dict[str, jax.Array], frozen_params: Any,
                 rng: jax.Array, *, model: nn.Module
                 ) -> tuple[jax.Array, dict[str, jax.Array]]:
  """The trainer's loss of head `model` (`LossFn`): `readout_bce` of its
  logits on batch['features'] against batch['labels']. A head with dropout
  (the PHYRE readout's Transformer, officially 0.1) trains with it, drawn
  with `rng` (one key per step); `predict` is deterministic."""
  del frozen_params
  kwargs = {}
  if getattr(model, 'dropout_rate', 0.0) > 0:
    kwargs = {'deterministic': False, 'rngs': {'dropout': rng}}
  logits = model.apply({'params': params}, batch['features'], **kwargs)
  return readout_bce(logits, batch['labels']), {}


def training_batches(features: np.ndarray, labels: np.ndarray,
                     batch_size: int, seed: int, start_step: int = 0,
                     process_index: int = 0, process_count: int = 1
                     ) -> Iterator[dict[str, np.ndarray]]:
  """{'features', 'labels'} of every update from `start_step` on: epoch
  after epoch, `batch_size` examples at a time in an order drawn anew each
  epoch (`np.random.default_rng(seed).permutation`, one per epoch; the
  len % batch_size examples at its end unused), this process's share of
  each (rows [p * b, (p + 1) * b), b = batch_size / process_count)."""
  rng = np.random.default_rng(seed)
  steps_per_epoch = len(features) // batch_size
  share = batch_size // process_count
  epoch, order = 0, rng.permutation(len(features))
  for step in range(start_step, np.iinfo(np.int64).max):
    target, index = divmod(step, steps_per_epoch)
    while epoch < target:
      epoch, order = epoch + 1, rng.permutation(len(features))
    rows = order[index * batch_size:(index + 1) * batch_size][
        process_index * share:(process_index + 1) * share]
    yield {'features': features[rows], 'labels': labels[rows]}
