"""STEVE's losses, schedules and stages: resume, single tracing, devices."""

import functools

import chex
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import pytest

from slotformer_jax.data import pipeline
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.train import optim
from slotformer_jax.runtime import sharding
from slotformer_jax.train import steps
from slotformer_jax import losses
from slotformer_jax.slot_models import steve as steve_slots
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit
from tiny_models import tiny_steve

RESOLUTION = (16, 16)
VOCAB = 16


def _dvae():
  return DVAE(vocab_size=VOCAB, hidden_size=8)


def _steve():
  return tiny_steve(RESOLUTION, VOCAB, decoder=dict(dropout_rate=0.1))


def _video(batch, time, seed=0):
  rng = np.random.default_rng(seed)
  return rng.integers(0, 256, (batch, time, *RESOLUTION, 3), dtype=np.uint8)


def _tokens(batch, time, seed=0):
  rng = np.random.default_rng(seed + 100)
  return rng.integers(0, VOCAB, (batch, time, 16), dtype=np.uint16)


def test_gumbel_temperature_schedule():
  num_steps = 1000  # annealed over the first 150 steps
  temperature = lambda step: steve_slots.gumbel_temperature(step, num_steps)
  assert temperature(0) == pytest.approx(1.0)
  assert temperature(75) == pytest.approx(0.55)  # half-way down the cosine
  assert temperature(150) == pytest.approx(0.1)
  assert temperature(999) == pytest.approx(0.1)
  values = [temperature(s) for s in range(160)]
  assert all(a > b for a, b in zip(values[:150], values[1:151]))
  # Cosine, not linear: slow at both ends.
  assert 1.0 - temperature(15) < 0.55 - temperature(90)
  # The batches carry their own step's temperature, also when resumed.
  stream = steve_slots.with_gumbel_temperature(
      iter([{'video': np.zeros((2, 1))}] * 3), 74, num_steps)
  got = [float(b['gumbel_temperature'][0]) for b in stream]
  np.testing.assert_allclose(got, [temperature(74), temperature(75),
                                   temperature(76)], rtol=1e-6)


def test_decoder_group_learning_rate():
  """The decoder's Adam steps are 3x the rest (lr 3e-4 vs 1e-4)."""
  config = ml_collections.ConfigDict(dict(
      num_train_steps=100, learning_rate=1e-4, warmup_fraction=0.05,
      min_lr_fraction=0.0, grad_clip=0.05,
      group_learning_rates={'decoder': 3e-4}))
  optimizer, schedule = optim.make_optimizer(config)
  params = {'decoder': {'w': jnp.ones(3)}, 'encoder': {'w': jnp.ones(3)}}
  grads = jax.tree.map(lambda x: 0.01 * x, params)
  state = optimizer.init(params)
  for _ in range(3):
    updates, state = optimizer.update(grads, state, params)
  ratio = updates['decoder']['w'] / updates['encoder']['w']
  np.testing.assert_allclose(ratio, 3.0, rtol=1e-5)
  np.testing.assert_allclose(updates['encoder']['w'], -schedule(2), rtol=1e-3)


def _stage_config(num_steps, **extra):
  # `extra` may replace a field (group_learning_rates), not only add one.
  fields = dict(
      num_train_steps=num_steps, learning_rate=1e-3, warmup_fraction=0.25,
      grad_clip=0.05, min_lr_fraction=0.0,
      group_learning_rates={}, stop_check_every=1, batch_size=4,
      log_every=1, checkpoint_every=2)
  return ml_collections.ConfigDict({**fields, **extra})


class _Interrupted(Exception):
  pass


def _interruptible(stream, interrupt_after):
  for count, batch in enumerate(stream):
    if interrupt_after is not None and count == interrupt_after:
      raise _Interrupted()
    yield batch


def _dvae_stage(directory, num_steps, source, interrupt_after=None):
  model = _dvae()

  def batches(start_step):
    frames = pipeline.train_batches(source, batch_size=4, clip_length=1,
                                    seed=0, start_step=start_step, prefetch=0)
    return _interruptible(steve_slots.with_gumbel_temperature(
        frames, start_step, num_steps), interrupt_after)

  return Stage(
      name='dvae', directory=str(directory), config=_stage_config(num_steps),
      loss_fn=functools.partial(losses.dvae_loss, model=model),
      init_params=lambda rng: steps.init_params(
          model, rng, jnp.zeros((1, *RESOLUTION, 3)), 1.0),
      batches=batches)


def _steve_stage(directory, num_steps, source, interrupt_after=None):
  model = _steve()  # dropout on: the resumed RNG stream must match
  config = _stage_config(num_steps, group_learning_rates={'decoder': 3e-3})

  def batches(start_step):
    return _interruptible(pipeline.train_batches(
        source, batch_size=4, clip_length=2, seed=0, start_step=start_step,
        fields=('video', 'tokens'), prefetch=0), interrupt_after)

  return Stage(
      name='steve', directory=str(directory), config=config,
      loss_fn=functools.partial(losses.steve_loss, model=model),
      init_params=lambda rng: steps.init_params(
          model, rng, jnp.zeros((1, 2, *RESOLUTION, 3)),
          jnp.zeros((1, 2, 16), jnp.int32)),
      batches=batches)


def _source():
  return [{'video': _video(1, 4, seed=i)[0], 'tokens': _tokens(1, 4, i)[0]}
          for i in range(6)]


# Three fits each (about a minute of compiling per stage on 2 cores): slow.
@pytest.mark.slow
@pytest.mark.parametrize('make_stage', [_dvae_stage, _steve_stage],
                         ids=['dvae', 'steve'])
def test_killed_run_resumes_to_identical_parameters(tmp_path, make_stage):
  source = _source()
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  uninterrupted = fit(make_stage(tmp_path / 'a', 4, source), mesh=mesh,
                      seed=0)
  assert int(uninterrupted.step) == 4
  with pytest.raises(_Interrupted):  # killed while fetching batch 4
    fit(make_stage(tmp_path / 'b', 4, source, interrupt_after=3), mesh=mesh,
        seed=0)
  resumed = fit(make_stage(tmp_path / 'b', 4, source), mesh=mesh, seed=0)
  assert int(resumed.step) == 4
  chex.assert_trees_all_close(resumed.params, uninterrupted.params, atol=0,
                              rtol=0)
  chex.assert_trees_all_close(resumed.opt_state, uninterrupted.opt_state,
                              atol=0, rtol=0)
  # Training moved the parameters.
  initial = make_stage(tmp_path / 'c', 4, source).init_params(
      jax.random.key(0))
  assert not np.allclose(jax.tree.leaves(initial)[-1],
                         jax.tree.leaves(resumed.params)[-1])


def _setup(name):
  if name == 'dvae':
    model = _dvae()
    params = steps.init_params(model, jax.random.key(0),
                               jnp.zeros((1, *RESOLUTION, 3)), 1.0)
    loss_fn = functools.partial(losses.dvae_loss, model=model)
    batch = {'video': _video(4, 1),
             'gumbel_temperature': np.full(4, 0.5, np.float32)}
  else:
    model = _steve()
    params = steps.init_params(model, jax.random.key(0),
                               jnp.zeros((1, 2, *RESOLUTION, 3)),
                               jnp.zeros((1, 2, 16), jnp.int32))
    loss_fn = functools.partial(losses.steve_loss, model=model)
    batch = {'video': _video(4, 2), 'tokens': _tokens(4, 2)}
  return params, loss_fn, batch


def _run_step(mesh, params, loss_fn, batch, optimizer):
  replicated = sharding.replicated_sharding(mesh)
  update = jax.jit(
      functools.partial(steps.train_step, loss_fn=loss_fn,
                        optimizer=optimizer, seed=3),
      in_shardings=(replicated, sharding.batch_sharding(mesh), replicated),
      out_shardings=(replicated, replicated))
  state = sharding.replicate(TrainState.create(params, optimizer), mesh)
  state, metrics = update(state, sharding.to_global_batch(batch, mesh), None)
  return jax.device_get(state), jax.device_get(metrics)


@pytest.mark.parametrize(
    'name', [pytest.param('dvae', marks=pytest.mark.slow), 'steve'])
def test_four_device_step_equals_one_device_step(name):
  assert jax.device_count() == 4, 'conftest.py asks XLA for 4 CPU devices'
  params, loss_fn, batch = _setup(name)
  # Plain SGD: the update is linear in the all-reduced gradient. The RNG
  # (Gumbel noise, dropout) is drawn for the global batch, so the sharded
  # step must match exactly, not just in distribution.
  optimizer = optax.sgd(0.1)
  one = _run_step(Mesh(np.asarray(jax.devices()[:1]), ('data',)), params,
                  loss_fn, batch, optimizer)
  four = _run_step(sharding.make_mesh(), params, loss_fn, batch, optimizer)
  for key in one[1]:
    np.testing.assert_allclose(four[1][key], one[1][key], rtol=1e-5,
                               atol=1e-5, err_msg=key)
  chex.assert_trees_all_close(four[0].params, one[0].params, atol=1e-5,
                              rtol=1e-5)
  assert one[1]['grad_norm'] > 0


@pytest.mark.parametrize('name', ['dvae', 'steve'])
def test_train_step_traces_once(name):
  chex.clear_trace_counter()
  params, loss_fn, batch = _setup(name)
  optimizer = optax.adam(1e-3)

  def step_fn(state, batch):
    return steps.train_step(state, batch, None, loss_fn=loss_fn,
                            optimizer=optimizer, seed=0)

  update = jax.jit(chex.assert_max_traces(step_fn, n=1))
  state = TrainState.create(params, optimizer)
  for step in range(3):
    changed = dict(batch, video=batch['video'] + step)
    if 'gumbel_temperature' in batch:  # a new temperature every step
      changed['gumbel_temperature'] = batch['gumbel_temperature'] / (step + 1)
    state, _ = update(state, changed)
  assert int(state.step) == 3
