"""experiments/vqa_state_aloe.py: state slots, option objects and masking by hand."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline_helpers import load_experiment
from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.datasets.synthetic import COLORS, SHAPES


def _bench():
  return load_experiment('vqa_state_aloe')


OBJECTS = [{'color': 'red', 'shape': 'cube', 'size': 'small'},
           {'color': 'blue', 'shape': 'sphere', 'size': 'large'}]


def test_state_slots_by_hand():
  bench = _bench()
  # Object 0 moves +0.3 m in x per frame from x = 0.6; object 1 rests at
  # (0, -1.5) and is out of view at frame 1.
  positions = np.zeros((3, 2, 3))
  positions[:, 0, 0] = [0.6, 0.9, 1.2]
  positions[:, 1, 1] = -1.5
  positions[:, :, 2] = 0.4  # heights are not read
  in_view = np.array([[True, True], [True, False], [True, True]])
  slots = bench.state_slots(positions, in_view, OBJECTS, num_slots=4,
                            slot_size=20)
  assert slots.shape == (3, 4, 20) and slots.dtype == np.float32
  c, s = len(COLORS), len(COLORS) + len(SHAPES)
  red, cube = COLORS.index('red'), c + SHAPES.index('cube')
  for t in range(3):
    expected = np.zeros(20, np.float32)
    expected[[red, cube, s + 4]] = 1.0
    expected[s] = positions[t, 0, 0] / 3.0
    expected[s + 2] = 0.0 if t == 0 else 0.3 * 5.0  # per-frame velocity x 5
    np.testing.assert_allclose(slots[t, 0], expected, atol=1e-6)
  blue, sphere = COLORS.index('blue'), c + SHAPES.index('sphere')
  expected = np.zeros(20, np.float32)
  expected[[blue, sphere, s + 4]] = 1.0
  expected[s + 1] = -0.5
  np.testing.assert_allclose(slots[0, 1], expected, atol=1e-6)
  np.testing.assert_allclose(slots[2, 1], expected, atol=1e-6)
  assert not slots[1, 1].any()  # out of view: all zero
  assert not slots[:, 2:].any()  # no object
  with pytest.raises(ValueError):
    bench.state_slots(positions, in_view, OBJECTS, num_slots=1,
                      slot_size=20)
  with pytest.raises(ValueError):
    bench.state_slots(positions, in_view, OBJECTS, num_slots=4,
                      slot_size=bench.STATE_FEATURES - 1)


def test_keep_slots_zeroes_the_others():
  bench = _bench()
  slots = np.arange(2 * 3 * 2, dtype=np.float32).reshape(2, 3, 2) + 1.0
  kept = bench.keep_slots(slots, (0, 2))
  np.testing.assert_array_equal(kept[:, [0, 2]], slots[:, [0, 2]])
  assert not kept[:, 1].any()


def test_choice_objects_and_one_choice_questions():
  bench = _bench()
  assert bench.choice_objects('the blue sphere collides with the red cube',
                              OBJECTS) == (1, 0)
  with pytest.raises(ValueError):
    bench.choice_objects('the presence of the red cube', OBJECTS)
  question = vqa_data.EncodedQuestion(
      scene_index=3, video_filename='video_00003.mp4', question_id=5,
      question_type=2, template='next',
      tokens=np.array([[1, 2, 3], [1, 2, 4]], np.int32),
      pad_mask=np.zeros((2, 3), bool),
      choice_ids=np.array([0, 1], np.int32),
      choice_labels=np.array([1, 0], np.int32))
  ones = bench.one_choice_questions(
      question, ['the red cube collides with the blue sphere',
                 'the blue sphere collides with the red cube'], '3:5',
      OBJECTS)
  assert [named for _, named in ones] == [(0, 1), (1, 0)]
  assert [q.video_filename for q, _ in ones] == ['3:5#0', '3:5#1']
  assert [q.choice_labels.tolist() for q, _ in ones] == [[1], [0]]
  assert ones[1][0].tokens.tolist() == [[1, 2, 4]]
  assert ones[1][0].choice_ids.tolist() == [1]
  assert all(q.question_type == 2 and q.scene_index == 3 for q, _ in ones)
