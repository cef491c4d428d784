"""The downstream-task stages' pure parts: readout inputs, task splits,
first frames, error messages."""

from __future__ import annotations

import numpy as np
import pytest

from configs import synthetic_contact
from configs import synthetic_phyre
from slotformer_jax.run import Run
from slotformer_jax.stages import contact as contact_stages
from slotformer_jax.tasks import contact
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.workdir.identity import flat_differences
from slotformer_jax.tasks import phyre_world


def test_condition_features():
  slots = np.arange(2 * 6 * 3 * 2, dtype=np.float32).reshape(2, 6, 3, 2)
  observed = contact.condition_features(slots, 'observed', 4)
  np.testing.assert_array_equal(observed, slots[:, :4])
  np.testing.assert_array_equal(
      contact.condition_features(slots, 'ground_truth', 4), slots)
  copied = contact.condition_features(slots, 'copy_last', 4)
  assert copied.shape == slots.shape
  np.testing.assert_array_equal(copied[:, 4], slots[:, 3])
  np.testing.assert_array_equal(copied[:, 5], slots[:, 3])
  calls = []

  def rollout(obs, steps):
    calls.append((obs.shape, steps))
    return np.full((obs.shape[0], steps) + obs.shape[2:], -1.0, np.float32)

  rolled = contact.condition_features(slots, 'rollout', 4, rollout)
  assert calls == [((2, 4, 3, 2), 2)]
  np.testing.assert_array_equal(rolled[:, :4], slots[:, :4])
  assert (rolled[:, 4:] == -1).all()
  with pytest.raises(ValueError, match='unknown condition'):
    contact.condition_features(slots, 'oracle', 4)


def test_contact_stage_names_the_missing_stage(tmp_path):
  config = synthetic_contact.get_config('tiny')
  with pytest.raises(FileNotFoundError, match='extract_slots'):
    contact_stages.load_split(Run.create(config, str(tmp_path)),
                              'readout_train')


def test_planning_task_splits_are_disjoint_and_within_template():
  config = synthetic_phyre.get_config('tiny')
  splits = phyre_planning.task_splits(config.data, config.readout)
  names = {k: {(t.template, t.index) for t in v} for k, v in splits.items()}
  assert not names['train'] & names['dev']
  assert not (names['train'] | names['dev']) & names['test']
  total = len(phyre_world.TEMPLATES) * config.data.tasks_per_template
  assert sum(len(v) for v in names.values()) == total
  # Within-template: every template has training and test tasks (the dev
  # tasks are drawn from all training tasks, as phyre's create_dev_set).
  for split in ('train', 'test'):
    assert ({template for template, _ in names[split]}
            == set(phyre_world.TEMPLATES))


def test_first_frames_draw_the_action_ball():
  config = phyre_world.PhyreLikeConfig(tasks_per_template=1)
  task = phyre_world.make_task(config, 'stack', 0)
  action = np.array([[0.1, 0.9, 0.5]])
  frame = phyre_planning.first_frames(task, action, (64, 64))[0]
  red = (frame == phyre_world.KIND_RGB[phyre_world.ACTION]).all(-1)
  rows, cols = np.nonzero(red)
  # The ball's centre at (1 m, 9 m) of a 10 m scene: upper-left corner.
  assert abs(rows.mean() - 0.1 * 64) < 1.5 and abs(cols.mean() - 0.1 * 64) < 1.5
  # Without the ball it is the task's first frame of a real rollout.
  video = phyre_world.render_video(task, action[0], config)
  np.testing.assert_array_equal(video['video'][0], frame)


def test_first_frames_draw_the_tilted_ramp_as_the_simulator():
  # The classifier's first frame must be the rollout's frame 0, tilted
  # bodies included (drawing the ramp flat would show another task).
  config = phyre_world.PhyreLikeConfig(templates=('ramp',),
                                      tasks_per_template=1)
  task = phyre_world.make_task(config, 'ramp', 0)
  action = np.array([[0.5, 0.9, 0.2]])
  assert phyre_world.is_valid(task, action[0])
  frame = phyre_planning.first_frames(task, action, (64, 64))[0]
  video = phyre_world.render_video(task, action[0], config)
  np.testing.assert_array_equal(video['video'][0], frame)


@pytest.mark.parametrize('stride', [1, 3])
def test_interleaved_rollout_restores_frame_order(stride):
  # Slots hold their frame index; the fake model continues its context's
  # spacing, so a correct interleaving returns the future frame indices.
  num_observed, num_steps, burn_in = 12, 7, 3
  frames = np.arange(num_observed, dtype=np.float32)
  observed = np.broadcast_to(frames[None, :, None, None], (2, num_observed,
                                                           1, 1)).copy()

  def predict(context, steps):
    assert context.shape[1] == burn_in
    spacing = context[:, -1] - context[:, -2]
    assert np.all(spacing == stride)
    k = np.arange(1, steps + 1, dtype=np.float32)[None, :, None, None]
    return context[:, -1:] + k * spacing[:, None]

  out = contact.interleaved_rollout(observed, num_steps, burn_in, stride,
                                    predict)
  np.testing.assert_array_equal(out[0, :, 0, 0],
                                np.arange(num_observed,
                                          num_observed + num_steps))
  with pytest.raises(ValueError, match='observed frames'):
    contact.interleaved_rollout(observed[:, :2], 3, burn_in, stride, predict)


def test_physion_contact_config_names_real_splits():
  from configs import physion_contact  # pylint: disable=g-import-not-at-top
  config = physion_contact.get_config()
  assert contact.readout_splits(config.readout) == (
      'readout_train', 'readout_val', 'test')
  assert set(contact.readout_splits(config.readout)) <= set(
      config.extraction.splits)


def test_ramp_layouts_variant_changes_only_where_dynamics_videos_come_from():
  ramp = synthetic_phyre.get_config('ramp').to_dict()
  layouts = synthetic_phyre.get_config('ramp_layouts').to_dict()
  # max_context = 6 is what every measured :ramp run passed on the command line.
  assert sorted(flat_differences(ramp, layouts)) == [
      'data.dynamics_layouts: 0 -> 300', 'slotformer.max_context: 0 -> 6']


def test_every_config_file_loads_from_any_folder(tmp_path):
  """A config file that builds on another (physion_contact.py on
  physion.py) finds it by path: `--config=<checkout>/configs/...` works
  from any folder, with nothing of the checkout on sys.path (it ended in
  `No module named 'configs'`)."""
  import os  # pylint: disable=g-import-not-at-top
  import subprocess  # pylint: disable=g-import-not-at-top
  import sys  # pylint: disable=g-import-not-at-top
  root = os.path.dirname(os.path.dirname(os.path.dirname(
      os.path.abspath(__file__))))
  configs = os.path.join(root, 'configs')
  script = ('import sys; from slotformer_jax.config.checks import '
            'load_config_file; [load_config_file(p) for p in sys.argv[1:]]')
  env = {k: v for k, v in os.environ.items() if k != 'PYTHONPATH'}
  result = subprocess.run(
      [sys.executable, '-c', script] + sorted(
          os.path.join(configs, name) for name in os.listdir(configs)
          if name.endswith('.py')),
      cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
  assert result.returncode == 0, result.stderr[-2000:]
