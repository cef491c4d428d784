"""Several seeds through the SAVi pipeline (config.seeds, docs/seeds.md).

One run of the micro SAVi pipeline with seeds (0, 1) on 2 devices (the
seeds unrolled, as on every CPU, so replicated and the batch split) is
shared by the tests of this module: per-seed slots and evaluations, the
summary, seed k of the stacked SlotFormer against the one-seed run on
stage-1 seed k's slots, resuming.
"""

import dataclasses
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
from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax.stages import task as task_lib
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.slots import read_meta
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import evaluate as evaluate_lib
from slotformer_jax.evaluation import seeds as seeds_lib
from slotformer_jax.run import Run
from slotformer_jax.runtime.checkpoint import Checkpointer
from slotformer_jax.slot_models import chain
from slotformer_jax.stages import dynamics as dynamics_stages
from slotformer_jax.stages import video_prediction
from slotformer_jax.train.trainer import fit
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import Paths

SEEDS = (0, 1)
STAGES = ['train_savi', 'extract_slots', 'train_slotformer',
          'train_slot_lstm', 'evaluate']
# As tests/train/test_seeds.py: seed k of the vmapped program against the
# one-seed program, after the same Adam steps.
TOLERANCE = dict(atol=2e-5, rtol=2e-5)


def _mesh(devices):
  return Mesh(np.asarray(jax.devices()[:devices]), ('data',))


@pytest.fixture(scope='module')
def seeded(tmp_path_factory):
  """(config, workdir, {stage: result}) of the micro SAVi pipeline with
  seeds (0, 1) on 2 devices (seeds replicated, batch split in 2)."""
  root = tmp_path_factory.mktemp('seeds')
  config = micro_config('savi', root / 'data')
  config.seeds = SEEDS
  config.slot_lstm.train = True  # the baseline of the video-prediction table
  # Fewer metrics than the one-seed pipeline test (each seed's evaluation is
  # that one-seed code): a third of the evaluation's compile time.
  config.evaluation.metrics = ('psnr', 'ssim', 'fg_ari', 'fg_miou')
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


def _assert_same_slotformer(config, workdir, reference):
  """The stacked SlotFormer of `workdir` equals `reference`'s, bit for
  bit."""
  shapes = dynamics_lib.param_shapes(
      config.slotformer, 'slotformer',
      Run.create(config, reference, _mesh(1)).slot_model.slot_shape)
  chex.assert_trees_all_close(
      _stacked_params(os.path.join(workdir, 'slotformer'), shapes),
      _stacked_params(os.path.join(reference, 'slotformer'), shapes),
      atol=0, rtol=0)


def test_each_seed_has_its_slots_and_evaluation(seeded):
  config, workdir, results = seeded
  assert not os.path.exists(os.path.join(workdir, 'slots'))
  slots = {}
  for seed in SEEDS:
    paths = Paths.of(workdir).for_seed(seed)
    for split in config.extraction.splits:
      meta = read_meta(paths.slots(split))
      assert meta['complete'] and meta['fields']['seed'] == seed
    slots[seed] = SlotSource(paths.slots('test'), None, ())[0]['slots']
    assert os.path.exists(os.path.join(paths.eval, 'metrics.json'))
  # Seed s's slots are stage-1 seed s's: the seeds differ.
  assert not np.allclose(slots[0], slots[1])
  # One stacked checkpoint per trained stage, with its seeds recorded.
  for stage, offset in (('savi', 0), ('slotformer', 1)):
    identity = identity_lib.read_identity(os.path.join(workdir, stage))
    assert identity['fields']['seeds'] == {
        'seeds': [s + offset for s in SEEDS], 'data_order': 'shared'}


def test_summary_has_mean_std_and_every_seed(seeded):
  config, workdir, results = seeded
  with open(os.path.join(workdir, 'eval', 'metrics.json')) as f:
    summary = json.load(f)
  assert summary == json.loads(json.dumps(results['evaluate']))
  assert summary['seeds'] == summary['evaluated'] == list(SEEDS)
  assert summary['excluded'] == {}
  assert 'population' in summary['std']
  per_seed = {}
  for seed in SEEDS:
    with open(os.path.join(workdir, f'seed_{seed}', 'eval',
                           'metrics.json')) as f:
      per_seed[seed] = json.load(f)
    assert per_seed[seed]['identity']['slotformer']['seed'] == seed
    assert per_seed[seed]['identity']['savi']['seed'] == seed
  assert {'slotformer', 'slot_lstm'} <= set(summary['rollout'])
  for method, per_metric in summary['rollout'].items():
    for metric, stats in per_metric.items():
      values = [per_seed[s]['rollout'][method][metric]['mean'] for s in SEEDS]
      assert stats['per_seed'] == {str(s): v for s, v in zip(SEEDS, values)}
      assert stats['num_seeds'] == 2
      np.testing.assert_allclose(stats['mean'], np.mean(values), rtol=1e-12)
      np.testing.assert_allclose(stats['std'], np.std(values), rtol=1e-12)
      assert len(stats['per_step']) == config.evaluation.rollout_steps
  fg_ari = summary['savi']['fg_ari']
  assert fg_ari['per_seed'] == {str(s): per_seed[s]['savi']['fg_ari']
                                for s in SEEDS}
  assert summary['savi']['num_videos'] == config.data.num_test
  table = seeds_lib.format_table(summary, 'SAVi')
  assert ' +- ' in table and 'seeds [0, 1]' in table


def test_seed_k_is_the_one_seed_run_on_stage1_seed_k(seeded, tmp_path):
  """Seed k's SlotFormer after its steps against a one-seed SlotFormer run
  (init / step RNG seed k + 1, the shared order's stream) on the slots and
  decoder of stage-1 seed k, on one device; and seed k's metrics against
  the one-seed evaluation of that run (float32 rounding apart)."""
  config, workdir, _ = seeded
  run = Run.create(config, workdir, _mesh(1))
  slot_model = run.slot_model
  section = run.dynamics_section('slotformer')
  savi = _stacked_params(os.path.join(workdir, 'savi'),
                         chain.param_shapes(slot_model.parts[0]))
  stacked = _stacked_params(
      os.path.join(workdir, 'slotformer'),
      dynamics_lib.param_shapes(section, 'slotformer', slot_model.slot_shape))
  for index, seed in enumerate(SEEDS):
    slot_params = {'savi': jax.tree.map(lambda x: x[index], savi)}
    slots = Paths.of(workdir).for_seed(seed).slots
    stage = dynamics_stages.dynamics_stage(
        section, 'slotformer', str(tmp_path / f'one_seed_{seed}'),
        run.mesh, slot_model, slot_params,
        SlotSource(slots('train'), run.videos('train'), ('video',)),
        seed=config.seed + 1, compute_dtype=config.compute_dtype)
    one_seed = jax.device_get(fit(stage, mesh=run.mesh, seed=seed + 1))
    assert int(one_seed.step) == section.num_train_steps
    chex.assert_trees_all_close(jax.tree.map(lambda x: x[index], stacked),
                                one_seed.params, **TOLERANCE)
    if index == 0:
      continue
    # The last seed's evaluation against the one-seed evaluation.
    reference = evaluate_lib.evaluate(
        config.evaluation, section, run.mesh, slot_model=slot_model,
        slot_params=slot_params, slot_steps={'savi': 4},
        dynamics={'slotformer': dynamics_lib.Loaded(
            'slotformer', dynamics_lib.build(section, 'slotformer'),
            one_seed.params, int(one_seed.step))},
        identity={}, source=SlotSource(
            slots('test'), run.videos('test'),
            evaluate_lib.video_fields(config.evaluation)),
        videos=run.videos('test'), num_true=evaluate_lib.num_true_ids(
            config.data.max_instances),
        compute_dtype=config.compute_dtype, output_dir=None)
    with open(os.path.join(workdir, f'seed_{seed}', 'eval',
                           'metrics.json')) as f:
      evaluated = json.load(f)
    for method, per_metric in reference['rollout'].items():
      for metric, value in per_metric.items():
        np.testing.assert_allclose(
            evaluated['rollout'][method][metric]['per_step'],
            value['per_step'], rtol=1e-4, atol=1e-5,
            err_msg=f'{method} {metric}')
    for key, value in reference['savi'].items():
      np.testing.assert_allclose(evaluated['savi'][key], value, rtol=1e-5,
                                 err_msg=key)


def test_a_rerun_resumes_where_the_seeds_stopped(seeded, tmp_path):
  """A run killed in the extraction of seed 1 and in SlotFormer resumes
  there (seed 0's slots are not recomputed) and ends as the whole run did
  (evaluation, which always reruns, is left out: the same code)."""
  config, workdir, _ = seeded
  copy = str(tmp_path / 'copy')
  shutil.copytree(workdir, copy)
  seed0_test = os.path.join(Paths.of(copy).for_seed(0).slots('test'),
                            'slots.f32')
  before = os.path.getmtime(seed0_test)
  # As a kill leaves them: seed 1's test slots incomplete, SlotFormer's
  # last checkpoint not written.
  seed1 = Paths.of(copy).for_seed(1).slots('test')
  meta = read_meta(seed1)
  with open(os.path.join(seed1, 'meta.json'), 'w') as f:
    json.dump(dict(meta, complete=False), f)
  checkpoints = os.path.join(copy, 'slotformer', 'checkpoints')
  steps = sorted(int(s) for s in os.listdir(checkpoints) if s.isdigit())
  assert steps[-1] == config.slotformer.num_train_steps and len(steps) > 1
  shutil.rmtree(os.path.join(checkpoints, str(steps[-1])))
  savi_checkpoints = sorted(os.listdir(os.path.join(copy, 'savi',
                                                    'checkpoints')))
  run_stages(config, copy, _mesh(2), STAGES[:-1])
  assert sorted(os.listdir(os.path.join(copy, 'savi', 'checkpoints'))) == (
      savi_checkpoints)
  assert os.path.getmtime(seed0_test) == before
  assert read_meta(seed1)['complete']
  _assert_same_slotformer(config, copy, workdir)


def test_a_read_only_stage1_of_several_seeds(seeded, tmp_path):
  """stage1_workdir with seeds (0, 1): stage 1 and its slots are read from
  the other workdir, seed s's SlotFormer trains on its seed s's slots (the
  same stacked state as that run's own SlotFormer); a stage 1 of other
  seeds is refused in one line before any work."""
  config, workdir, _ = seeded
  ablation = config.copy_and_resolve_references()
  ablation.stage1_workdir = workdir
  other = str(tmp_path / 'ablation')
  run_stages(ablation, other, _mesh(2), STAGES[:3])
  assert not os.path.exists(os.path.join(other, 'savi'))
  assert not os.path.exists(os.path.join(other, 'seed_0', 'slots'))
  _assert_same_slotformer(config, other, workdir)
  ablation.seeds = (0, 2)
  run = Run.create(ablation, str(tmp_path / 'refused'), _mesh(2))
  with pytest.raises(UserError, match='seeds') as raised:
    chain.check_identities(run.slot_model, run.paths, run.chains()[0].stacked)
  assert '\n' not in str(raised.value)
  assert not os.path.exists(str(tmp_path / 'refused'))


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
    assert identity['slotformer']['seed'] == seed
  assert not os.path.exists(os.path.join(workdir, 'render'))
  assert not os.path.exists(os.path.join(workdir, 'explore'))


@dataclasses.dataclass
class _Model:
  diverged_at: int = 0


def test_a_diverged_seed_is_left_out_and_named():
  stage1 = dataclasses.make_dataclass('S', ['diverged_at'])
  trained = video_prediction.Evaluated(
      stage1=stage1({}), dynamics={'slotformer': _Model(117)}, identity={})
  assert video_prediction.diverged(trained) == (
      'slotformer diverged in update 117')
  trained = video_prediction.Evaluated(
      stage1=stage1({'savi': 3}), dynamics={'slotformer': _Model()},
      identity={})
  assert video_prediction.diverged(trained) == 'savi diverged in update 3'

  def results(psnr, fg_miou):
    return {'slot_model': 'savi',
            'savi': {'psnr': psnr, 'fg_miou_per_frame': fg_miou,
                     'num_videos': 4},
            'rollout': {'slotformer': {'psnr': {
                'mean': psnr, 'per_step': [psnr, None]}}},
            'protocol': {'rollout_steps': 2, 'burn_in': 2, 'num_videos': 4,
                         'split': 'test'},
            'checkpoints': {}, 'identity': {}}

  summary = seeds_lib.summarise(
      {0: results(20.0, 0.5), 2: results(22.0, None)},
      {1: 'slotformer diverged in update 117'}, (0, 1, 2))
  assert summary['evaluated'] == [0, 2]
  assert summary['excluded'] == {'1': 'slotformer diverged in update 117'}
  psnr = summary['rollout']['slotformer']['psnr']
  assert psnr['per_seed'] == {'0': 20.0, '2': 22.0}
  assert (psnr['mean'], psnr['std'], psnr['num_seeds']) == (21.0, 1.0, 2)
  assert psnr['per_step'] == [21.0, None]
  # A missing value is shown and left out of the mean, never a NaN in it.
  miou = summary['savi']['fg_miou_per_frame']
  assert miou == {'mean': 0.5, 'std': 0.0, 'num_seeds': 1,
                  'per_seed': {'0': 0.5, '2': None}}
  assert summary['savi']['num_videos'] == 4
  table = seeds_lib.format_table(summary, 'SAVi')
  assert '21.0000 +- 1.0000' in table
  assert 'seed 1: slotformer diverged in update 117' in table
  nothing = seeds_lib.summarise({}, {0: 'savi diverged in update 2'}, (0,))
  assert 'No seed evaluated' in seeds_lib.format_table(nothing, 'SAVi')


def test_nested_task_metrics_fold_into_mean_std_and_each_seed():
  # Aloe's metrics per question type (stages/vqa.py evaluate_vqa).
  folded = seeds_lib.fold({
      0: {'descriptive': {'accuracy': 0.5}, 'per_option': 0.25,
          'left_out': {'questions': 3, 'videos_not_converted': ['v1']}},
      1: {'descriptive': {'accuracy': 0.7}, 'per_option': float('nan')},
      2: {'descriptive': {'accuracy': 0.9}, 'per_option': 0.75}})
  accuracy = folded['descriptive']['accuracy']
  assert accuracy['mean'] == pytest.approx(0.7)
  assert accuracy['std'] == pytest.approx(np.std([0.5, 0.7, 0.9]))
  assert accuracy['per_seed'] == {'0': 0.5, '1': 0.7, '2': 0.9}
  # Not finite or missing: shown as null, left out of the mean.
  assert folded['per_option']['per_seed']['1'] is None
  assert folded['per_option']['num_seeds'] == 2
  assert folded['per_option']['mean'] == pytest.approx(0.5)
  assert folded['left_out'] == {'questions': {
      'mean': 3.0, 'std': 0.0, 'num_seeds': 1,
      'per_seed': {'0': 3.0, '1': None, '2': None}}}  # the list left out


def test_what_takes_several_seeds_is_said_in_one_line():
  config = micro_config('savi', '/nonexistent')
  config.seeds = SEEDS
  assert task_lib.seeds_problems(config, ['prepare_data', *STAGES,
                                        'render', 'explore']) == []
  problems = task_lib.seeds_problems(config, ['train_readout'])
  assert len(problems) == 1 and problems[0].startswith(
      'seeds=(0, 1) trains several seeds in train_savi, train_dvae, '
      'extract_slots, train_slotformer, train_slot_lstm, evaluate, render, '
      "explore only for now (slot_model='savi'; docs/seeds.md); "
      'train_readout does not')
  config.stage1_workdir = '/elsewhere'  # a read-only stage 1 too
  assert task_lib.seeds_problems(config, ['extract_slots']) == []
  # The STEVE chain takes them too (test_steve_seeds_pipeline.py).
  steve = micro_config('steve', '/nonexistent')
  steve.seeds = SEEDS
  assert task_lib.seeds_problems(steve, ['train_dvae', 'tokenize_frames',
                                       'train_steve', 'extract_slots']) == []
