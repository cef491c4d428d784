"""Optimiser: Adam with linear warm-up, cosine decay, optional clipping."""

from __future__ import annotations

import ml_collections
import optax


def learning_rate_schedule(peak_learning_rate: float, num_steps: int,
                           warmup_fraction: float,
                           min_lr_fraction: float = 0.0) -> optax.Schedule:
  """floor -> peak linearly over `warmup_fraction` of the steps, then cosine
  back to floor = min_lr_fraction * peak (0.01 in the official recipe, whose
  scheduler starts and ends at lr / 100)."""
  warmup_steps = max(1, int(round(warmup_fraction * num_steps)))
  floor = min_lr_fraction * peak_learning_rate
  return optax.warmup_cosine_decay_schedule(
      init_value=floor, peak_value=peak_learning_rate,
      warmup_steps=warmup_steps, decay_steps=max(num_steps, warmup_steps + 1),
      end_value=floor)


def make_optimizer(stage_config: ml_collections.ConfigDict
                   ) -> tuple[optax.GradientTransformation, optax.Schedule]:
  """Adam over the stage's schedule; global-norm clipping if `grad_clip` > 0.

  Reads `learning_rate`, `num_train_steps`, `warmup_fraction`, `grad_clip`,
  `min_lr_fraction` and `group_learning_rates`: {top-level parameter name:
  peak learning rate} for parts trained faster (STEVE's decoder: 3e-4 vs
  1e-4), on the same warm-up + cosine shape; clipping stays global over all
  parameters. The returned schedule is the default group's.
  """
  def schedule_for(peak: float) -> optax.Schedule:
    return learning_rate_schedule(
        peak, stage_config.num_train_steps, stage_config.warmup_fraction,
        stage_config.min_lr_fraction)

  schedule = schedule_for(stage_config.learning_rate)
  transforms = []
  if stage_config.grad_clip:
    transforms.append(optax.clip_by_global_norm(stage_config.grad_clip))
  groups = dict(stage_config.group_learning_rates or {})
  if groups:
    optimizers = {name: optax.adam(schedule_for(peak))
                  for name, peak in groups.items()}
    optimizers['default'] = optax.adam(schedule)
    transforms.append(optax.multi_transform(
        optimizers,
        lambda params: {key: key if key in groups else 'default'
                        for key in params}))
  else:
    transforms.append(optax.adam(schedule))
  return optax.chain(*transforms), schedule
