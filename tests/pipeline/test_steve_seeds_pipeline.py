"""Several seeds through the STEVE pipeline (config.seeds, docs/seeds.md).

One run of the micro STEVE pipeline (`synthetic.py:steve_tiny` at 16x16)
with seeds (0, 1) on 2 devices is shared by the tests of this module:
per-seed tokens, slots and evaluations, seed k of the stacked STEVE against
the one-seed run on dVAE seed k's tokens, resuming. The seeds are
replicated and the batch split (`seed_axis=False`, the unrolled program):
split on a 'seed' axis, the vmapped dVAE step fails on XLA:CPU
(jaxlib 0.10.2: its 1x1 output convolution, batched over the seeds into a
grouped convolution, is partitioned with 3 output features for 2 groups).

The pipeline fixture takes minutes on a 2-core CPU (docs/seeds.md), so
every test that runs it is `slow` (the default suite keeps the
config check; the SAVi chain with seeds, which shares every stage after
stage 1, is in the default suite: test_seeds_pipeline.py).
"""

import json
import os
import shutil

import chex
import jax
from jax.sharding import Mesh
import numpy as np
import pytest

from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from slotformer_jax.stages import task as task_lib
from slotformer_jax.data import slots as tokens_lib
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.slots import read_meta
from slotformer_jax.run import Run
from slotformer_jax.runtime.checkpoint import Checkpointer
from slotformer_jax.slot_models import chain
from slotformer_jax.stages import stage1
from slotformer_jax.train.trainer import fit
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import Paths

SEEDS = (0, 1)
STAGES = ['train_dvae', 'tokenize_frames', 'train_steve', 'extract_slots',
          'train_slotformer', 'evaluate']
# As tests/train/test_seeds.py: seed k of the several-seed program against
# the one-seed program, after the same Adam steps.
TOLERANCE = dict(atol=2e-5, rtol=2e-5)


def _mesh(devices):
  return Mesh(np.asarray(jax.devices()[:devices]), ('data',))


@pytest.fixture(scope='module')
def seeded(tmp_path_factory):
  """(config, workdir, {stage: result}) of the micro STEVE pipeline with
  seeds (0, 1) on 2 devices (the seeds replicated, the batch split)."""
  root = tmp_path_factory.mktemp('steve_seeds')
  config = micro_config('steve', root / 'data')
  config.seeds = SEEDS
  config.seed_axis = False
  config.evaluation.metrics = ('fg_ari', 'fg_miou')
  workdir = str(root / 'run')
  return config, workdir, run_stages(config, workdir, _mesh(2), STAGES)


def _stacked_params(directory, shapes):
  """Every seed's parameters of a stacked checkpoint, read by hand:
  [len(SEEDS), ...] leaves, as numpy."""
  stacked = jax.tree.map(
      lambda x: jax.ShapeDtypeStruct((len(SEEDS), *x.shape), x.dtype),
      shapes)
  checkpointer = Checkpointer(os.path.join(directory, 'checkpoints'),
                              read_only=True)
  try:
    params, _ = checkpointer.restore_params(stacked)
  finally:
    checkpointer.close()
  return jax.device_get(params)


def _dvae_parent(workdir):
  """The stacked dVAE's run id and last step (what every seed's tokens and
  the stacked STEVE descend from)."""
  dvae = identity_lib.read_identity(os.path.join(workdir, 'dvae'))
  return identity_lib.parent_of(dvae, 4, 'dvae')


@pytest.mark.slow
def test_each_seed_has_its_tokens_slots_and_evaluation(seeded):
  config, workdir, _ = seeded
  for name in ('tokens', 'slots', 'render', 'explore'):
    assert not os.path.exists(os.path.join(workdir, name)), name
  parent = _dvae_parent(workdir)
  tokens, slots = {}, {}
  for seed in SEEDS:
    paths = Paths.of(workdir).for_seed(seed)
    directory = paths.derived('tokens', 'train')
    assert directory == os.path.join(workdir, f'seed_{seed}', 'tokens',
                                     'train')
    meta = tokens_lib.read_meta(directory)
    assert meta['complete'] and meta['parent'] == parent
    tokens[seed] = np.fromfile(os.path.join(directory, tokens_lib.TOKENS_FILE),
                               np.uint16)
    for split in config.extraction.splits:
      meta = read_meta(paths.slots(split))
      assert meta['complete'] and meta['fields']['seed'] == seed
    slots[seed] = SlotSource(paths.slots('test'), None, ())[0]['slots']
    assert os.path.exists(os.path.join(paths.eval, 'metrics.json'))
  # Seed s's tokens and slots are dVAE / STEVE seed s's: the seeds differ.
  assert not np.array_equal(tokens[0], tokens[1])
  assert not np.allclose(slots[0], slots[1])
  # One stacked checkpoint per trained stage, with its seeds recorded; the
  # stacked STEVE descends from the stacked dVAE.
  for stage, offset in (('dvae', 0), ('steve', 0), ('slotformer', 1)):
    identity = identity_lib.read_identity(os.path.join(workdir, stage))
    assert identity['fields']['seeds'] == {
        'seeds': [s + offset for s in SEEDS], 'data_order': 'shared'}
  steve = identity_lib.read_identity(os.path.join(workdir, 'steve'))
  assert steve['parent'] == parent


@pytest.mark.slow
def test_summary_has_mean_std_and_every_seed(seeded):
  config, workdir, results = seeded
  with open(os.path.join(workdir, 'eval', 'metrics.json')) as f:
    summary = json.load(f)
  assert summary == json.loads(json.dumps(results['evaluate']))
  assert summary['seeds'] == summary['evaluated'] == list(SEEDS)
  assert summary['slot_model'] == 'steve'
  per_seed = {}
  for seed in SEEDS:
    with open(os.path.join(workdir, f'seed_{seed}', 'eval',
                           'metrics.json')) as f:
      per_seed[seed] = json.load(f)
    identity = per_seed[seed]['identity']
    assert identity['dvae']['seed'] == identity['steve']['seed'] == seed
    assert identity['slotformer']['seed'] == seed
  for method, per_metric in summary['rollout'].items():
    for metric, stats in per_metric.items():
      values = [per_seed[s]['rollout'][method][metric]['mean'] for s in SEEDS]
      assert stats['per_seed'] == {str(s): v for s, v in zip(SEEDS, values)}
      np.testing.assert_allclose(stats['mean'], np.mean(values), rtol=1e-12)
      np.testing.assert_allclose(stats['std'], np.std(values), rtol=1e-12)
  fg_ari = summary['steve']['fg_ari']
  assert fg_ari['per_seed'] == {str(s): per_seed[s]['steve']['fg_ari']
                                for s in SEEDS}
  assert {'mean', 'std', 'num_seeds'} <= set(fg_ari)


@pytest.mark.slow
def test_seed_k_is_the_one_seed_steve_on_dvae_seed_k(seeded, tmp_path):
  """Seed k's STEVE after its steps against a one-seed STEVE run (init /
  step RNG seed k, config.seed's stream: the shared order) on the tokens
  of dVAE seed k, on one device."""
  config, workdir, _ = seeded
  run = Run.create(config, workdir, _mesh(1))
  part = run.slot_model.part('steve')
  stacked = _stacked_params(os.path.join(workdir, 'steve'),
                            chain.param_shapes(part))
  for index, seed in enumerate(SEEDS):
    tokens = Paths.of(workdir).for_seed(seed).derived('tokens', 'train')
    source = tokens_lib.TokenSource(tokens, run.videos('train'))
    stage = stage1.part_stage(part, str(tmp_path / f'one_seed_{seed}'),
                              run.mesh, source, seed=config.seed)
    one_seed = jax.device_get(fit(stage, mesh=run.mesh, seed=seed))
    assert int(one_seed.step) == part.section.num_train_steps
    chex.assert_trees_all_close(jax.tree.map(lambda x: x[index], stacked),
                                one_seed.params, **TOLERANCE)


@pytest.mark.slow
def test_a_rerun_resumes_where_the_seeds_stopped(seeded, tmp_path):
  """A run killed in the tokenization of seed 1 and in STEVE resumes there
  (seed 0's tokens, the dVAE, every seed's slots and SlotFormer are not
  remade) and ends as the whole run did."""
  config, workdir, _ = seeded
  copy = str(tmp_path / 'copy')
  shutil.copytree(workdir, copy)
  kept = [os.path.join(Paths.of(copy).for_seed(0).derived('tokens', 'train'),
                       tokens_lib.TOKENS_FILE)]
  kept += [os.path.join(Paths.of(copy).for_seed(s).slots(split), 'slots.f32')
           for s in SEEDS for split in config.extraction.splits]
  before = [os.path.getmtime(path) for path in kept]
  # As a kill leaves them: seed 1's tokens incomplete, STEVE's last
  # checkpoint not written.
  seed1 = Paths.of(copy).for_seed(1).derived('tokens', 'train')
  meta = tokens_lib.read_meta(seed1)
  with open(os.path.join(seed1, tokens_lib.META_FILE), 'w') as f:
    json.dump(dict(meta, complete=False), f)
  checkpoints = os.path.join(copy, 'steve', 'checkpoints')
  steps = sorted(int(s) for s in os.listdir(checkpoints) if s.isdigit())
  assert steps[-1] == config.steve.num_train_steps and len(steps) > 1
  shutil.rmtree(os.path.join(checkpoints, str(steps[-1])))
  unchanged = {stage: sorted(os.listdir(os.path.join(copy, stage,
                                                     'checkpoints')))
               for stage in ('dvae', 'slotformer')}
  run_stages(config, copy, _mesh(2), STAGES[:-1])
  assert [os.path.getmtime(path) for path in kept] == before
  for stage, listing in unchanged.items():
    assert sorted(os.listdir(os.path.join(copy, stage, 'checkpoints'))) == (
        listing), stage
  assert tokens_lib.read_meta(seed1)['complete']
  shapes = chain.param_shapes(
      Run.create(config, copy, _mesh(1)).slot_model.part('steve'))
  chex.assert_trees_all_close(
      _stacked_params(os.path.join(copy, 'steve'), shapes),
      _stacked_params(os.path.join(workdir, 'steve'), shapes),
      atol=0, rtol=0)


@pytest.mark.slow
def test_each_seed_has_its_pictures_and_explorer(seeded):
  config, workdir, _ = seeded
  pictures = run_stages(config, workdir, _mesh(2), ['render'])['render']
  pages = run_stages(config, workdir, _mesh(2), ['explore'])['explore']
  for seed in SEEDS:
    paths = Paths.of(workdir).for_seed(seed)
    assert os.path.join(paths.render, 'rollout_000.gif') in pictures
    assert os.path.join(paths.explore, 'index.html') in pages
    with open(os.path.join(paths.explore, 'identity.json')) as f:
      identity = json.load(f)['identity']
    assert identity['steve']['seed'] == seed
  assert not os.path.exists(os.path.join(workdir, 'render'))
  assert not os.path.exists(os.path.join(workdir, 'explore'))


@pytest.mark.slow
def test_slot_lstm_trains_every_seed_on_its_steve_slots(seeded, tmp_path):
  """The Slot-LSTM baseline (off in the STEVE configs) with several seeds:
  one stacked checkpoint on every seed's STEVE slots."""
  config, workdir, _ = seeded
  config = config.copy_and_resolve_references()
  config.slot_lstm.train = True
  config.slot_lstm.num_train_steps = 2
  copy = str(tmp_path / 'copy')
  shutil.copytree(workdir, copy)
  run_stages(config, copy, _mesh(2), ['train_slot_lstm'])
  slot_lstm = identity_lib.read_identity(os.path.join(copy, 'slot_lstm'))
  slotformer = identity_lib.read_identity(os.path.join(copy, 'slotformer'))
  assert slot_lstm['fields']['seeds'] == {
      'seeds': [s + 1 for s in SEEDS], 'data_order': 'shared'}
  assert slot_lstm['parent'] == slotformer['parent']
  assert os.listdir(os.path.join(copy, 'slot_lstm', 'checkpoints'))


def test_the_steve_chain_takes_several_seeds_the_tasks_do_not():
  config = micro_config('steve', '/nonexistent')
  config.seeds = SEEDS
  assert task_lib.seeds_problems(config, ['prepare_data', *STAGES,
                                        'train_slot_lstm', 'render',
                                        'explore']) == []
  problems = task_lib.seeds_problems(config, ['train_readout'])
  assert len(problems) == 1 and problems[0].startswith(
      'seeds=(0, 1) trains several seeds in train_savi, train_dvae, '
      'tokenize_frames, train_steve, extract_slots, train_slotformer, '
      'train_slot_lstm, evaluate, render, explore only for now '
      "(slot_model='steve'; docs/seeds.md); train_readout does not")
  config.stage1_workdir = '/elsewhere'  # a read-only stage 1 too
  assert task_lib.seeds_problems(config, ['train_steve']) == []
