"""Planning on the real, pre-rendered PHYRE layout (tasks/phyre_rendered.py).

A tiny source in the layout tools/render_phyre.py writes (meta.json,
rollouts.jsonl, vertically stacked PNG frames), converted by the real
converter; the slow test runs every stage of configs/phyre.py:planning on it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
import numpy as np
import pytest

import dataset_fixtures as fx
from configs import phyre as phyre_config
from slotformer_jax.datasets import phyre
from slotformer_jax.data import prepare
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.tasks import phyre_rendered
from slotformer_jax.tasks import planning
from slotformer_jax.runtime import sharding
from slotformer_jax.stages.planning import rendered as planning_rendered
from pipeline_helpers import run_stage
from slotformer_jax.run import Run

SCENE = 16
FRAMES = 4
# split -> task -> outcomes of its rendered rollouts (the layout never holds
# invalid actions). Two templates, so the dev set is drawn per template.
ROLLOUTS = {
    'train': {f'0000{t}:00{v}': [1, 0, 0, 1] for t in (0, 1) for v in range(4)},
    'val': {'00000:010': [0, 1, 0, 0], '00001:011': [0, 0, 1, 0]},
}


def _frames(task_number: int, action: tuple[float, float, float]
            ) -> np.ndarray:
  """A black scene with a green block per task and the red ball falling."""
  frames = np.zeros((FRAMES, SCENE, SCENE, 3), np.uint8)
  frames[:, -3:, 2 + task_number % 8] = (0, 200, 0)
  x = int(action[0] * (SCENE - 2))
  for t in range(FRAMES):
    frames[t, t:t + 2, x:x + 2] = (230, 40, 40)
  return frames


def write_layout(root: Path) -> Path:
  fx.write_json(root / phyre.META_FILE, {
      'format': phyre.FORMAT, 'format_version': phyre.FORMAT_VERSION,
      'tier': 'ball', 'eval_setup': 'ball_within_template', 'fold': 0,
      'fps': 1, 'max_frames': FRAMES, 'background': 'black',
      'frame_size': [SCENE, SCENE], 'splits': ['train', 'val']})
  rollout_id = 0
  for split, by_task in ROLLOUTS.items():
    lines = []
    for task_number, (task, outcomes) in enumerate(by_task.items()):
      for k, success in enumerate(outcomes):
        key = f'{rollout_id:06d}'
        action = [0.1 + 0.2 * k, 0.5, 0.3]
        fx.write_png(root / split / 'frames' / f'{key}.png',
                     _frames(task_number, action).reshape(-1, SCENE, 3))
        lines.append(json.dumps({'id': key, 'task': task, 'action': action,
                                 'success': bool(success),
                                 'num_frames': FRAMES}))
        rollout_id += 1
    (root / split / phyre.INDEX_FILE).write_text('\n'.join(lines) + '\n')
  return root


@pytest.fixture(scope='module')
def converted(tmp_path_factory) -> Path:
  base = tmp_path_factory.mktemp('phyre_rendered')
  source = write_layout(base / 'PHYRE')
  assert prepare.main([
      '--dataset=phyre', f'--source={source}', f'--data_dir={base / "data"}',
      f'--resolution={SCENE}', f'--num_frames={FRAMES}', '--num_workers=1',
      '--no_progress']) == 0
  return base / 'data'


def micro_config(data_dir: Path):
  config = phyre_config.get_config('planning')
  config.data.data_dir = str(data_dir)
  config.data.resolution = (SCENE, SCENE)
  savi = config.savi
  savi.num_slots, savi.slot_size = 3, 8
  savi.encoder.features = (8, 8)
  savi.encoder.strides = (2, 1)
  savi.encoder.output_size = 8
  savi.encoder.padding = 'same'
  savi.slot_attention.mlp_size = 16
  savi.predictor.kind = 'transformer'
  savi.predictor.lstm_size = 0
  savi.predictor.num_heads, savi.predictor.mlp_size = 1, 16
  savi.posterior_head = 'none'
  savi.decoder.features = (8, 8)
  savi.decoder.broadcast_resolution = (4, 4)
  savi.batch_size, savi.clip_length = 4, 2
  savi.num_train_steps = savi.log_every = savi.checkpoint_every = 2
  config.extraction.batch_size = 4
  config.extraction.chunk_length = FRAMES
  dyn = config.slotformer
  dyn.embed_dim, dyn.num_layers, dyn.num_heads = 8, 1, 1
  dyn.rollout = 3
  dyn.batch_size = 4
  dyn.num_train_steps = dyn.log_every = dyn.checkpoint_every = 2
  r = config.readout
  r.embed_dim, r.num_layers, r.num_heads = 8, 1, 1
  r.seeds = (0, 1)
  r.epochs = 2
  r.batch_size = 8
  r.encode_batch_size = 8
  r.dev_share = 0.25
  return config


def test_dev_tasks_are_drawn_within_each_template():
  tasks_ = [f'{t:05d}:{v:03d}' for t in range(3) for v in range(8)]
  dev = phyre_rendered.dev_tasks(tasks_, 0.25, seed=0)
  assert len(dev) == 6
  for template in ('00000', '00001', '00002'):
    assert sum(t.startswith(template) for t in dev) == 2
  assert dev == phyre_rendered.dev_tasks(list(reversed(tasks_)), 0.25, 0)
  assert dev != phyre_rendered.dev_tasks(tasks_, 0.25, seed=1)
  assert phyre_rendered.dev_tasks(tasks_, 0.0, 0) == set()


def test_task_auccess_ranks_each_task_separately():
  # Task a (rows 0-2): its solving rollout ranks 2nd -> attempt 2; task b
  # (rows 3-4): solved at attempt 1. Scores of other tasks do not interfere.
  tasks_ = ['a', 'a', 'a', 'b', 'b']
  outcomes = np.array([0, 1, 0, 1, 0])
  scores = np.array([0.9, 0.5, 0.1, 0.2, 0.1])
  groups = phyre_rendered.group_by_task(tasks_)
  expected = planning.auccess([2, 1])
  assert phyre_rendered.task_auccess(scores, outcomes, groups) == (
      pytest.approx(expected))
  weights = planning.attempt_weights()
  assert expected == pytest.approx(
      (0.5 * weights[0] + weights[1:].sum()) / weights.sum())


def test_official_candidates_name_the_missing_package():
  config = phyre_config.get_config('planning')
  config.readout.candidates = 'phyre_cache'
  with pytest.raises(ConfigError) as error:
    phyre_rendered.check_candidates(config.readout)
  message = str(error.value)
  assert '\n' not in message and '`phyre` package' in message
  assert "readout.candidates='rendered'" in message


def test_missing_slots_name_the_stage(converted, tmp_path):
  config = micro_config(converted)
  with pytest.raises(MissingInputError, match='--mode=extract_slots'):
    planning_rendered.load_rendered(Run.create(config, str(tmp_path)), 'val')


@pytest.mark.slow
def test_planning_stages_on_the_rendered_layout(converted, tmp_path):
  config = micro_config(converted)
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  run_stage(config, workdir, mesh, 'train_savi')
  run_stage(config, workdir, mesh, 'extract_slots')
  run_stage(config, workdir, mesh, 'train_slotformer')
  run_stage(config, workdir, mesh, 'train_readout')
  selection = json.load(open(os.path.join(
      workdir, 'planning', 'rollout', 'seed_0', 'selection.json')))
  # 8 training tasks, 25% of each template's 4 -> one dev task each.
  assert len(selection['dev_tasks']) == 2
  assert {t[:5] for t in selection['dev_tasks']} == {'00000', '00001'}
  summary = run_stage(config, workdir, mesh, 'plan')
  assert summary['num_test_tasks'] == 2
  assert summary['candidates_per_task'] == [4, 4]
  assert summary['solving_share'] == 0.25
  assert summary['oracle']['mean'] == 1.0
  for name in ('random', 'first_frame', 'rollout'):
    assert len(summary[name]['auccess']) == 2
    # Each test task has 1 solving rollout in 4: attempt 1..4.
    assert planning.auccess([4, 4]) - 1e-9 <= summary[name]['mean'] <= 1.0
  text = open(os.path.join(workdir, 'planning', 'results.md')).read()
  assert 'NOT the official protocol' in text


@pytest.mark.slow
def test_rendered_planning_with_seeds_fits_one_classifier_per_chain(
    converted, tmp_path):
  """config.seeds=(0, 1): classifier s is fitted with seed s on chain s's
  rollout features (its slots and SlotFormer), its dev tasks drawn with s,
  as the one-seed run of seed s would; one AUCCESS per chain."""
  config = micro_config(converted)
  config.seeds = (0, 1)
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  for stage in ('train_savi', 'extract_slots', 'train_slotformer',
                'train_readout'):
    run_stage(config, workdir, mesh, stage)
  summary = run_stage(config, workdir, mesh, 'plan')
  assert summary['seeds'] == [0, 1] and summary['chains'] == 'per_seed'
  for name in ('random', 'first_frame', 'rollout'):
    assert len(summary[name]['auccess']) == 2
  run = Run.create(config, workdir, mesh)
  fitted = {}
  for index, seed in enumerate(config.seeds):
    view = run.for_seed(index)
    data = planning_rendered.training_set(view)
    _, params, _ = planning_rendered.fit_classifier(
        config.readout, 'rollout', data, seed,
        str(tmp_path / f'again_{seed}'))
    _, fitted[seed] = planning_rendered.load_classifier(
        view, 'rollout', seed, data.features.shape[1])
    jax.tree.map(np.testing.assert_array_equal, fitted[seed],
                 jax.device_get(params))
    assert os.path.exists(os.path.join(
        workdir, f'seed_{seed}', 'planning', 'rollout', f'seed_{seed}',
        'selection.json'))
  assert not all(np.array_equal(a, b) for a, b in zip(
      jax.tree.leaves(fitted[0]), jax.tree.leaves(fitted[1])))
