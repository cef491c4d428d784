"""Optimiser: Adam with linear warm-up, cosine decay to 0, optional clipping."""

from __future__ import annotations

import ml_collections
import optax


def learning_rate_schedule(peak_learning_rate: float, num_steps: int,
                           warmup_fraction: float) -> optax.Schedule:
  """0 -> peak linearly over `warmup_fraction` of the steps, then cosine to 0."""
  warmup_steps = max(1, int(round(warmup_fraction * num_steps)))
  return optax.warmup_cosine_decay_schedule(
      init_value=0.0, peak_value=peak_learning_rate,
      warmup_steps=warmup_steps, decay_steps=max(num_steps, warmup_steps + 1),
      end_value=0.0)


def make_optimizer(stage_config: ml_collections.ConfigDict
                   ) -> tuple[optax.GradientTransformation, optax.Schedule]:
  """Adam over the stage's schedule; global-norm clipping if `grad_clip` > 0.

  Reads `learning_rate`, `num_train_steps`, `warmup_fraction`, `grad_clip`.
  """
  schedule = learning_rate_schedule(
      stage_config.learning_rate, stage_config.num_train_steps,
      stage_config.warmup_fraction)
  transforms = []
  if stage_config.get('grad_clip'):
    transforms.append(optax.clip_by_global_norm(stage_config.grad_clip))
  transforms.append(optax.adam(schedule))
  return optax.chain(*transforms), schedule
