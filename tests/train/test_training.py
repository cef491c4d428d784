"""Train steps: data parallelism, single tracing, checkpoint/resume."""

import dataclasses
import functools

import chex
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import pytest

from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.runtime import sharding
from slotformer_jax import losses
from slotformer_jax.train import steps
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit
from slotformer_jax.data import pipeline
from tiny_models import tiny_savi

RESOLUTION = (16, 16)


def _savi(stochastic=False):
  return tiny_savi(RESOLUTION, decoder=dict(broadcast_resolution=(8, 8)),
                   stochastic=stochastic,
                   posterior_head='mlp' if stochastic else 'none')


def _decoder():
  return SpatialBroadcastDecoder(output_resolution=RESOLUTION,
                                 broadcast_resolution=(8, 8),
                                 features=(8, 8), kernel_size=3)


def _slotformer():
  return SlotFormer(burn_in=2, embed_dim=16, num_layers=1, num_heads=2,
                    mlp_size=32, dropout_rate=0.1)


def _video(batch, time, seed=0):
  rng = np.random.default_rng(seed)
  return rng.integers(0, 256, (batch, time, *RESOLUTION, 3), dtype=np.uint8)


def _savi_setup(stochastic=False):
  model = _savi(stochastic)
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, 2, *RESOLUTION, 3)))
  loss_fn = functools.partial(losses.savi_loss, model=model, kl_weight=1e-4)
  return params, loss_fn, {'video': _video(4, 2)}


def _slotformer_setup():
  model = _slotformer()
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, 2, 3, 16)), 2)
  decoder_params = _decoder().init(jax.random.key(1), jnp.zeros((1, 3, 16)))
  loss_fn = functools.partial(
      losses.slotformer_loss, model=model, decoder=_decoder(), rollout=2,
      weights={'slot_loss': 1.0, 'image_loss': 1.0}, teacher_forcing=False)
  batch = {'slots': np.random.default_rng(2).normal(
      size=(4, 4, 3, 16)).astype(np.float32), 'video': _video(4, 4)}
  return params, loss_fn, batch, decoder_params['params']


def _run_step(mesh, params, loss_fn, batch, frozen, optimizer):
  replicated = sharding.replicated_sharding(mesh)
  update = jax.jit(
      functools.partial(steps.train_step, loss_fn=loss_fn,
                        optimizer=optimizer, seed=3),
      in_shardings=(replicated, sharding.batch_sharding(mesh), replicated),
      out_shardings=(replicated, replicated))
  state = sharding.replicate(TrainState.create(params, optimizer), mesh)
  state, metrics = update(state, sharding.to_global_batch(batch, mesh),
                          sharding.replicate(frozen, mesh))
  return jax.device_get(state), jax.device_get(metrics)


@pytest.mark.parametrize('stage', ['stochastic_savi', 'slotformer'])
def test_four_device_step_equals_one_device_step(stage):
  assert jax.device_count() == 4, 'conftest.py asks XLA for 4 CPU devices'
  if stage == 'slotformer':
    params, loss_fn, batch, frozen = _slotformer_setup()
  else:
    # Stochastic SAVi: the deterministic path plus per-device RNG use.
    params, loss_fn, batch = _savi_setup(stochastic=True)
    frozen = None
  # Plain SGD: the updated parameters are a linear function of the
  # all-reduced gradient, so they expose any error in the reduction.
  optimizer = optax.sgd(0.1)
  one = _run_step(Mesh(np.asarray(jax.devices()[:1]), ('data',)), params,
                  loss_fn, batch, frozen, optimizer)
  four = _run_step(sharding.make_mesh(), params, loss_fn, batch, frozen,
                   optimizer)
  for key in one[1]:
    np.testing.assert_allclose(four[1][key], one[1][key], rtol=1e-5,
                               atol=1e-5, err_msg=key)
  chex.assert_trees_all_close(four[0].params, one[0].params, atol=1e-5,
                              rtol=1e-5)
  # The step did something.
  assert one[1]['grad_norm'] > 0
  assert not np.allclose(jax.tree.leaves(one[0].params)[0],
                         jax.tree.leaves(params)[0])


def test_batch_must_split_evenly_over_devices():
  with pytest.raises(ValueError, match='divisible'):
    sharding.per_host_batch_size(6, sharding.make_mesh())


def test_train_step_traces_once():
  params, loss_fn, batch, frozen = _slotformer_setup()
  optimizer = optax.adam(1e-3)

  def step_fn(state, batch, frozen):
    return steps.train_step(state, batch, frozen, loss_fn=loss_fn,
                            optimizer=optimizer, seed=0)

  update = jax.jit(chex.assert_max_traces(step_fn, n=1))
  state = TrainState.create(params, optimizer)
  for step in range(3):
    state, _ = update(state, {k: v + step for k, v in batch.items()}, frozen)
  assert int(state.step) == 3


def _stage_config(num_steps):
  return ml_collections.ConfigDict(dict(
      num_train_steps=num_steps, learning_rate=1e-3, warmup_fraction=0.25,
      grad_clip=0.05, min_lr_fraction=0.0,
      group_learning_rates={}, stop_check_every=1, batch_size=4,
      log_every=1, checkpoint_every=2))


class _Interrupted(Exception):
  pass


def _savi_stage(directory, num_steps, source, interrupt_after=None,
                trace_counter=None):
  model = _savi()

  def loss_fn(*args):
    if trace_counter is not None:
      trace_counter.append(1)  # runs once per trace, not per step
    return losses.savi_loss(*args, model=model, kl_weight=0.0)

  def batches(start_step):
    stream = pipeline.train_batches(source, batch_size=4, clip_length=2,
                                    seed=0, start_step=start_step,
                                    prefetch=0)
    for count, batch in enumerate(stream):
      if interrupt_after is not None and count == interrupt_after:
        raise _Interrupted()
      yield batch

  return Stage(
      name='savi', directory=str(directory), config=_stage_config(num_steps),
      loss_fn=loss_fn,
      init_params=lambda rng: steps.init_params(
          model, rng, jnp.zeros((1, 2, *RESOLUTION, 3))),
      batches=batches)


def test_killed_run_resumes_to_identical_parameters(tmp_path):
  source = [{'video': _video(1, 5, seed=i)[0]} for i in range(6)]
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  traces = []
  uninterrupted = fit(_savi_stage(tmp_path / 'a', 5, source,
                                  trace_counter=traces), mesh=mesh, seed=0)
  assert len(traces) == 1, 'the update step was traced more than once'
  assert int(uninterrupted.step) == 5

  with pytest.raises(_Interrupted):  # killed while fetching batch 4
    fit(_savi_stage(tmp_path / 'b', 5, source, interrupt_after=3), mesh=mesh,
        seed=0)
  resumed = fit(_savi_stage(tmp_path / 'b', 5, source), mesh=mesh, seed=0)
  assert int(resumed.step) == 5
  chex.assert_trees_all_close(resumed.params, uninterrupted.params, atol=0,
                              rtol=0)
  chex.assert_trees_all_close(resumed.opt_state, uninterrupted.opt_state,
                              atol=0, rtol=0)
  # The resumed run continued from step 2's checkpoint: its log starts at 3.
  log = (tmp_path / 'b' / 'train_log.jsonl').read_text().splitlines()
  assert [int(line.split('"step": ')[1].split(',')[0]) for line in log] == [
      1, 2, 3, 3, 4, 5]


def _slotformer_stage(directory, num_steps, source, decoder_params,
                      interrupt_after=None):
  model = _slotformer()  # dropout on: the resumed RNG stream must match

  def batches(start_step):
    stream = pipeline.train_batches(
        source, batch_size=4, clip_length=4, seed=0, start_step=start_step,
        fields=('slots', 'video'), prefetch=0)
    for count, batch in enumerate(stream):
      if interrupt_after is not None and count == interrupt_after:
        raise _Interrupted()
      yield batch

  return Stage(
      name='slotformer', directory=str(directory),
      config=_stage_config(num_steps),
      loss_fn=functools.partial(
          losses.slotformer_loss, model=model, decoder=_decoder(), rollout=2,
          weights={'slot_loss': 1.0, 'image_loss': 1.0}, teacher_forcing=False),
      init_params=lambda rng: steps.init_params(
          model, rng, jnp.zeros((1, 2, 3, 16)), 2),
      batches=batches, frozen_params=decoder_params)


def test_killed_slotformer_run_resumes_to_identical_parameters(tmp_path):
  rng = np.random.default_rng(0)
  source = [{'slots': rng.normal(size=(6, 3, 16)).astype(np.float32),
             'video': _video(1, 6, seed=i)[0]} for i in range(6)]
  decoder_params = _decoder().init(jax.random.key(1),
                                   jnp.zeros((1, 3, 16)))['params']
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  uninterrupted = fit(_slotformer_stage(tmp_path / 'a', 5, source,
                                        decoder_params), mesh=mesh, seed=0)
  with pytest.raises(_Interrupted):
    fit(_slotformer_stage(tmp_path / 'b', 5, source, decoder_params,
                          interrupt_after=3), mesh=mesh, seed=0)
  resumed = fit(_slotformer_stage(tmp_path / 'b', 5, source, decoder_params),
                mesh=mesh, seed=0)
  assert int(resumed.step) == 5
  chex.assert_trees_all_close(resumed.params, uninterrupted.params, atol=0,
                              rtol=0)
  # The frozen decoder is an input of the step, never trained or saved.
  assert 'decoder' not in resumed.params


def test_nan_loss_stops_with_a_clear_message(tmp_path):
  source = [{'video': _video(1, 3, seed=i)[0]} for i in range(4)]
  stage = _savi_stage(tmp_path, 3, source)
  poisoned = dataclasses.replace(stage, loss_fn=lambda *a: (jnp.nan, {}))
  with pytest.raises(FloatingPointError, match='loss became nan at step 1'):
    fit(poisoned, mesh=Mesh(np.asarray(jax.devices()[:1]), ('data',)),
        seed=0)


def test_image_loss_reads_the_last_rollout_frames():
  """The training stream hands L_I only the rollout's frames
  (SlotSource(video_from=burn_in)); the loss equals the full clip's."""
  params, loss_fn, batch, decoder_params = _slotformer_setup()
  rng = jax.random.key(4)
  full_loss, full_metrics = loss_fn(params, batch, decoder_params, rng)
  tail = dict(batch, video=batch['video'][:, 2:])  # burn-in 2, rollout 2
  tail_loss, tail_metrics = loss_fn(params, tail, decoder_params, rng)
  assert float(full_metrics['image_loss']) > 0
  np.testing.assert_array_equal(np.asarray(tail_loss), np.asarray(full_loss))
  np.testing.assert_array_equal(np.asarray(tail_metrics['image_loss']),
                                np.asarray(full_metrics['image_loss']))
  # The burn-in frames do not enter it.
  other = dict(batch, video=np.concatenate(
      [255 - batch['video'][:, :2], batch['video'][:, 2:]], axis=1))
  np.testing.assert_array_equal(
      np.asarray(loss_fn(params, other, decoder_params, rng)[0]),
      np.asarray(full_loss))
