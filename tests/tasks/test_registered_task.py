"""A fourth downstream task from this one file, without editing the package.

'end_position': where do the objects end up? From SlotFormer's rollout of
the slots to a video's last frame, a linear readout of the mean slot
predicts the objects' mean final position (the embedded OBJ3D-like videos
store each object's 3-D position per frame). Its two stages train the head
through the shared trainer (checkpoints, resume, the run's mesh) and score
it on the test videos. The `Task` declares its stages, its seeded stages
(none), its section and the splits it reads; registered at import, it runs
after the data stage, SAVi, extraction and SlotFormer as any task does.
"""

from __future__ import annotations

import functools
import itertools
import json
import os
import pathlib

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import pytest

from pipeline_helpers import check
from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from slotformer_jax import inference
from slotformer_jax import stages
from slotformer_jax.errors import UserError
from slotformer_jax.runtime import checkpoint
from slotformer_jax.runtime import sharding
from slotformer_jax.stages import task as task_lib
from slotformer_jax.train import trainer

NAME = 'end_position'


def defaults() -> ml_collections.ConfigDict:
  """`config.position`: the head's training and the splits it reads."""
  return ml_collections.ConfigDict(dict(
      train_split='train', test_split='test', batch_size=4,
      num_train_steps=30, learning_rate=1e-2, log_every=10,
      checkpoint_every=30, stop_check_every=1))


def _features_and_targets(run, split: str) -> tuple[np.ndarray, np.ndarray]:
  """float32 [N, D] mean slot of SlotFormer's rollout at each video's last
  frame, and [N, 3] the visible objects' mean position there."""
  slots = run.slots(split)
  videos = run.videos(split)
  trained = run.dynamics('slotformer')
  burn_in = run.dynamics_section('slotformer').burn_in
  # Jitted once: outside jit, flax's time loop is traced and compiled anew
  # at every call.
  rollout_slots = jax.jit(
      functools.partial(inference.rollout_slots, model=trained.module),
      static_argnames='num_steps')
  features, targets = [], []
  for i in range(len(slots)):
    observed = np.asarray(slots[i]['slots'])[None, :burn_in]
    steps = len(slots[i]['slots']) - burn_in
    rollout = rollout_slots(trained.params, jnp.asarray(observed),
                            num_steps=steps)
    features.append(np.asarray(rollout)[0, -1].mean(axis=0))
    video = videos[i]
    visible = np.asarray(video['visible'][-1], bool)
    targets.append(np.asarray(video['positions'][-1])[visible].mean(axis=0))
  return (np.stack(features).astype(np.float32),
          np.stack(targets).astype(np.float32))


def _mse(params, features, targets) -> float:
  predicted = features @ params['w'] + params['b']
  return float(np.mean(np.square(predicted - targets)))


def _directory(run) -> str:
  return os.path.join(run.paths.root, NAME)


def train_position_readout(run) -> None:
  """Fits the head on the train split's rollouts (the shared trainer)."""
  section = run.config.position
  features, targets = _features_and_targets(run, section.train_split)

  def loss_fn(params, batch, frozen_params, rng):
    del frozen_params, rng
    predicted = batch['features'] @ params['w'] + params['b']
    loss = jnp.mean(jnp.square(predicted - batch['targets']))
    return loss, {}

  def batches(start_step):
    order = np.random.default_rng(run.seed).permutation(len(features))
    size = section.batch_size
    for step in itertools.count(start_step):
      start = (step * size) % (len(order) - size + 1)
      rows = order[start:start + size]
      yield {'features': features[rows], 'targets': targets[rows]}

  trainer.fit(trainer.Stage(
      name=NAME, directory=_directory(run), config=section,
      loss_fn=loss_fn,
      init_params=lambda rng: {'w': jnp.zeros((features.shape[1], 3)),
                               'b': jnp.asarray(targets.mean(axis=0))},
      batches=batches,
      optimizer=(optax.adam(section.learning_rate),
                 optax.constant_schedule(section.learning_rate))),
      mesh=sharding.one_device_per_process(), seed=run.seed)


def evaluate_position_readout(run) -> dict[str, float]:
  """The head's MSE on the test split against predicting the train mean."""
  section = run.config.position
  shapes = {'w': jax.ShapeDtypeStruct((run.slot_model.slot_shape[-1], 3),
                                     jnp.float32),
            'b': jax.ShapeDtypeStruct((3,), jnp.float32)}
  restored, _ = checkpoint.restore_params(
      _directory(run), shapes, sharding.replicated_sharding(run.mesh),
      what=NAME, train_command='--mode=train_position_readout')
  params = jax.tree.map(np.asarray, restored)
  features, targets = _features_and_targets(run, section.test_split)
  _, train_targets = _features_and_targets(run, section.train_split)
  results = {'mse': _mse(params, features, targets),
             'train_mean_mse': float(np.mean(np.square(
                 train_targets.mean(axis=0) - targets)))}
  with open(os.path.join(_directory(run), 'results.json'), 'w') as f:
    json.dump(results, f)
  return results


TASK = task_lib.register(task_lib.Task(
    name=NAME, config=__file__,
    stages={'train_position_readout': train_position_readout,
            'evaluate_position_readout': evaluate_position_readout},
    section='position', defaults=defaults,
    reads=lambda config: (('position.train_split',
                           config.position.train_split),
                          ('position.test_split',
                           config.position.test_split))))


def position_config(data_dir) -> ml_collections.ConfigDict:
  config = micro_config('savi', str(data_dir))
  config.task = NAME
  config.slot_lstm.train = False
  config.position = defaults()
  return config


def test_the_package_does_not_know_it():
  package = pathlib.Path(stages.__file__).parent.parent
  assert not any(NAME in path.read_text() for path in package.rglob('*.py'))
  assert task_lib.get(NAME) is TASK
  assert task_lib.register(TASK) is TASK  # a re-import


def test_its_mistakes_are_one_line_before_any_work(tmp_path):
  config = position_config(tmp_path / 'data')
  config.position.test_split = 'tset'
  with pytest.raises(UserError, match="position.test_split='tset' is not"):
    check(config, ['train_position_readout', 'evaluate_position_readout'])
  del config.position
  with pytest.raises(UserError, match="task='end_position' reads "
                     'config.position'):
    check(config, ['train_position_readout'])
  config = position_config(tmp_path / 'data')
  config.task = 'end_positon'
  with pytest.raises(UserError, match="unknown task 'end_positon'.*"
                     "'end_position'"):
    check(config, ['train_savi'])
  assert not (tmp_path / 'data').exists()


def test_a_task_from_one_test_file_runs_its_stages(tmp_path):
  config = position_config(tmp_path / 'data')
  workdir = tmp_path / 'run'
  mesh = sharding.make_mesh()
  run = stages.Run.create(config, str(workdir), mesh)
  assert stages.selected_stages(run, 'all')[-2:] == (
      'train_position_readout', 'evaluate_position_readout')
  results = run_stages(config, workdir, mesh)
  scored = results['evaluate_position_readout']
  assert np.isfinite(scored['mse']) and scored['mse'] >= 0
  log = (workdir / NAME / 'train_log.jsonl').read_text().splitlines()
  assert json.loads(log[-1])['step'] == config.position.num_train_steps
  # Trained, it resumes as every stage: already trained, nothing redone.
  again = run_stages(config, workdir, mesh, ['train_position_readout',
                                             'evaluate_position_readout'])
  assert again['evaluate_position_readout'] == scored
  # --mode=<its stage> on another config names where it belongs.
  other = stages.Run.create(micro_config('savi', str(tmp_path / 'data')),
                            str(tmp_path / 'other'), mesh)
  with pytest.raises(UserError, match='train_position_readout belongs to '
                     f'{__file__}'):
    stages.selected_stages(other, 'train_position_readout')
