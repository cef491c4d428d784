r"""STEVE at the official Physion size: train step, frame generation, memory.

  python benchmarks/steve_time.py [--repeats=3] [--recompute_steps=8]

Cases (configs/physion.py, 128x128 frames, 32x32 = 1024 tokens, vocabulary
4096, 6 slots of 192, 4-layer token decoder):
* `steve_train_b4x6`: one STEVE training step (Adam, two learning rates,
  clipping) on 4 clips of 6 frames.
* `generate_kv_cache_b8`: greedy generation of one frame for 8 slot sets
  (all 1024 tokens with the key/value cache in `lax.scan`) + the dVAE
  decoder.
* `generate_recompute_b8`: the same generation re-running the decoder over
  the whole 1024-token sequence at every step (the official code re-runs the
  growing prefix). Every step costs the same, so it is timed over the first
  `--recompute_steps` steps and scaled by 1024 / recompute_steps.
  The growing prefix of the official code costs about half of that
  (sum of lengths 1..1024 ~ 1024^2 / 2): both ratios are printed.

Peak memory: XLA's compiled memory analysis (arguments + outputs + temporary
buffers of the one program; on a GPU also the allocator's peak,
`memory_stats()['peak_bytes_in_use']`).
"""

import argparse
import functools
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..', 'configs'))

import physion  # noqa: E402  (configs/physion.py)
from slotformer_jax import losses  # noqa: E402
from slotformer_jax.slot_models import steve as steve_slots  # noqa: E402
from slotformer_jax.train import optim  # noqa: E402
from slotformer_jax.train import steps  # noqa: E402
from slotformer_jax.train.state import TrainState  # noqa: E402
from slotformer_jax.slot_models.steve import build_steve
from slotformer_jax.slot_models.steve import build_dvae


def timed(compiled, args, repeats):
  """Median seconds of `compiled(*args)` after one warm-up call."""
  jax.block_until_ready(compiled(*args))
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    times.append(time.perf_counter() - start)
  return float(np.median(times))


def memory_mib(compiled) -> str:
  analysis = compiled.memory_analysis()
  total = (analysis.argument_size_in_bytes + analysis.output_size_in_bytes +
           analysis.temp_size_in_bytes - analysis.alias_size_in_bytes)
  text = f'{total / 2**20:.0f} MiB (XLA analysis)'
  stats = jax.devices()[0].memory_stats()
  if stats and 'peak_bytes_in_use' in stats:
    text += f', allocator peak {stats["peak_bytes_in_use"] / 2**20:.0f} MiB'
  return text


def steve_train_case(config, batch_size, clip_length, repeats):
  model = build_steve(config.steve, tuple(config.data.resolution),
                             config.dvae.vocab_size)
  height, width = model.token_grid
  rng = np.random.default_rng(0)
  batch = {
      'video': rng.integers(0, 256, (batch_size, clip_length,
                                     *config.data.resolution, 3), np.uint8),
      'tokens': rng.integers(0, config.dvae.vocab_size,
                             (batch_size, clip_length, height * width),
                             np.int32)}
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, 1, *config.data.resolution, 3)),
                             jnp.zeros((1, 1, height * width), jnp.int32))
  optimizer, _ = optim.make_optimizer(config.steve)
  state = TrainState.create(params, optimizer)
  update = jax.jit(functools.partial(
      steps.train_step,
      loss_fn=functools.partial(losses.steve_loss, model=model),
      optimizer=optimizer, seed=0))
  compiled = update.lower(state, batch, None).compile()
  seconds = timed(compiled, (state, batch, None), repeats)
  return seconds, memory_mib(compiled)


def generation_cases(config, batch_size, repeats, recompute_steps):
  steve = build_steve(config.steve, tuple(config.data.resolution),
                             config.dvae.vocab_size)
  decoder = steve_slots.token_decoder(steve)
  dvae = build_dvae(config.dvae)
  grid = steve.token_grid
  slots = jax.random.normal(jax.random.key(1), (
      batch_size, config.steve.num_slots, config.steve.slot_size))
  decoder_params = steps.init_params(
      decoder, jax.random.key(2), slots[:1],
      jnp.zeros((1, decoder.num_tokens), jnp.int32))
  dvae_params = steps.init_params(
      dvae, jax.random.key(3), jnp.zeros((1, *config.data.resolution, 3)),
      1.0)

  def with_cache(decoder_params, dvae_params, slots):
    frames, _ = steve_slots.generate_frames(
        decoder_params, dvae_params, slots, decoder=decoder, dvae=dvae,
        token_grid=grid)
    return frames

  compiled = jax.jit(with_cache).lower(decoder_params, dvae_params,
                                       slots).compile()
  cache_seconds = timed(compiled, (decoder_params, dvae_params, slots),
                        repeats)
  cache_memory = memory_mib(compiled)

  # The recomputing decoder, over the first `recompute_steps` positions only.
  variables = {'params': decoder_params}

  def recompute(slots):
    def step(tokens, position):
      logits = decoder.apply(variables, slots, tokens)
      chosen = jnp.argmax(logits[:, position], -1).astype(jnp.int32)
      return tokens.at[:, position].set(chosen), None
    tokens = jnp.zeros((slots.shape[0], decoder.num_tokens), jnp.int32)
    return jax.lax.scan(step, tokens, jnp.arange(recompute_steps))[0]

  compiled = jax.jit(recompute).lower(slots).compile()
  partial_seconds = timed(compiled, (slots,), max(1, repeats // 2))
  recompute_seconds = partial_seconds * decoder.num_tokens / recompute_steps
  return (cache_seconds, cache_memory, recompute_seconds, partial_seconds,
          memory_mib(compiled))


def main():
  parser = argparse.ArgumentParser()
  parser.add_argument('--repeats', type=int, default=3)
  parser.add_argument('--recompute_steps', type=int, default=8)
  parser.add_argument('--train_batch', type=int, default=4)
  parser.add_argument('--train_clip', type=int, default=6)
  parser.add_argument('--generate_batch', type=int, default=8)
  parser.add_argument('--skip_train', action='store_true')
  args = parser.parse_args()
  config = physion.get_config()
  print(f'devices: {jax.devices()}')
  if not args.skip_train:
    seconds, memory = steve_train_case(config, args.train_batch,
                                       args.train_clip, args.repeats)
    print(f'steve_train_b{args.train_batch}x{args.train_clip}: '
          f'{seconds:.3f} s/step, peak {memory}')
  (cache, cache_memory, recompute, partial,
   recompute_memory) = generation_cases(config, args.generate_batch,
                                        args.repeats, args.recompute_steps)
  b = args.generate_batch
  print(f'generate_kv_cache_b{b} (1024 tokens + dVAE decoder): {cache:.3f} s,'
        f' peak {cache_memory}')
  print(f'generate_recompute_b{b}: {partial:.3f} s for '
        f'{args.recompute_steps} steps -> {recompute:.1f} s for 1024 tokens, '
        f'peak {recompute_memory}')
  print(f'KV cache speed-up: {recompute / cache:.1f}x vs full-length '
        f'recomputation, ~{recompute / 2 / cache:.1f}x vs the official growing '
        'prefix')


if __name__ == '__main__':
  main()
