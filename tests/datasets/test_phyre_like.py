"""Tests of the PHYRE-like world (pymunk) and of its dataset's generator."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slotformer_jax.datasets import synthetic_phyre as phyre_writer
from slotformer_jax.tasks import phyre_world as p

CONFIG = phyre_writer.PhyreLikeConfig(tasks_per_template=5, num_candidates=40)


def _action(x: float, y: float, radius: float) -> tuple[float, float, float]:
  """World (x, y, radius) [m] -> the [0, 1]^3 action."""
  return (x / p.WORLD, y / p.WORLD,
          (radius - p.MIN_ACTION_RADIUS)
          / (p.MAX_ACTION_RADIUS - p.MIN_ACTION_RADIUS))


# A green ball balanced on a thin static peg; the goal strip starts just
# right of the peg. Dropping the red ball on the ball's upper-left shoulder
# knocks it right, onto the goal; on the upper-right shoulder, left.
BALANCED = p.Task('hand', 0, (
    p.Body(p.STATIC, 'box', (5.0, 1.0), size=(0.2, 2.0)),
    p._goal_strip(1, 5.3),  # pylint: disable=protected-access
    p.Body(p.GREEN, 'ball', (5.0, 2.5), radius=0.5),
))


def test_known_success_failure_and_invalid_actions():
  assert p.simulate(BALANCED, None, CONFIG)['outcome'] == p.NOT_SOLVED
  assert p.simulate(BALANCED, _action(4.4, 4.0, 0.5),
                    CONFIG)['outcome'] == p.SOLVED
  assert p.simulate(BALANCED, _action(5.6, 4.0, 0.5),
                    CONFIG)['outcome'] == p.NOT_SOLVED
  # Overlapping the green ball, or sticking out of the scene: invalid.
  assert p.simulate(BALANCED, _action(5.0, 2.8, 0.5),
                    CONFIG)['outcome'] == p.INVALID
  assert not p.is_valid(BALANCED, _action(0.2, 5.0, 0.5))
  # Needs the contact to last: with more time than simulated it cannot pass.
  strict = dataclasses.replace(CONFIG, success_seconds=CONFIG.sim_seconds)
  assert p.simulate(BALANCED, _action(4.4, 4.0, 0.5),
                    strict)['outcome'] == p.NOT_SOLVED


def test_render_video_shapes_and_masks():
  out = p.render_video(BALANCED, _action(4.4, 4.0, 0.5), CONFIG)
  assert out['video'].shape == (CONFIG.num_frames, 64, 64, 3)
  assert out['segmentations'].shape == (CONFIG.num_frames, 64, 64)
  assert int(out['outcome']) == p.SOLVED
  # Ids: peg 1, goal 2, green 3, red ball 4; all visible in frame 0.
  np.testing.assert_array_equal(np.unique(out['segmentations'][0]),
                                [0, 1, 2, 3, 4])
  green = out['segmentations'][0] == 3
  # Edge pixels are blended by anti-aliasing; most are pure green.
  pure = (out['video'][0][green] == p.KIND_RGB[p.GREEN]).all(-1)
  assert pure.mean() > 0.5
  # The ball falls: its mask moves down the image.
  rows = [np.nonzero(m == 4)[0].mean() for m in out['segmentations'][:3]]
  assert rows[0] < rows[1] < rows[2]


def test_generator_is_deterministic_and_split_within_templates():
  actions = p.candidate_actions(CONFIG)
  np.testing.assert_array_equal(actions, p.candidate_actions(CONFIG))
  task = p.make_task(CONFIG, 'tower', 3)
  assert task == p.make_task(CONFIG, 'tower', 3)
  assert task != p.make_task(dataclasses.replace(CONFIG, seed=1), 'tower', 3)
  labels = p.label_candidates(task, actions, CONFIG)
  np.testing.assert_array_equal(labels,
                                p.label_candidates(task, actions, CONFIG))
  video = p.render_video(task, actions[labels != p.INVALID][0], CONFIG)
  again = p.render_video(task, actions[labels != p.INVALID][0], CONFIG)
  np.testing.assert_array_equal(video['video'], again['video'])
  splits = p.split_tasks(CONFIG)
  for template in CONFIG.templates:
    train = [t.index for t in splits['train'] if t.template == template]
    test = [t.index for t in splits['test'] if t.template == template]
    assert len(train) == 4 and len(test) == 1
    assert sorted(train + test) == list(range(5))
  other_fold = p.split_tasks(dataclasses.replace(CONFIG, fold=1))
  assert ([t.index for t in other_fold['test']]
          != [t.index for t in splits['test']])


def test_bad_config():
  with pytest.raises(ValueError, match='unknown templates'):
    phyre_writer.PhyreLikeConfig(templates=('seesaw',))


# ---- the 'ramp' template ----------------------------------------------------

RAMP_CONFIG = phyre_writer.PhyreLikeConfig(templates=('ramp',),
                                         tasks_per_template=4,
                                         num_candidates=40)

# A hand-built ramp task: a 30-degree ramp whose lower end is at (3, 3); the
# green ball starts at its top and flies right over a basket (goal from
# x = 2.5 to 5.0, static lip at 5.15) to land near x ~ 6.
_ANGLE = np.deg2rad(30.0)
_RAMP = p._ramp_box((3.0, 3.0), 3.0, _ANGLE)  # pylint: disable=protected-access
_ALONG = 3.0 - 0.5 - 0.1
HAND_RAMP = p.Task('hand', 0, (
    _RAMP,
    p.Body(p.STATIC, 'box', (5.15, 0.35), size=(0.3, 0.7)),
    p.Body(p.GOAL, 'box', (3.75, p.GOAL_THICKNESS / 2),
           size=(2.5, p.GOAL_THICKNESS)),
    p.Body(p.GREEN, 'ball',
           (3.0 - np.cos(_ANGLE) * _ALONG + np.sin(_ANGLE) * 0.5,
            3.0 + np.sin(_ANGLE) * _ALONG + np.cos(_ANGLE) * 0.5),
           radius=0.5),
))


def test_ramp_hand_task_success_and_failure():
  # No red ball: the green ball rolls off the ramp and over the basket.
  landing = p._first_floor_touch(HAND_RAMP.bodies)  # pylint: disable=protected-access
  assert landing > 5.3
  assert p.simulate(HAND_RAMP, None, RAMP_CONFIG)['outcome'] == p.NOT_SOLVED
  # A red ball far left of everything changes nothing.
  assert p.simulate(HAND_RAMP, _action(1.0, 1.0, 0.5),
                    RAMP_CONFIG)['outcome'] == p.NOT_SOLVED
  # A big red ball resting on the floor just beyond the lip, where the green
  # ball would land: the green ball hits it and drops back into the basket.
  assert p.simulate(HAND_RAMP, _action(6.3, 1.0, 1.0),
                    RAMP_CONFIG)['outcome'] == p.SOLVED
  # Overlapping the ramp: invalid.
  assert not p.is_valid(HAND_RAMP, _action(2.0, 3.3, 0.5))


def test_ramp_tasks_deterministic_and_unsolved_without_action():
  task = p.make_task(RAMP_CONFIG, 'ramp', 2)
  assert task == p.make_task(RAMP_CONFIG, 'ramp', 2)
  assert task != p.make_task(dataclasses.replace(RAMP_CONFIG, seed=1),
                             'ramp', 2)
  for task in p.all_tasks(RAMP_CONFIG):
    kinds = [b.kind for b in task.bodies]
    assert kinds == [p.STATIC, p.STATIC, p.GOAL, p.GREEN]
    assert task.bodies[0].angle != 0.0  # the ramp is tilted
    assert p.simulate(task, None, RAMP_CONFIG)['outcome'] == p.NOT_SOLVED
  labels = p.label_candidates(task, p.candidate_actions(RAMP_CONFIG),
                              RAMP_CONFIG)
  np.testing.assert_array_equal(labels, p.label_candidates(
      task, p.candidate_actions(RAMP_CONFIG), RAMP_CONFIG))
  # The ramp is drawn tilted: its mask spans many rows and columns.
  frame = p.render_video(task, p.candidate_actions(RAMP_CONFIG)[
      labels != p.INVALID][0], RAMP_CONFIG)['segmentations'][0]
  rows, cols = np.nonzero(frame == 1)
  assert np.ptp(rows) > 8 and np.ptp(cols) > 8


def test_default_templates_unchanged():
  # The first templates keep their names, order, tasks and dataset folder
  # names (cached datasets are found by slug) when templates are added.
  assert p.TEMPLATES == ('ledge', 'tower', 'stack')
  assert p.ALL_TEMPLATES[:3] == p.TEMPLATES
  assert phyre_writer.PhyreLikeConfig().templates == p.TEMPLATES
  config = phyre_writer.PhyreLikeConfig(resolution=(32, 32))
  assert phyre_writer.slug(config) == (
      'r32x32_f2_t5_k1_3x25_c200_fold0_s0_35de6daa')
  assert all(b.angle == 0.0 for t in p.all_tasks(CONFIG) for b in t.bodies)


def test_dynamics_layouts_are_never_labelled_tasks_and_fold_free():
  config = phyre_writer.PhyreLikeConfig(templates=('stack', 'tower'),
                                      tasks_per_template=4, num_candidates=6,
                                      resolution=(16, 16))
  layouts = p.layout_tasks(config, 3)
  labelled = {(t.template, t.index) for t in p.all_tasks(config)}
  assert len(layouts) == 6
  assert not {(t.template, t.index) for t in layouts} & labelled
  other_fold = p.layout_tasks(dataclasses.replace(config, fold=2), 3)
  assert [t.bodies for t in layouts] == [t.bodies for t in other_fold]
  actions = p.candidate_actions(config)
  labels = {(t.template, t.index): p.label_candidates(t, actions, config)
            for t in layouts}
  for index in range(6):  # each layout once, in layout_tasks' order
    video = phyre_writer.training_video(config, labels, 0.0, 'train', index,
                                        layouts=3)
    task = layouts[index]
    assert int(video['task']) == (config.templates.index(task.template)
                                  * 10_000 + task.index)
  # Without layouts the videos stay on the fold's training tasks.
  train = {(t.template, t.index) for t in p.split_tasks(config)['train']}
  labels = {(t.template, t.index): p.label_candidates(t, actions, config)
            for t in p.all_tasks(config)}
  video = phyre_writer.training_video(config, labels, 0.0, 'train', 0)
  code = int(video['task'])
  assert (config.templates[code // 10_000], code % 10_000) in train


def test_dynamics_layouts_change_only_their_own_dataset_name():
  plain = phyre_writer.Videos(CONFIG, 8, 0, 0.2)
  with_layouts = phyre_writer.Videos(CONFIG, 8, 0, 0.2, layouts=5)
  assert with_layouts.slug == plain.slug + '_l5'
  assert not plain.slug.endswith('_l0')
