r"""Times the jitted steps at the paper's model sizes (median after warm-up).

  python benchmarks/step_time.py [--repeats=5] [--cases=savi,lpips_32]
      [--compute_dtype=bfloat16] [--json=out.json] [--reference=ref.json]

Prints one line per case with the time of the official PyTorch
implementation on the same shapes (torch 2.13 CPU, 2 threads; the defaults
are idle-machine figures measured earlier, --reference takes your own, see
docs/performance.md) and the ratio (< 1: this project is faster). The faster XLA:CPU flags of
`slotformer_jax.runtime.xla_flags` are on unless $SLOTFORMER_XLA_CPU_FLAGS=0.

Cases (shapes as the official configs):
  savi              StoSAVi CLEVRER config train step, batch 4 x 6 frames 64x64
  decoder           SAVi decoder forward + backward alone, 168 slot images
                    64x64 (= the 4 x 6 x 7 slots of `savi`)
  slots_only        SlotFormer OBJ3D train step, batch 32, L_S only
  image_loss        SlotFormer OBJ3D train step, batch 4, L_S + L_I through
                    the frozen decoder
  rollout           44-step rollout, batch 8
  rollout_decode    44-step rollout + decoding the 44 frames, batch 8
  lpips_32/lpips_64 LPIPS-VGG of 100 frame pairs at 32x32 / 64x64
  lpips_32_features / lpips_64_features
                    the same with the ground-truth frames' VGG features
                    computed beforehand (what the evaluation does: once for
                    all methods), i.e. the per-method cost
  savi_synthetic    SAVi train step of configs/synthetic.py (32x32 frames,
                    its batch and clip length): a small case
  slotformer_synthetic
                    SlotFormer train step of configs/synthetic.py

Several seeds (config.seeds, train/seeds.py):

  python benchmarks/step_time.py --seeds=3 --cases=savi_synthetic

times, for each train-step case, K seeds in one program in both forms of
`seeds.seeds_train_step` ('vmap': one batched step; 'unroll': the one-seed
step written K times into the program, the trainer's choice on CPU) against K
one-seed steps, the three alternating each repeat, and prints the medians
and the ratios (the issue's bar: one program <= K one-seed steps, ratio
<= 1). The one-seed
steps are compiled as the one-seed trainer compiles them; --same_options
compiles them with the several-seed program's XLA:CPU options too.
"""

import argparse
import functools
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..'))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'configs'))

from slotformer_jax.runtime import xla_flags  # noqa: E402  (imports no jax)

# Before jax starts its backend.
ADDED_FLAGS = xla_flags.apply_fast_cpu_flags()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import clevrer  # noqa: E402  (configs/clevrer.py)
import obj3d  # noqa: E402  (configs/obj3d.py)
from slotformer_jax import inference  # noqa: E402
from slotformer_jax import losses  # noqa: E402
from slotformer_jax.evaluation import metrics  # noqa: E402
from slotformer_jax.train import optim  # noqa: E402
from slotformer_jax.runtime import precision  # noqa: E402
from slotformer_jax.train import steps  # noqa: E402
from slotformer_jax.train.state import TrainState  # noqa: E402
from slotformer_jax.train import seeds as seeds_lib  # noqa: E402
import synthetic  # noqa: E402  (configs/synthetic.py)
from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax.slot_models.savi import build_decoder
from slotformer_jax.slot_models.savi import build_savi

# Seconds per call of the official PyTorch code (torch 2.13 CPU, 2 threads)
# on the same shapes, as measured on an idle 2-core Intel Xeon
# (its second alternating run). No reference for LPIPS there. Pass
# --reference=official.json to compare with a run of your own instead.
PYTORCH_SECONDS = {
    'savi': 4.64,
    'decoder': 3.15,
    'slots_only': 0.84,
    'image_loss': 3.50,
    'rollout': 0.161,
    'rollout_decode': 25.5,
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


# --seeds: K > 1 makes the train-step cases return both runners.
NUM_SEEDS = 1
# --same_options: the one-seed steps compiled with the vmapped several-seed
# program's XLA:CPU options too (the vmap's cost apart from the options').
SAME_OPTIONS = False


def seeds_runners(loss_fn, params, batch, frozen, stage_config, num_seeds):
  """{'vmap': K seeds' vmapped step, 'unroll': the one-seed step written K
  times into one program, 'separate': K one-seed steps}.

  The seeds' parameters are copies of `params` (the cost does not depend on
  the values); each one-program form is traced and compiled as the trainer
  does (`seeds.seeds_update`, `seeds.compiler_options` on XLA:CPU for
  that form)."""
  optimizer, _ = optim.make_optimizer(stage_config)
  one_seed = TrainState.create(params, optimizer)
  mesh = jax.sharding.Mesh(np.asarray(jax.devices()[:1]), ('data',))
  holder = {'states': [one_seed] * num_seeds}
  runners = {}
  for loop in ('vmap', 'unroll'):
    options = seeds_lib.compiler_options(mesh, loop)
    update = jax.jit(seeds_lib.seeds_update(loss_fn, optimizer,
                                            tuple(range(num_seeds)),
                                            loop=loop),
                     compiler_options=options)
    holder[loop] = seeds_lib.SeedsState.stack([one_seed] * num_seeds)

    def one_program(loop=loop, update=update):
      holder[loop], metrics_ = update(holder[loop], batch, frozen)
      return metrics_['loss']

    runners[loop] = one_program
  vmap_options = seeds_lib.compiler_options(mesh, 'vmap')
  single = jax.jit(functools.partial(steps.train_step, loss_fn=loss_fn,
                                     optimizer=optimizer, seed=0),
                   compiler_options=vmap_options if SAME_OPTIONS else None)

  def separate():
    losses_ = []
    for k in range(num_seeds):
      holder['states'][k], metrics_ = single(holder['states'][k], batch,
                                             frozen)
      losses_.append(metrics_['loss'])
    return losses_

  runners['separate'] = separate
  return runners


def alternating_medians(runners, repeats):
  """{name: median seconds}, the runners taking turns each repeat (a load
  change on a shared machine hits both)."""
  for fn in runners.values():  # compile + warm-up
    jax.block_until_ready(fn())
    jax.block_until_ready(fn())
  times = {name: [] for name in runners}
  for _ in range(repeats):
    for name, fn in runners.items():
      start = time.perf_counter()
      jax.block_until_ready(fn())
      times[name].append(time.perf_counter() - start)
  return {name: float(np.median(t)) for name, t in times.items()}


def train_step_runner(loss_fn, params, batch, frozen, stage_config):
  if NUM_SEEDS > 1:
    return seeds_runners(loss_fn, params, batch, frozen, stage_config,
                         NUM_SEEDS)
  optimizer, _ = optim.make_optimizer(stage_config)
  state = TrainState.create(params, optimizer)
  update = jax.jit(functools.partial(steps.train_step, loss_fn=loss_fn,
                                     optimizer=optimizer, seed=0))
  holder = {'state': state}

  def run():
    holder['state'], metrics_ = update(holder['state'], batch, frozen)
    return metrics_['loss']

  return run


def savi_case(dtype, batch_size=4, clip_length=6):
  config = clevrer.get_config()
  model = build_savi(config.savi, tuple(config.data.resolution))
  video = np.random.default_rng(0).integers(
      0, 256, (batch_size, clip_length, *config.data.resolution, 3), np.uint8)
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, clip_length,
                                        *config.data.resolution, 3)))
  loss_fn = precision.with_compute_dtype(functools.partial(
      losses.savi_loss, model=model, kl_weight=config.savi.kl_weight), dtype)
  return train_step_runner(loss_fn, params, {'video': video}, None,
                           config.savi)


def savi_synthetic_case(dtype):
  config = synthetic.get_config()
  model = build_savi(config.savi, tuple(config.data.resolution))
  batch_size, clip_length = config.savi.batch_size, config.savi.clip_length
  video = np.random.default_rng(0).integers(
      0, 256, (batch_size, clip_length, *config.data.resolution, 3), np.uint8)
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, clip_length,
                                        *config.data.resolution, 3)))
  loss_fn = precision.with_compute_dtype(functools.partial(
      losses.savi_loss, model=model, kl_weight=config.savi.kl_weight), dtype)
  return train_step_runner(loss_fn, params, {'video': video}, None,
                           config.savi)


def decoder_case(dtype, num_images=4 * 6):
  """Forward + backward (parameters and slots) of the CLEVRER decoder."""
  config = clevrer.get_config()
  decoder = build_decoder(config.savi.decoder,
                                 tuple(config.data.resolution))
  slots = jnp.asarray(np.random.default_rng(0).normal(size=(
      num_images, config.savi.num_slots, config.savi.slot_size)), jnp.float32)
  params = decoder.init(jax.random.key(0), slots[:1])['params']

  def loss(params, slots):
    params, slots = precision.cast_floats((params, slots), dtype)
    recon = decoder.apply({'params': params}, slots).recon
    return jnp.mean(jnp.square(recon.astype(jnp.float32)))

  grad = jax.jit(jax.grad(loss, argnums=(0, 1)))
  return lambda: grad(params, slots)


def slotformer_case(dtype, batch_size, image_loss_weight, config=None):
  config = config or obj3d.get_config()
  config.slotformer.image_loss_weight = image_loss_weight
  dyn = config.slotformer
  model = dynamics_lib.build(config.slotformer, 'slotformer')
  decoder = build_decoder(config.savi.decoder,
                                 tuple(config.data.resolution))
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
  loss_fn = precision.with_compute_dtype(functools.partial(
      losses.slotformer_loss, model=model, decoder=decoder,
      rollout=dyn.rollout,
      weights={'slot_loss': 1.0, 'image_loss': image_loss_weight},
      teacher_forcing=False), dtype)
  return train_step_runner(loss_fn, params, batch, decoder_params, dyn)


def _rollout_inputs(batch_size):
  config = obj3d.get_config()
  model = dynamics_lib.build(config.slotformer, 'slotformer')
  history = jnp.asarray(np.random.default_rng(0).normal(size=(
      batch_size, config.slotformer.burn_in, config.savi.num_slots,
      config.savi.slot_size)), jnp.float32)
  params = steps.init_params(model, jax.random.key(0), history[:1], 1)
  return config, model, history, params


def rollout_case(dtype, batch_size=8, num_steps=44):
  _, model, history, params = _rollout_inputs(batch_size)
  rollout = jax.jit(precision.with_compute_dtype(functools.partial(
      inference.rollout_slots, model=model, num_steps=num_steps), dtype))
  return lambda: rollout(params, history)


def rollout_decode_case(dtype, batch_size=8, num_steps=44):
  config, model, history, params = _rollout_inputs(batch_size)
  decoder = build_decoder(config.savi.decoder,
                                 tuple(config.data.resolution))
  decoder_params = decoder.init(jax.random.key(1), history[:1, 0])['params']

  def rollout_and_decode(params, decoder_params, history):
    slots = inference.rollout_slots(params, history, model=model,
                                num_steps=num_steps)
    return decoder.apply({'params': decoder_params}, slots).recon

  run = jax.jit(precision.with_compute_dtype(rollout_and_decode, dtype))
  return lambda: run(params, decoder_params, history)


def lpips_case(dtype, resolution, with_features, num_pairs=100):
  del dtype  # LPIPS is a metric: always float32
  rng = np.random.default_rng(0)
  pred, target = (jnp.asarray(rng.uniform(size=(num_pairs, resolution,
                                                resolution, 3)), jnp.float32)
                  for _ in range(2))
  lpips = metrics.make_lpips_vgg()
  if not with_features:
    return lambda: lpips(pred, target)
  target_features = jax.block_until_ready(lpips.features(target))
  return lambda: lpips.distance_to_features(pred, target_features)


TRAIN_STEP_CASES = ('savi', 'slots_only', 'image_loss', 'savi_synthetic',
                    'slotformer_synthetic')
CASES = {
    'savi': savi_case,
    'decoder': decoder_case,
    'slots_only': lambda dtype: slotformer_case(dtype, 32, 0.0),
    'image_loss': lambda dtype: slotformer_case(dtype, 4, 1.0),
    'rollout': rollout_case,
    'rollout_decode': rollout_decode_case,
    'savi_synthetic': savi_synthetic_case,
    'slotformer_synthetic': lambda dtype: slotformer_case(
        dtype, synthetic.get_config().slotformer.batch_size,
        synthetic.get_config().slotformer.image_loss_weight,
        synthetic.get_config()),
    'lpips_32': lambda dtype: lpips_case(dtype, 32, False),
    'lpips_64': lambda dtype: lpips_case(dtype, 64, False),
    'lpips_32_features': lambda dtype: lpips_case(dtype, 32, True),
    'lpips_64_features': lambda dtype: lpips_case(dtype, 64, True),
}


def main():
  parser = argparse.ArgumentParser(
      description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  parser.add_argument('--repeats', type=int, default=5)
  parser.add_argument('--same_options', action='store_true',
                      help='with --seeds: compile the one-seed steps with '
                      "the several-seed program's XLA:CPU options too")
  parser.add_argument('--seeds', type=int, default=1,
                      help='K > 1: time K seeds in one program against K '
                      'one-seed steps (train-step cases only)')
  parser.add_argument('--cases', default=','.join(CASES),
                      help='comma-separated subset of: ' + ', '.join(CASES))
  parser.add_argument('--compute_dtype', default='float32',
                      choices=precision.COMPUTE_DTYPES)
  parser.add_argument('--json', help='also write {case: seconds} here')
  parser.add_argument('--reference', help='{case: seconds} of the official '
                      'code measured on this machine (replaces the defaults)')
  args = parser.parse_args()
  names = [n for n in args.cases.split(',') if n]
  unknown = sorted(set(names) - set(CASES))
  if unknown:
    parser.error(f'unknown cases {unknown}; choose from {list(CASES)}')
  global NUM_SEEDS, SAME_OPTIONS
  NUM_SEEDS, SAME_OPTIONS = args.seeds, args.same_options
  not_steps = sorted(set(names) - set(TRAIN_STEP_CASES))
  if NUM_SEEDS > 1 and not_steps:
    parser.error(f'--seeds={NUM_SEEDS} times train steps only; not '
                 f'{not_steps}: choose from {list(TRAIN_STEP_CASES)}')
  print(f'jax {jax.__version__} on {jax.devices()[0].device_kind}, '
        f'{os.cpu_count()} cores, compute_dtype={args.compute_dtype}, '
        f'XLA_FLAGS={os.environ.get("XLA_FLAGS", "")!r}; median of '
        f'{args.repeats} after warm-up', flush=True)
  references = dict(PYTORCH_SECONDS)
  if args.reference:
    with open(args.reference) as f:
      references = json.load(f)
  results = {}
  if NUM_SEEDS > 1:
    print(f'load average before: {os.getloadavg()}', flush=True)
  for name in names:
    if NUM_SEEDS > 1:
      medians = alternating_medians(CASES[name](args.compute_dtype),
                                    args.repeats)
      results[name] = medians
      print(f'{name:<20} {NUM_SEEDS} seeds in one program: vmap '
            f'{medians["vmap"]:.3f} s, unroll {medians["unroll"]:.3f} s; '
            f'{NUM_SEEDS} one-seed steps {medians["separate"]:.3f} s; ratio '
            f'vmap {medians["vmap"] / medians["separate"]:.2f}, map '
            f'{medians["unroll"] / medians["separate"]:.2f} '
            f'(load average {os.getloadavg()[0]:.2f})', flush=True)
      continue
    seconds = median_seconds(CASES[name](args.compute_dtype), args.repeats)
    results[name] = seconds
    # The *_features cases are the per-method cost of the same comparison.
    reference = references.get(name.removesuffix('_features'))
    note = (f'   (official PyTorch {reference:.3f} s, ratio '
            f'{seconds / reference:.2f}x)' if reference else '')
    print(f'{name:<20} {seconds:8.3f} s{note}', flush=True)
  if args.json:
    with open(args.json, 'w') as f:
      json.dump(results, f, indent=1)


if __name__ == '__main__':
  main()
