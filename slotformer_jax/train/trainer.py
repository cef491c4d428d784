"""The training loop shared by both stages, readable top to bottom.

mesh -> optimiser -> restore or initialise the state -> jit the update step
-> loop: host batch -> global batch -> update -> log / NaN check ->
checkpoint. Re-running resumes from the newest checkpoint, and the data
stream resumes at the same step (batches are a function of the step).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import dataclasses
import functools
import json
import logging
import math
import os
import time
from typing import Any
import warnings

import jax
from jax.sharding import Mesh
import ml_collections
import numpy as np
import tqdm

from slotformer_jax.train import optim
from slotformer_jax.train import sharding
from slotformer_jax.train.checkpoint import Checkpointer
from slotformer_jax.train.checkpoint import abstract_like
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.steps import LossFn
from slotformer_jax.train.steps import train_step

logger = logging.getLogger(__name__)

# XLA:CPU cannot reuse donated buffers and says so on every call.
warnings.filterwarnings('ignore', message='Some donated buffers were not usable')


@dataclasses.dataclass(frozen=True)
class Stage:
  """What differs between training SAVi and training SlotFormer.

  Attributes:
    name: 'savi' or 'slotformer'; also the sub-folder of the workdir.
    directory: where checkpoints and the training log go.
    config: the stage's config section (batch_size, num_train_steps,
      learning_rate, warmup_fraction, grad_clip, log_every,
      checkpoint_every).
    loss_fn: (params, batch, frozen_params, rng) -> (loss, metrics).
    init_params: rng -> params.
    batches: start_step -> iterator of this host's batches.
    frozen_params: parameters used but not trained (SAVi's decoder).
  """

  name: str
  directory: str
  config: ml_collections.ConfigDict
  loss_fn: LossFn
  init_params: Callable[[jax.Array], Any]
  batches: Callable[[int], Iterator[dict[str, np.ndarray]]]
  frozen_params: Any = None


def checkpointer_for(stage_directory: str, **kwargs) -> Checkpointer:
  return Checkpointer(os.path.join(stage_directory, 'checkpoints'), **kwargs)


def abstract_train_state(init_params: Callable[[jax.Array], Any],
                         stage_config: ml_collections.ConfigDict,
                         mesh: Mesh) -> TrainState:
  """Shapes (replicated) of the stage's TrainState, for restoring."""
  optimizer, _ = optim.make_optimizer(stage_config)
  shapes = jax.eval_shape(
      lambda: TrainState.create(init_params(jax.random.key(0)), optimizer))
  return abstract_like(shapes, sharding.replicated_sharding(mesh))


def fit(stage: Stage, *, mesh: Mesh, seed: int) -> TrainState:
  """Trains `stage` to `config.num_train_steps`, resuming if possible."""
  config = stage.config
  num_steps = config.num_train_steps
  is_lead_host = jax.process_index() == 0
  replicated = sharding.replicated_sharding(mesh)
  optimizer, schedule = optim.make_optimizer(config)

  checkpointer = checkpointer_for(stage.directory)
  if checkpointer.latest_step() is not None:
    state = checkpointer.restore(
        abstract_train_state(stage.init_params, config, mesh))
    logger.info('%s: resumed from step %d', stage.name, int(state.step))
  else:
    init_rng = jax.random.key(seed)
    state = jax.jit(
        lambda: TrainState.create(stage.init_params(init_rng), optimizer),
        out_shardings=replicated)()
  start_step = int(state.step)
  if start_step >= num_steps:
    logger.info('%s: already trained (%d steps)', stage.name, start_step)
    checkpointer.close()
    return state

  num_params = sum(x.size for x in jax.tree.leaves(state.params))
  logger.info('%s: %s parameters, training steps %d -> %d on %d devices',
               stage.name, f'{num_params:,}', start_step, num_steps,
               mesh.devices.size)
  update = jax.jit(
      functools.partial(train_step, loss_fn=stage.loss_fn,
                        optimizer=optimizer, seed=seed),
      in_shardings=(replicated, sharding.batch_sharding(mesh), replicated),
      out_shardings=(replicated, replicated),
      donate_argnums=(0,))
  frozen_params = sharding.replicate(stage.frozen_params, mesh)

  log_path = os.path.join(stage.directory, 'train_log.jsonl')
  batches = stage.batches(start_step)
  last_log_time, last_log_step = time.time(), start_step
  try:
    with tqdm.tqdm(total=num_steps, initial=start_step, desc=stage.name,
                   disable=not is_lead_host, dynamic_ncols=True) as progress:
      for step in range(start_step, num_steps):
        batch = sharding.to_global_batch(next(batches), mesh)
        state, metrics = update(state, batch, frozen_params)
        progress.update(1)
        done = step + 1
        should_save = (done % config.checkpoint_every == 0
                       or done == num_steps)
        should_log = done % config.log_every == 0 or done == num_steps
        if should_log or should_save:
          # Never checkpoint a diverged state.
          metrics = {k: float(v) for k, v in sharding.to_host(metrics).items()}
          if not math.isfinite(metrics['loss']):
            raise FloatingPointError(
                f'{stage.name}: the loss became {metrics["loss"]} at step '
                f'{done}; the last checkpoint is step '
                f'{checkpointer.latest_step()}. Lower the learning rate or '
                'check the data; re-running resumes from that checkpoint.')
        if should_log:
          now = time.time()
          metrics['learning_rate'] = float(schedule(step))
          metrics['steps_per_second'] = (done - last_log_step) / max(
              now - last_log_time, 1e-9)
          last_log_time, last_log_step = now, done
          progress.set_postfix(loss=f'{metrics["loss"]:.4g}')
          logger.info('%s step %d: %s', stage.name, done, ', '.join(
              f'{k}={v:.4g}' for k, v in sorted(metrics.items())))
          if is_lead_host:
            with open(log_path, 'a') as log_file:
              log_file.write(json.dumps({'step': done, **metrics}) + '\n')
        if should_save:
          checkpointer.save(done, state, force=done == num_steps)
  finally:
    # Also on an exception or Ctrl-C: finish the save in flight so the next
    # run resumes from it.
    checkpointer.wait_until_finished()
    checkpointer.close()
  return state
