"""A one-parameter-vector training stage: the training loop's logic
(checkpoints, resume, signals, faults) without a model's compile time."""

import itertools

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax.train.trainer import Stage


def linear_stage(directory, *, tensorboard=False, device_work=0,
                 **config_changes) -> Stage:
  """Fits w [3] to the step number (batch 'x': float32 [4, 3]); every
  trainer field set, `config_changes` on top; TensorBoard when asked;
  `device_work` 256 x 256 matrix products per update (a slow device step,
  the loss unchanged)."""
  config = ml_collections.ConfigDict(dict(
      num_train_steps=3, learning_rate=1e-2, warmup_fraction=0.0,
      grad_clip=0.0, min_lr_fraction=0.0,
      group_learning_rates={}, stop_check_every=1, batch_size=4,
      log_every=1, checkpoint_every=2))
  config.update(config_changes)

  def loss_fn(params, batch, frozen_params, rng):
    del frozen_params, rng
    loss = jnp.mean(jnp.square(params['w'] - batch['x']))
    if device_work:
      work = jax.lax.fori_loop(
          0, device_work, lambda i, m: jnp.tanh(m @ m),
          jnp.full((256, 256), 1e-3, jnp.float32) + loss * 1e-9)
      loss = loss + 0.0 * jnp.sum(work)
    return loss, {}

  def batches(start_step):
    for step in itertools.count(start_step):
      yield {'x': np.full((4, 3), float(step), np.float32)}

  logging = (ml_collections.ConfigDict(dict(tensorboard=True, image_every=0))
             if tensorboard else None)
  return Stage(name='linear', directory=str(directory), config=config,
               loss_fn=loss_fn,
               init_params=lambda rng: {'w': jnp.zeros(3, jnp.float32)},
               batches=batches, logging=logging)
