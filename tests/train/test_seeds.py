"""Several seeds in one program (train/seeds.py): seed k of a K-seed run is
the one-seed run with seed k, on 1 and 4 devices and after a resume; a
diverging seed is named in one line and stops the run or is left behind."""

import dataclasses
import functools
import itertools
import json
import logging
import os
import re
import signal

import chex
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from slotformer_jax.errors import ConfigError
from slotformer_jax.stages import task as task_lib
from slotformer_jax.runtime import sharding
from slotformer_jax.runtime.preemption import Preempted
from slotformer_jax.train import seeds as seeds_lib
from slotformer_jax.train.seeds import Seeds
from slotformer_jax.train.seeds import SeedsState
from slotformer_jax.train.trainer import DEVICE_PREFETCH
from slotformer_jax.train.trainer import Diverged
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train import trainer
import test_steve_training
import test_training

SEEDS = (1, 2)
NUM_STEPS = 3
# Seed k of the vmapped program against the one-seed program: the same
# float32 operations batched, which XLA may order differently; measured
# differences are ~1e-7 after 3 Adam steps, far below this bound.
TOLERANCE = dict(atol=2e-5, rtol=2e-5)


def _fit(stage, *, mesh, seed=0, seeds=None):
  """The trainer as the pipeline calls it (`seeds.fit`): one stage every
  seed shares; one seed without `seeds`."""
  return seeds_lib.fit([stage], mesh=mesh,
                       seeds=seeds if seeds is not None else Seeds((seed,)))


def _one_device():
  return Mesh(np.asarray(jax.devices()[:1]), ('data',))


def _savi(directory, num_steps=NUM_STEPS, interrupt_after=None):
  source = [{'video': test_training._video(1, 5, seed=i)[0]}
            for i in range(6)]
  return test_training._savi_stage(directory, num_steps, source,
                                   interrupt_after=interrupt_after)


def _slotformer(directory, num_steps=NUM_STEPS, interrupt_after=None):
  rng = np.random.default_rng(0)
  source = [{'slots': rng.normal(size=(6, 3, 16)).astype(np.float32),
             'video': test_training._video(1, 6, seed=i)[0]}
            for i in range(6)]
  decoder_params = test_training._decoder().init(
      jax.random.key(1), jnp.zeros((1, 3, 16)))['params']
  return test_training._slotformer_stage(directory, num_steps, source,
                                         decoder_params,
                                         interrupt_after=interrupt_after)


def _steve(directory, num_steps=NUM_STEPS, interrupt_after=None):
  return test_steve_training._steve_stage(
      directory, num_steps, test_steve_training._source(),
      interrupt_after=interrupt_after)


def _dvae(directory, num_steps=NUM_STEPS, interrupt_after=None):
  return test_steve_training._dvae_stage(
      directory, num_steps, test_steve_training._source(),
      interrupt_after=interrupt_after)


STAGES = {'savi': _savi, 'slotformer': _slotformer, 'steve': _steve,
          'dvae': _dvae}


def _mesh(devices):
  return Mesh(np.asarray(jax.devices()[:devices]), ('data',))


@pytest.fixture(scope='module')
def one_seed_runs(tmp_path_factory):
  """{(stage, seed, devices): TrainState of the one-seed run} (made once)."""
  cache = {}

  def get(name, seed, devices=1):
    if (name, seed, devices) not in cache:
      directory = tmp_path_factory.mktemp(f'{name}_seed{seed}')
      cache[name, seed, devices] = jax.device_get(
          trainer.fit(STAGES[name](directory), mesh=_mesh(devices),
                      seed=seed))
    return cache[name, seed, devices]
  return get


def _assert_seeds_equal_one_seed_runs(state, one_seed_runs, name, seeds,
                                      devices=1, checked=None):
  """Seed k of `state` against the one-seed run with seed k on as many
  devices (the same split of the batch); `checked`: those indices only."""
  assert isinstance(state, SeedsState)
  state = jax.device_get(state)
  np.testing.assert_array_equal(state.diverged_at, 0)
  for index, seed in enumerate(seeds):
    if checked is not None and index not in checked:
      continue
    reference = one_seed_runs(name, seed, devices)
    assert int(state.seed(index).step) == int(reference.step) == NUM_STEPS
    chex.assert_trees_all_close(state.seed(index).params, reference.params,
                                **TOLERANCE)
    chex.assert_trees_all_close(state.seed(index).opt_state,
                                reference.opt_state, **TOLERANCE)
  # The seeds differ (initialisation and step RNG are their own).
  first, second = (jax.tree.leaves(state.seed(i).params)[0] for i in (0, 1))
  assert not np.allclose(first, second)


# 4 devices and STEVE: about a minute each on 2 cores, in the slow suite.
# loop 'auto': 'unroll' on CPU (1 device, or split over 4: 2 x 2); 'vmap'
# split over 4 as on an accelerator.
@pytest.mark.parametrize('name,devices,loop', [
    ('savi', 1, 'auto'), ('slotformer', 1, 'auto'), ('savi', 1, 'vmap'),
    pytest.param('slotformer', 1, 'vmap', marks=pytest.mark.slow),
    pytest.param('savi', 4, 'auto', marks=pytest.mark.slow),
    pytest.param('slotformer', 4, 'auto', marks=pytest.mark.slow),
    pytest.param('savi', 4, 'vmap', marks=pytest.mark.slow),
    pytest.param('steve', 1, 'auto', marks=pytest.mark.slow),
    pytest.param('steve', 4, 'auto', marks=pytest.mark.slow),
    # Vmapped and split, XLA:CPU miscompiled its 1x1 output convolution.
    pytest.param('dvae', 4, 'auto', marks=pytest.mark.slow)])
def test_seed_k_of_k_seeds_is_the_one_seed_run(tmp_path, one_seed_runs,
                                               name, devices, loop):
  """On 4 devices, vmapped: 2 seeds x 2 data devices (the 'seed' mesh
  axis), seed k against the one-seed run on 2 devices, the same split of
  the batch; unrolled ('auto' on CPU): the seeds replicated, the batch
  split in 4, against the 4-device run (only the last seed there, to keep
  the compiles few: the first is checked on 1 device)."""
  seeds = Seeds(SEEDS, loop=loop)
  assert seeds.loop_on(_mesh(devices)) == (
      'vmap' if loop == 'vmap' else 'unroll')
  state = _fit(STAGES[name](tmp_path), mesh=_mesh(devices), seeds=seeds)
  reference_devices = 1
  if devices == 4:
    leaf = jax.tree.leaves(state.params)[0]
    if loop == 'vmap':
      assert leaf.sharding.spec[0] == 'seed'
      reference_devices = 2
    else:
      assert leaf.sharding.is_fully_replicated
      reference_devices = 4
  _assert_seeds_equal_one_seed_runs(
      state, one_seed_runs, name, SEEDS, reference_devices,
      checked=None if devices == 1 else (len(SEEDS) - 1,))
  # One log line per seed and step, named.
  lines = [json.loads(line) for line in
           (tmp_path / 'train_log.jsonl').read_text().splitlines()]
  assert [(r['step'], r['seed']) for r in lines] == [
      (step, seed) for step in range(1, NUM_STEPS + 1) for seed in SEEDS]


@pytest.mark.parametrize('name', ['savi', 'slotformer'])
def test_k_seed_init_is_each_one_seed_init(tmp_path, name):
  """The K-seed initialiser (one program, a loop over the seeds' keys)
  draws seed k's parameters and optimiser state bit for bit as the one-seed
  initialiser with seed k."""
  stage = STAGES[name](tmp_path)
  stacked = jax.device_get(
      seeds_lib.program([stage], _one_device(), Seeds(SEEDS)).init())
  np.testing.assert_array_equal(stacked.step, 0)
  np.testing.assert_array_equal(stacked.diverged_at, 0)
  for index, seed in enumerate(SEEDS):
    one = jax.device_get(trainer.one_seed(stage, _one_device(), seed).init())
    chex.assert_trees_all_equal(stacked.seed(index).params, one.params)
    chex.assert_trees_all_equal(stacked.seed(index).opt_state, one.opt_state)


def test_k_seed_init_takes_no_batched_lapack_call(tmp_path):
  """The K-seed initialiser, replicated on 4 CPU devices, decomposes each
  orthogonal recurrent kernel (SAVi's GRU) as one matrix: a batched QR's
  LAPACK kernel (jaxlib 0.10.2) waits on XLA:CPU's thread pool from a
  thread of that pool, and four at once hung the init (docs/seeds.md)."""
  text = seeds_lib.program([_savi(tmp_path)], _mesh(4),
                           Seeds(SEEDS)).init.lower().as_text()
  calls = re.findall(r'(lapack_\w+)"?\(%[^)]*\)[^\n]*: \(tensor<([0-9x]+)x',
                     text)
  assert calls, 'no LAPACK call: the test no longer sees the QR'
  for name, shape in calls:
    assert shape.count('x') == 1, (name, shape)  # one 2-D matrix


def test_seed_mesh_shapes():
  mesh = sharding.make_mesh()
  assert dict(seeds_lib.seed_mesh(mesh, 2).shape) == {'seed': 2, 'data': 2}
  assert dict(seeds_lib.seed_mesh(mesh, 4).shape) == {'seed': 4, 'data': 1}
  # 4 devices do not split into 3 seed groups: seeds replicated.
  assert seeds_lib.seed_mesh(mesh, 3) is mesh
  assert seeds_lib.seed_mesh(mesh, 1) is mesh


@pytest.mark.slow
def test_seeds_replicated_when_the_devices_do_not_split(tmp_path,
                                                        one_seed_runs):
  """3 seeds on 4 devices (or seed_axis=False): the seeds are replicated
  and the batch split in 4, as in the 4-device one-seed run."""
  seeds = (0, 1, 2)
  state = _fit(_savi(tmp_path), mesh=_mesh(4), seed=0, seeds=Seeds(seeds))
  assert jax.tree.leaves(state.params)[0].sharding.is_fully_replicated
  _assert_seeds_equal_one_seed_runs(state, one_seed_runs, 'savi', seeds, 4,
                                    checked=(2,))


@pytest.mark.parametrize('devices,seed_axis', [
    (1, True), pytest.param(4, True, marks=pytest.mark.slow),
    pytest.param(4, False, marks=pytest.mark.slow)])
def test_killed_k_seed_run_resumes_to_identical_state(tmp_path, devices,
                                                      seed_axis):
  mesh = _mesh(devices)
  num_steps = 5
  seeds = Seeds(SEEDS, seed_axis=seed_axis)
  uninterrupted = _fit(_slotformer(tmp_path / 'a', num_steps), mesh=mesh,
                      seed=0, seeds=seeds)
  with pytest.raises(test_training._Interrupted):  # after step 2's save
    _fit(_slotformer(tmp_path / 'b', num_steps, interrupt_after=3),
        mesh=mesh, seed=0, seeds=seeds)
  resumed = _fit(_slotformer(tmp_path / 'b', num_steps), mesh=mesh, seed=0,
                seeds=seeds)
  assert isinstance(resumed, SeedsState)
  chex.assert_trees_all_close(jax.device_get(resumed),
                              jax.device_get(uninterrupted), atol=0, rtol=0)


def test_preempted_k_seed_run_resumes_to_identical_state(tmp_path):
  """SIGTERM while step 3 runs (the trainer fetches DEVICE_PREFETCH - 1
  batches ahead): step 3's stacked state is saved, `Preempted` raised; the
  rerun ends where the uninterrupted run does."""
  good, _ = _toy_seeds()
  seeds = Seeds(good)
  uninterrupted = jax.device_get(_fit(_toy_stage(tmp_path / 'a', 5),
                                     mesh=_one_device(), seed=0,
                                     seeds=seeds))
  stage = _toy_stage(tmp_path / 'b', 5)
  plain = stage.batches
  # The trainer takes the batch of step k while step k - DEVICE_PREFETCH + 1
  # runs (tests/reliability/test_reliability.py): signalled then, it stops
  # after update 3.
  signal_at = 2 + DEVICE_PREFETCH - 1

  def batches(start_step):
    for step, batch in zip(itertools.count(start_step), plain(start_step)):
      if step == signal_at:
        os.kill(os.getpid(), signal.SIGTERM)
      yield batch

  with pytest.raises(Preempted, match='stopped by SIGTERM after step 3;'):
    _fit(dataclasses.replace(stage, batches=batches), mesh=_one_device(),
        seed=0, seeds=seeds)
  resumed = jax.device_get(_fit(_toy_stage(tmp_path / 'b', 5),
                               mesh=_one_device(), seed=0, seeds=seeds))
  chex.assert_trees_all_close(resumed, uninterrupted, atol=0, rtol=0)


def test_resuming_with_other_seeds_is_one_line(tmp_path):
  good, _ = _toy_seeds()
  _fit(_toy_stage(tmp_path, num_steps=2), mesh=_one_device(), seed=0,
      seeds=Seeds(good))
  longer = _toy_stage(tmp_path, num_steps=4)
  with pytest.raises(ConfigError, match=(
      rf'trained with seeds \[{good[0]}, {good[1]}\] \(shared data order\), '
      rf'the config asks for seeds \[{good[0]}, 99\]')):
    _fit(longer, mesh=_one_device(), seed=0, seeds=Seeds((good[0], 99)))
  with pytest.raises(ConfigError, match='the config asks for one seed'):
    _fit(longer, mesh=_one_device(), seed=0)


@pytest.mark.parametrize('values', [(), (1, 1)])
def test_bad_seeds_are_one_line(values):
  with pytest.raises(ConfigError, match='seeds must be distinct ints'):
    Seeds(values)


# A toy stage whose loss is log(w): finite for a seed whose init w > 0,
# NaN in the first update for one whose w < 0.
def _toy_init(rng):
  return {'w': jax.random.uniform(rng, (), minval=-1.0, maxval=1.0)}


def _toy_stage(directory, num_steps=4):
  def batches(start_step):
    del start_step
    while True:
      yield {'x': np.ones((4, 1), np.float32)}

  def loss_fn(params, batch, frozen, rng):
    del frozen, rng
    loss = jnp.log(params['w']) * jnp.mean(batch['x'])
    return loss, {}

  config = ml_collections.ConfigDict(dict(
      num_train_steps=num_steps, learning_rate=1e-2, warmup_fraction=0.25,
      grad_clip=0.0, min_lr_fraction=0.0,
      group_learning_rates={}, stop_check_every=1, batch_size=4,
      log_every=1, checkpoint_every=2))
  return Stage(name='toy', directory=str(directory), config=config,
               loss_fn=loss_fn, init_params=_toy_init, batches=batches)


def _toy_seeds():
  """(seeds whose init w is > 0, the first seed whose w is < 0)."""
  w = {s: float(_toy_init(jax.random.key(s))['w']) for s in range(20)}
  good = tuple(s for s in w if w[s] > 0.1)[:2]
  bad = next(s for s in w if w[s] < 0)
  return good, bad


def test_a_diverging_seed_stops_the_run_in_one_line(tmp_path):
  good, bad = _toy_seeds()
  with pytest.raises(Diverged) as caught:
    _fit(_toy_stage(tmp_path), mesh=_one_device(), seed=0,
        seeds=Seeds((good[0], bad, good[1])))
  message = str(caught.value)
  assert '\n' not in message
  assert message.startswith(f'toy: seed {bad} diverged in update 1 ')
  assert 'there is no checkpoint yet' in message
  assert not (tmp_path / 'checkpoints').exists() or not any(
      p.name.isdigit() for p in (tmp_path / 'checkpoints').iterdir())


def test_a_diverging_seed_is_left_behind_and_the_others_go_on(tmp_path,
                                                             caplog):
  good, bad = _toy_seeds()
  seeds = Seeds((good[0], bad, good[1]), on_divergence='continue')
  with caplog.at_level(logging.WARNING):
    state = jax.device_get(_fit(_toy_stage(tmp_path), mesh=_one_device(),
                               seed=0, seeds=seeds))
  warnings = [r.getMessage() for r in caplog.records
              if 'diverged' in r.getMessage()]
  assert len(warnings) == 1  # named once, not at every step
  assert warnings[0].startswith(f'toy: seed {bad} diverged in update 1 ')
  np.testing.assert_array_equal(state.diverged_at, [0, 1, 0])
  # The diverged seed keeps its initial (finite) parameters; the others
  # trained all 4 steps.
  assert float(state.params['w'][1]) == float(_toy_init(
      jax.random.key(bad))['w'])
  for index, seed in ((0, good[0]), (2, good[1])):
    assert float(state.params['w'][index]) != float(
        _toy_init(jax.random.key(seed))['w'])
  assert np.isfinite(state.params['w']).all()
  # The log holds the two training seeds only: no NaN in it.
  lines = [json.loads(line) for line in
           (tmp_path / 'train_log.jsonl').read_text().splitlines()]
  assert {r['seed'] for r in lines} == set(good)
  assert all(np.isfinite(r['loss']) for r in lines)
  # Resumed (a longer run) it stays diverged and is named again once.
  caplog.clear()
  longer = dataclasses.replace(_toy_stage(tmp_path, num_steps=6))
  with caplog.at_level(logging.WARNING):
    state = jax.device_get(_fit(longer, mesh=_one_device(), seed=0,
                               seeds=seeds))
  np.testing.assert_array_equal(state.diverged_at, [0, 1, 0])
  assert int(state.step[0]) == 6


def test_every_seed_diverging_stops_even_when_continuing(tmp_path):
  _, bad = _toy_seeds()
  other_bad = next(s for s in range(bad + 1, 50)
                   if float(_toy_init(jax.random.key(s))['w']) < 0)
  with pytest.raises(Diverged, match='no seed is left'):
    _fit(_toy_stage(tmp_path), mesh=_one_device(), seed=0,
        seeds=Seeds((bad, other_bad), on_divergence='continue'))


def test_per_seed_data_order_gives_each_seed_its_stream(tmp_path):
  """One stage per seed: seed k trains on stage k's batches, stacked."""
  drawn = []

  def batches_of(seed, start_step):
    for step in range(start_step, 100):
      drawn.append((seed, step))
      yield {'x': np.full((4, 1), 1.0 + seed + step, np.float32)}

  good, _ = _toy_seeds()
  stages = [dataclasses.replace(_toy_stage(tmp_path, num_steps=2),
                                batches=functools.partial(batches_of, seed))
            for seed in good]
  state = seeds_lib.fit(stages, mesh=_one_device(),
                        seeds=Seeds(good, data_order='per_seed'))
  # Each seed's own stream from step 0 (the device prefetch may have
  # drawn a step ahead of the last update).
  assert {(seed, step) for seed, step in drawn if step < 2} == {
      (good[0], 0), (good[0], 1), (good[1], 0), (good[1], 1)}
  assert {seed for seed, _ in drawn} == set(good)
  assert int(jax.device_get(state.step)[0]) == 2
  # The seeds' losses: log(w) times their own batch's mean.
  lines = [json.loads(line) for line in
           (tmp_path / 'train_log.jsonl').read_text().splitlines()]
  first = {r['seed']: r['loss'] for r in lines if r['step'] == 1}
  for seed in good:
    w = float(_toy_init(jax.random.key(seed))['w'])
    np.testing.assert_allclose(first[seed], np.log(w) * (1.0 + seed),
                               rtol=1e-6)


def test_stages_are_one_or_one_per_seed(tmp_path):
  good, _ = _toy_seeds()
  with pytest.raises(ValueError, match='one stage or one per seed'):
    seeds_lib.fit([_toy_stage(tmp_path)] * 3, mesh=_one_device(),
                  seeds=Seeds(good))


# ---- config.seeds -----------------------------------------------------


def _config(**fields):
  from slotformer_jax.config.defaults import base_config
  config = base_config()
  for name, value in fields.items():
    config[name] = value
  return config


@pytest.mark.parametrize('seeds,needle', [
    ((), 'seeds must be a non-empty tuple of ints'),
    ((0, 1, 1), 'seeds must be distinct, got (0, 1, 1) (1 repeated)'),
    ((0, 1.5), 'seeds must be integers in [0, 2147483646] (what a jax '
     'PRNG key holds), got (0, 1.5)'),
    ((0, '1'), "seeds must be integers in [0, 2147483646] (what a jax "
     "PRNG key holds), got (0, '1')"),
    # Issue 61: these passed, made the data, then ended in a traceback.
    ((0, 2**31), 'seeds must be integers in [0, 2147483646]'),
    ((0, 2**31 - 1), 'seeds must be integers in [0, 2147483646]'),
    ((-1, 0), 'seeds must be integers in [0, 2147483646]'),
])
def test_bad_config_seeds_are_one_line(seeds, needle):
  problems = task_lib.seeds_problems(_config(seeds=seeds), ('train_savi',))
  assert problems == [problems[0]] and needle in problems[0]


def test_bad_seed_choices_are_one_line_each():
  problems = task_lib.seeds_problems(
      _config(seed_data_order='random', on_seed_divergence='skip'),
      ('train_savi',))
  assert problems == [
      "seed_data_order must be one of 'shared', 'per_seed', got 'random'",
      "on_seed_divergence must be one of 'stop', 'continue', got 'skip'"]


def test_stages_without_several_seeds_refuse_them_in_one_line():
  config = _config(seeds=(0, 1, 2))
  assert task_lib.seeds_problems(config, ('prepare_data', 'train_savi')) == []
  problems = task_lib.seeds_problems(
      config, ('prepare_data', 'train_savi', 'extract_slots',
               'train_slotformer', 'train_slot_lstm', 'train_readout'))
  assert len(problems) == 1
  assert problems[0].startswith(
      'seeds=(0, 1, 2) trains several seeds in train_savi, train_dvae, '
      'extract_slots, train_slotformer, train_slot_lstm, evaluate, render, '
      "explore only for now (slot_model='savi'; docs/seeds.md); "
      'train_readout does not take several')
  # One seed (or none) is today's run: nothing refused.
  for one in (None, (3,)):
    assert task_lib.seeds_problems(_config(seeds=one),
                                 ('train_slotformer', 'evaluate')) == []


def test_default_config_is_one_seed():
  config = _config(seed=5)
  assert Seeds.of_config(config) == Seeds((5,))
  # A one-value `seeds` is one seed: config.seed's.
  assert Seeds.of_config(_config(seed=5, seeds=(4,))) == Seeds((5,))
  assert not Seeds.of_config(config).several
  seeds = Seeds.of_config(
      _config(seeds=(0, 1, 2), seed_data_order='per_seed',
              on_seed_divergence='continue')).map(lambda seed: seed + 1)
  assert seeds == Seeds((1, 2, 3), data_order='per_seed',
                        on_divergence='continue')
