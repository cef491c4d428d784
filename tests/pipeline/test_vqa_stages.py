"""VQA stages wired end to end on stand-in slots (no SAVi / SlotFormer)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from pipeline_helpers import prepare_data
from slotformer_jax.data.sources import resolve_data_dir
from slotformer_jax.datasets import clevrer_like
from slotformer_jax.runtime import sharding
from slotformer_jax.run import Run
from slotformer_jax.workdir.paths import Paths
from pipeline_helpers import accept
from pipeline_helpers import run_stage


@pytest.mark.slow
def test_train_and_evaluate_vqa_on_random_slots(tmp_path, monkeypatch):
  import importlib.util  # pylint: disable=g-import-not-at-top
  spec = importlib.util.spec_from_file_location(
      'synthetic_vqa', os.path.join(os.path.dirname(__file__), '..', '..',
                                    'configs', 'synthetic_vqa.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  config = module.get_config('tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.num_workers = 1
  workdir = str(tmp_path / 'run')
  prepare_data(config)
  root = clevrer_like.complete_dataset_dir(
      config.data, resolve_data_dir(config.data.data_dir))
  assert (root / 'vocab.json').is_file()
  rng = np.random.default_rng(0)
  os.makedirs(os.path.join(workdir, 'vqa', 'slots'))
  for split in ('train', 'val', 'test'):
    slots = rng.normal(size=(config.data[f'num_{split}'],
                             config.vqa.video_length
                             + config.vqa.rollout_frames,
                             config.savi.num_slots, config.savi.slot_size))
    np.save(os.path.join(workdir, 'vqa', 'slots', f'{split}.npy'),
            slots.astype(np.float32))
  mesh = sharding.make_mesh()
  for inputs in ('rollout', 'blind'):
    config.vqa.inputs = inputs
    run_stage(config, workdir, mesh, 'train_vqa')
    results = run_stage(config, workdir, mesh, 'evaluate_vqa')
    assert 0.0 <= results['descriptive']['accuracy'] <= 1.0
    with open(os.path.join(Paths.of(workdir).aloe(inputs, config.vqa.seed),
                           'metrics_test.json')) as f:
      assert json.load(f) == results
  assert os.path.exists(os.path.join(workdir, 'vqa', 'answer_prior_test.json'))


def test_vqa_inputs_and_seed_are_variants_of_one_workdir(tmp_path):
  # The comparison trains every Aloe input and seed in one workdir (each in
  # vqa/<inputs>_s<seed>/): picking them is not a change of settings; an
  # Aloe size is.
  from slotformer_jax.errors import UserError  # pylint: disable=g-import-not-at-top
  config = _synthetic_vqa_config()
  workdir = str(tmp_path)
  assert accept(config, workdir) == []
  config.vqa.inputs, config.vqa.seed, config.vqa.eval_split = (
      'blind', 2, 'val')
  assert accept(config, workdir) == []
  # What evaluation accepts as input (the share of questions whose video
  # was not converted) is not a setting either.
  config.vqa.max_missing_video_fraction = 1.0
  assert accept(config, workdir) == []
  config.vqa.num_layers += 1
  with pytest.raises(UserError):
    accept(config, workdir)


def _synthetic_vqa_config(variant: str = ''):
  import importlib.util  # pylint: disable=g-import-not-at-top
  spec = importlib.util.spec_from_file_location(
      'synthetic_vqa', os.path.join(os.path.dirname(__file__), '..', '..',
                                    'configs', 'synthetic_vqa.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant)


def test_long_savi_variant_is_the_default():
  # Issue 12, round 2's variant (SAVi 4500 steps) became the default in
  # round 5; its name still runs the commands written for it.
  base = _synthetic_vqa_config().to_dict()
  assert base['savi']['num_train_steps'] == 4500
  assert _synthetic_vqa_config('long_savi').to_dict() == base


def test_big_variant_changes_only_data_size_and_schedules():
  # Round 3 of issue 12: more training videos (the val / test videos are the
  # same: a video is a function of seed, split and index), longer schedules,
  # Aloe on predictive + descriptive questions; nothing else.
  flat = lambda c: {f'{k}.{j}': w for k, v in c.to_dict().items()
                    for j, w in (v.items() if isinstance(v, dict)
                                 else [('', v)])}
  base, big = flat(_synthetic_vqa_config('long_savi')), flat(
      _synthetic_vqa_config('big'))
  changed = {k: (base[k], big[k]) for k in base if base[k] != big[k]}
  assert set(base) == set(big)
  assert changed == {
      'data.num_train': (600, 3000),
      'slotformer.num_train_steps': (1000, 4000),
      'vqa.num_train_steps': (1500, 12000),
      'vqa.choice_type_weights': (
          {'counterfactual': 1.0, 'explanatory': 1.0, 'predictive': 1.0},
          {'counterfactual': 0.0, 'explanatory': 0.0, 'predictive': 1.0}),
      'vqa.log_every': (100, 500),
      'vqa.checkpoint_every': (750, 3000),
  }


def test_future_inputs_read_the_extracted_slots_of_the_real_future(tmp_path):
  # vqa.inputs='future' (the ground-truth-future ceiling) reads SAVi's slots
  # of the frames after the video from the extraction, not the rollout file.
  from slotformer_jax.stages import vqa as vqa_stages  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data.slots import SlotWriter  # pylint: disable=g-import-not-at-top
  config = _synthetic_vqa_config()
  workdir = str(tmp_path)
  writer = SlotWriter(Paths.of(workdir).slots('val'), 2, 3, 2, 1)
  for v, frames in ((1, 20), (0, 20)):
    # value = 100 * video + frame, so the frames can be read back.
    writer.add(v, (100.0 * v + np.arange(frames, dtype=np.float32))[
        :, None, None] * np.ones((1, 3, 2), np.float32))
  writer.close()
  run = Run.create(config, workdir)
  slots = vqa_stages._true_future_slots(run, 'val', 18)  # pylint: disable=protected-access
  assert slots.shape == (2, 18, 3, 2)
  assert slots[1, :, 0, 0].tolist() == [100.0 + t for t in range(18)]
  assert slots[0, 17, 2, 1] == 17.0
  with pytest.raises(ValueError, match='whole simulated clip'):
    vqa_stages._true_future_slots(run, 'val', 21)  # pylint: disable=protected-access


def test_deflect_variant_changes_only_the_predictive_design():
  # Round 4 of issue 12: `:big` on the 'deflected' scene design
  # (clevrer_like.PREDICTIVE_DESIGNS); everything else as `:big`.
  flat = lambda c: {f'{k}.{j}': w for k, v in c.to_dict().items()
                    for j, w in (v.items() if isinstance(v, dict)
                                 else [('', v)])}
  big, deflect = flat(_synthetic_vqa_config('big')), flat(
      _synthetic_vqa_config('deflect'))
  assert deflect.pop('data.predictive_design') == 'deflected'
  assert 'data.predictive_design' not in big  # 'direct', the default
  assert deflect == big
  assert clevrer_like.config_from_data_config(
      _synthetic_vqa_config('deflect').data).predictive_design == 'deflected'


def test_missing_vqa_inputs_are_one_line_errors(tmp_path):
  from slotformer_jax.data import vqa_questions  # pylint: disable=g-import-not-at-top
  from slotformer_jax.errors import UserError  # pylint: disable=g-import-not-at-top
  from slotformer_jax.stages import vqa as vqa_stages  # pylint: disable=g-import-not-at-top
  from pipeline_helpers import load_config  # pylint: disable=g-import-not-at-top
  config = load_config('clevrer_vqa')
  config.vqa.questions_root = str(tmp_path / 'clevrer')
  with pytest.raises(UserError, match='questions/train.json not found'):
    vqa_questions.encoded_questions(config, 'train', None)
  with pytest.raises(UserError, match='--mode=vqa_slots'):
    vqa_stages.question_batches(Run.create(config, str(tmp_path / 'run')),
                                'train', vqa_questions.join_videos([], []))


@pytest.mark.slow
def test_aloe_of_seed_k_is_the_one_seed_aloe_on_chain_k(tmp_path):
  """config.seeds=(0, 1), per-seed question order: chain k's Aloe (trained
  with the other in one program, on chain k's slots) equals the one-seed
  run with seed k on those slots; the summary folds both evaluations."""
  import jax  # pylint: disable=g-import-not-at-top
  from slotformer_jax.stages import vqa as vqa_stages  # pylint: disable=g-import-not-at-top
  config = _synthetic_vqa_config('tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.num_workers = 1
  config.vqa.num_train_steps = 3
  config.vqa.log_every = config.vqa.checkpoint_every = 3
  prepare_data(config)
  seeds = (0, 1)
  rng = np.random.default_rng(0)
  chains = {}
  for seed in seeds:  # stand-ins for each chain's SAVi + SlotFormer slots
    chains[seed] = {split: rng.normal(size=(
        config.data[f'num_{split}'],
        config.vqa.video_length + config.vqa.rollout_frames,
        config.savi.num_slots, config.savi.slot_size)).astype(np.float32)
                    for split in ('train', 'val', 'test')}

  def write_slots(directory, seed):
    os.makedirs(directory, exist_ok=True)
    for split, slots in chains[seed].items():
      np.save(os.path.join(directory, f'{split}.npy'), slots)

  mesh = sharding.make_mesh()
  several = config.copy_and_resolve_references()
  several.seeds, several.seed_data_order = seeds, 'per_seed'
  workdir = str(tmp_path / 'seeds')
  for seed in seeds:
    write_slots(Paths.of(workdir).for_seed(seed).vqa_slots, seed)
  run_stage(several, workdir, mesh, 'train_vqa')
  summary = run_stage(several, workdir, mesh, 'evaluate_vqa')
  run = Run.create(several, workdir, mesh)
  per_seed = {}
  for index, seed in enumerate(seeds):
    one = config.copy_and_resolve_references()
    one.seed = seed
    own = str(tmp_path / f'one_{seed}')
    write_slots(Paths.of(own).vqa_slots, seed)
    run_stage(one, own, mesh, 'train_vqa')
    per_seed[seed] = run_stage(one, own, mesh, 'evaluate_vqa')
    expected = vqa_stages.load_aloe(Run.create(one, own, mesh))
    got = vqa_stages.load_aloe(run.for_seed(index))
    assert got.step == expected.step == 3
    # Attention key biases get no gradient (softmax ignores a shift shared
    # by every key) but rounding noise, which Adam scales to lr-sized
    # steps: they differ between any two programs, and change nothing.
    for path, value in jax.tree_util.tree_leaves_with_path(
        jax.device_get(got.params)):
      name = jax.tree_util.keystr(path)
      if "['key']['bias']" in name:
        continue
      reference = expected.params
      for key in path:
        reference = reference[key.key]
      np.testing.assert_allclose(value, jax.device_get(reference),
                                 atol=2e-5, rtol=2e-5, err_msg=name)
    with open(os.path.join(Paths.of(workdir).for_seed(seed).aloe_results(
        config.vqa.inputs, config.vqa.seed), 'metrics_test.json')) as f:
      mine = json.load(f)['descriptive']['accuracy']
    assert mine == pytest.approx(per_seed[seed]['descriptive']['accuracy'],
                                 abs=1e-6)
  folded = summary['metrics']['descriptive']['accuracy']
  assert summary['seeds'] == list(seeds) and folded['num_seeds'] == 2
  assert folded['mean'] == pytest.approx(np.mean(
      [per_seed[s]['descriptive']['accuracy'] for s in seeds]), abs=1e-6)
  with open(os.path.join(Paths.of(workdir).aloe(config.vqa.inputs,
                                                config.vqa.seed),
                         'metrics_test.json')) as f:
    assert json.load(f) == summary
