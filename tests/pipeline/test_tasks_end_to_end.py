"""Both downstream tasks through every stage on micro configs (slow), and
the contact task with several seeds."""

from __future__ import annotations

import json
import os

from flax import serialization
import jax
import numpy as np
import pytest

from configs import synthetic_contact
from configs import synthetic_phyre
from slotformer_jax.stages import task as task_lib
from slotformer_jax.files import read_json
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.stages import contact as contact_stage
from slotformer_jax.stages.planning import embedded as planning_stage
from slotformer_jax.stages import readout_fit
from slotformer_jax.tasks import contact
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.tasks import planning as planning_lib
from slotformer_jax.tasks import readout as readout_lib
from pipeline_helpers import load_config
from pipeline_helpers import run_stage


def _micro_models(config):
  config.savi.encoder.features = (8, 8)
  config.savi.encoder.strides = (2, 1)
  config.savi.decoder.features = (8, 8)
  config.savi.num_train_steps = 2
  config.savi.log_every = config.savi.checkpoint_every = 2
  config.slotformer.num_train_steps = 2
  config.slotformer.log_every = config.slotformer.checkpoint_every = 2
  config.readout.epochs = 1


def _run(config, workdir, stage_names):
  mesh = sharding.make_mesh()
  run_stage(config, workdir, mesh, 'train_savi')
  run_stage(config, workdir, mesh, 'extract_slots')
  run_stage(config, workdir, mesh, 'train_slotformer')
  return [run_stage(config, workdir, mesh, name) for name in stage_names]


@pytest.mark.slow
def test_contact_task_end_to_end(tmp_path):
  config = synthetic_contact.get_config('tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.resolution = (16, 16)
  config.data.supersample = 1
  _micro_models(config)
  workdir = str(tmp_path / 'run')
  _, results = _run(config, workdir, ('train_readout', 'evaluate_readout'))
  for condition in config.readout.conditions:
    assert len(results[condition]['test_accuracy']) == len(config.readout.seeds)
    assert 0.0 <= results[condition]['mean'] <= 1.0
  assert results['chance']['mean'] == 0.5  # balanced labels
  with open(os.path.join(workdir, 'readout', 'results.json')) as f:
    assert json.load(f)['num_test_videos'] == config.data.num_readout_test


@pytest.mark.slow
def test_planning_task_end_to_end(tmp_path):
  config = synthetic_phyre.get_config('tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.num_candidates = 12
  _micro_models(config)
  workdir = str(tmp_path / 'run')
  _, summary = _run(config, workdir, ('train_readout', 'plan'))
  assert summary['oracle']['mean'] == pytest.approx(
      summary['solvable_test_tasks'] / summary['num_test_tasks'])
  for name in ('random', 'first_frame', 'rollout'):
    assert 0.0 <= summary[name]['mean'] <= summary['oracle']['mean'] + 1e-9


def _contact_micro_config(data_dir):
  config = synthetic_contact.get_config('tiny')
  config.data.data_dir = str(data_dir)
  config.data.resolution = (16, 16)
  config.data.supersample = 1
  _micro_models(config)
  return config


def test_every_task_takes_several_seeds():
  contact_stages = ['prepare_data', 'train_savi', 'extract_slots',
                    'train_slotformer', 'train_readout', 'evaluate_readout']
  config = _contact_micro_config('/nonexistent')
  config.seeds = (0, 1)
  assert task_lib.seeds_problems(config, contact_stages) == []
  planning = synthetic_phyre.get_config('tiny')
  planning.seeds = (0, 1)
  assert task_lib.seeds_problems(planning, ['train_savi', 'train_readout',
                                          'plan']) == []
  # The real PHYRE's rendered rollouts (stages/planning/rendered.py) too.
  planning.data.name = 'phyre'
  assert task_lib.seeds_problems(planning, ['train_savi', 'train_readout',
                                          'plan']) == []
  vqa = load_config('synthetic_vqa', 'tiny')
  vqa.seeds = (0, 1)
  assert task_lib.seeds_problems(vqa, ['train_savi', 'vqa_slots', 'train_vqa',
                                     'evaluate_vqa']) == []


@pytest.mark.slow
def test_contact_task_with_seeds_fits_one_readout_per_chain(tmp_path):
  """config.seeds=(0, 1): readout s is fitted with seed s on chain s's
  slots and SlotFormer; results.json has one accuracy per chain."""
  config = _contact_micro_config(tmp_path / 'data')
  config.seeds = (0, 1)
  workdir = str(tmp_path / 'run')
  _, results = _run(config, workdir, ('train_readout', 'evaluate_readout'))
  assert results['seeds'] == [0, 1] and results['chains'] == 'per_seed'
  for condition in config.readout.conditions:
    assert len(results[condition]['test_accuracy']) == 2
  with open(os.path.join(workdir, 'readout', 'results.json')) as f:
    assert json.load(f)['seeds'] == [0, 1]
  run = Run.create(config, workdir, sharding.make_mesh())
  readout = config.readout
  train_split, val_split, _ = contact.readout_splits(readout)
  model = contact.build_readout(readout, run.slot_model.slot_shape[1])
  fitted = {}
  for index, seed in enumerate(config.seeds):
    view = run.for_seed(index)
    directory = view.paths.readout(contact.ROLLOUT, seed)
    assert directory.startswith(os.path.join(workdir, f'seed_{seed}'))
    with open(os.path.join(directory, 'params.msgpack'), 'rb') as f:
      fitted[seed] = serialization.msgpack_restore(f.read())
    # The one-seed fit of seed s on chain s's own features.
    train, train_labels = contact_stage._features_by_condition(  # pylint: disable=protected-access
        view, train_split, (contact.ROLLOUT,))
    val, val_labels = contact_stage._features_by_condition(  # pylint: disable=protected-access
        view, val_split, (contact.ROLLOUT,))

    def val_accuracy(params, val=val, val_labels=val_labels):
      probs = readout_lib.predict(model, params, val[contact.ROLLOUT])
      return readout_lib.best_threshold(probs, val_labels)[1]

    params, _ = readout_fit.fit_readout(
        str(tmp_path / f'again_{seed}'), 'readout', model,
        (train[contact.ROLLOUT], train_labels), val_accuracy,
        contact.fit_config(readout), seed)
    jax.tree.map(np.testing.assert_array_equal, fitted[seed],
                 jax.device_get(params))
    assert read_json(os.path.join(directory, 'selection.json'))[
        'val_accuracy'] is not None
  # Two chains, two seeds: the readouts differ.
  assert not all(np.array_equal(a, b) for a, b in zip(
      jax.tree.leaves(fitted[0]), jax.tree.leaves(fitted[1])))


@pytest.mark.slow
def test_planning_with_seeds_fits_one_classifier_per_chain(tmp_path):
  """config.seeds=(0, 1): classifier s is fitted with seed s on chain s's
  candidates (its slot model and SlotFormer); one AUCCESS per chain."""
  config = synthetic_phyre.get_config('tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.num_candidates = 12
  _micro_models(config)
  config.seeds = (0, 1)
  workdir = str(tmp_path / 'run')
  _, summary = _run(config, workdir, ('train_readout', 'plan'))
  assert summary['seeds'] == [0, 1] and summary['chains'] == 'per_seed'
  for name in ('random', *config.readout.conditions):
    assert len(summary[name]['auccess']) == 2
  run = Run.create(config, workdir, sharding.make_mesh())
  fitted = {}
  for index, seed in enumerate(config.seeds):
    view = run.for_seed(index)
    by_split, outcomes, generation = planning_stage.task_candidates(
        view, ('train', 'dev'))
    train = planning_stage.training_set(
        by_split['train'], outcomes['train'],
        config.readout.negatives_per_task, seed)
    condition = config.readout.conditions[-1]
    model, fitted[seed] = planning_stage.load_classifier(view, condition,
                                                         seed)

    def dev_auccess(params, model=model, by_split=by_split,
                    outcomes=outcomes, generation=generation):
      return planning_lib.plan_auccess(phyre_planning.candidate_scores(
          model, params, by_split['dev'], generation.num_candidates),
                                       outcomes['dev'])

    params, _ = readout_fit.fit_readout(
        str(tmp_path / f'again_{seed}'), 'classifier', model, train,
        dev_auccess, planning_stage.fit_config_of(config.readout), seed)
    jax.tree.map(np.testing.assert_array_equal, fitted[seed],
                 jax.device_get(params))
  assert not all(np.array_equal(a, b) for a, b in zip(
      jax.tree.leaves(fitted[0]), jax.tree.leaves(fitted[1])))
