"""experiments/vqa_state_probe.py: the state features by hand."""

from __future__ import annotations

import numpy as np

from pipeline_helpers import load_experiment


def _probe():
  return load_experiment('vqa_state_probe')


def test_closest_approach_by_hand():
  probe = _probe()
  # Head-on, 4 apart, closing at 2 per frame: they meet after 2 frames.
  t, d = probe.closest_approach(np.array([0., 0.]), np.array([4., 0.]),
                                np.array([1., 0.]), np.array([-1., 0.]), 16)
  assert (t, d) == (2.0, 0.0)
  # ... unless the horizon ends first.
  assert probe.closest_approach(np.array([0., 0.]), np.array([4., 0.]),
                                np.array([1., 0.]), np.array([-1., 0.]),
                                1) == (1.0, 2.0)
  # Moving apart: closest now.
  assert probe.closest_approach(np.array([0., 0.]), np.array([0., 3.]),
                                np.array([0., -1.]), np.array([0., 0.]),
                                16) == (0.0, 3.0)


def test_option_features_read_the_last_two_observed_frames():
  probe = _probe()
  # Object 0 moves +1 in x per frame from x = 0; object 1 rests at (10, 0).
  frames = np.arange(8, dtype=float)
  positions = np.zeros((8, 2, 2))
  positions[:, 0, 0] = frames
  positions[:, 1, 0] = 10.0
  state, future = probe.option_features(positions, 0, 1, observed=5,
                                        horizon=3)
  # Last observed frame 4: a at x = 4, b at 10, relative velocity (1, 0).
  np.testing.assert_allclose(state[:2], [4, 0])
  np.testing.assert_allclose(state[4:6], [1, 0])
  np.testing.assert_allclose(state[-3:], [6, 3, 3])  # distance, t, d(t)
  assert future == 3.0  # frame 7: x = 7 vs 10
