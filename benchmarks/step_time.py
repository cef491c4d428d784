r"""Times the jitted steps at the paper's model sizes (median after warm-up).

  python benchmarks/step_time.py [--repeats=5]

Prints one line per case with the reference time of the official PyTorch
implementation measured on the same 2-core CPU.
"""

import argparse
import functools
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'configs'))

import clevrer  # noqa: E402  (configs/clevrer.py)
import obj3d  # noqa: E402  (configs/obj3d.py)
from slotformer_jax import models  # noqa: E402
from slotformer_jax.train import optim  # noqa: E402
from slotformer_jax import inference  # noqa: E402
from slotformer_jax import losses  # noqa: E402
from slotformer_jax.train import steps  # noqa: E402
from slotformer_jax.train.state import TrainState  # noqa: E402

# Seconds per call of the official PyTorch code on the same CPU.
PYTORCH_SECONDS = {
    'savi_clevrer_b4x6': 6.74,
    'slotformer_obj3d_b32_slots_only': 1.25,
    'slotformer_obj3d_b4_with_image_loss': 5.53,
    'rollout_obj3d_44_steps_b8': 0.274,
}


def median_seconds(fn, repeats):
  jax.block_until_ready(fn())  # compile + warm-up
  jax.block_until_ready(fn())
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - start)
  return float(np.median(times))


def train_step_runner(loss_fn, params, batch, frozen, stage_config):
  optimizer, _ = optim.make_optimizer(stage_config)
  state = TrainState.create(params, optimizer)
  update = jax.jit(functools.partial(steps.train_step, loss_fn=loss_fn,
                                     optimizer=optimizer, seed=0))
  holder = {'state': state}

  def run():
    holder['state'], metrics = update(holder['state'], batch, frozen)
    return metrics['loss']

  return run


def savi_case(batch_size=4, clip_length=6):
  config = clevrer.get_config()
  model = models.build_savi(config)
  video = np.random.default_rng(0).integers(
      0, 256, (batch_size, clip_length, *config.data.resolution, 3), np.uint8)
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, clip_length,
                                        *config.data.resolution, 3)))
  loss_fn = functools.partial(losses.savi_loss, model=model,
                              kl_weight=config.savi.kl_weight)
  return train_step_runner(loss_fn, params, {'video': video}, None,
                           config.savi)


def slotformer_case(batch_size, image_loss_weight):
  config = obj3d.get_config()
  config.slotformer.image_loss_weight = image_loss_weight
  dyn = config.slotformer
  model = models.build_slotformer(config)
  decoder = models.build_decoder(config)
  length = dyn.burn_in + dyn.rollout
  rng = np.random.default_rng(0)
  batch = {'slots': rng.normal(size=(batch_size, length, config.savi.num_slots,
                                     config.savi.slot_size)).astype(np.float32)}
  if image_loss_weight:
    batch['video'] = rng.integers(
        0, 256, (batch_size, length, *config.data.resolution, 3), np.uint8)
  params = steps.init_params(model, jax.random.key(0),
                             jnp.asarray(batch['slots'][:1, :dyn.burn_in]),
                             dyn.rollout)
  decoder_params = decoder.init(jax.random.key(1),
                                jnp.asarray(batch['slots'][:1, 0]))['params']
  loss_fn = functools.partial(
      losses.slotformer_loss, model=model, decoder=decoder,
      rollout=dyn.rollout, image_loss_weight=image_loss_weight,
      teacher_forcing=False)
  return train_step_runner(loss_fn, params, batch, decoder_params, dyn)


def rollout_case(batch_size=8, num_steps=44):
  config = obj3d.get_config()
  model = models.build_slotformer(config)
  history = jnp.asarray(np.random.default_rng(0).normal(size=(
      batch_size, config.slotformer.burn_in, config.savi.num_slots,
      config.savi.slot_size)), jnp.float32)
  params = steps.init_params(model, jax.random.key(0), history[:1], 1)
  rollout = jax.jit(functools.partial(inference.rollout_slots, model=model,
                                      num_steps=num_steps))
  return lambda: rollout(params, history)


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument('--repeats', type=int, default=5)
  args = parser.parse_args()
  cases = {
      'savi_clevrer_b4x6': savi_case,
      'slotformer_obj3d_b32_slots_only': lambda: slotformer_case(32, 0.0),
      'slotformer_obj3d_b4_with_image_loss': lambda: slotformer_case(4, 1.0),
      'rollout_obj3d_44_steps_b8': rollout_case,
  }
  print(f'jax {jax.__version__} on {jax.devices()[0].device_kind}, '
        f'{os.cpu_count()} cores; median of {args.repeats} after warm-up')
  for name, make in cases.items():
    seconds = median_seconds(make(), args.repeats)
    reference = PYTORCH_SECONDS[name]
    print(f'{name:<40} {seconds:8.3f} s   (official PyTorch {reference:.3f} s,'
          f' ratio {seconds / reference:.2f}x)', flush=True)


if __name__ == '__main__':
  main()
