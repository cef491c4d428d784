"""experiments/vqa_pair_probe.py: slot of each object, features per input."""

from __future__ import annotations

import numpy as np

from pipeline_helpers import load_experiment


def _probe():
  return load_experiment('vqa_pair_probe')


def test_object_slots_pick_the_slot_most_on_each_object():
  probe = _probe()
  seg = np.zeros((4, 4), np.int64)
  seg[0, :2] = 1            # object 0
  seg[3, 3] = 2             # object 1: one pixel
  alpha = np.full((3, 4, 4), 1 / 3)
  alpha[2, 0, :2], alpha[0, 0, :2], alpha[1, 0, :2] = 0.8, 0.1, 0.1
  alpha[1, 3, 3], alpha[0, 3, 3], alpha[2, 3, 3] = 0.5, 0.3, 0.2
  # Object 2 is out of view: no entry.
  assert probe.object_slots(alpha, seg, num_objects=3) == {0: 2, 1: 1}


def test_pair_features_by_hand():
  probe = _probe()
  observed, length, slots = 3, 6, 3
  rollout = np.zeros((length, slots, 2))
  # Slot 0 at rest at (0, 0); slot 2 comes along x from (4, 0), 1 per frame.
  rollout[:, 2, 0] = 4.0 - np.arange(length) + 2  # frames 0..2: 6, 5, 4
  future = rollout.copy()
  future[observed:, 2, 0] = [5.0, 6.0, 7.0]       # really it turns back
  features = probe.pair_features(np.stack([rollout, future]), 0, 2,
                                 observed)
  # Last observed: a at (0, 0), b at (4, 0) moving -1 per frame.
  np.testing.assert_allclose(features['observed'][:4], [0, 0, 4, 0])
  np.testing.assert_allclose(features['observed'][4:8], [0, 0, -1, 0])
  np.testing.assert_allclose(features['observed'][-3:], [4.0, 3.0, 1.0])
  np.testing.assert_allclose(features['copy-last'], [4.0])
  np.testing.assert_allclose(features['rollout'], [1.0])  # frames 3..5: 3,2,1
  np.testing.assert_allclose(features['future'], [5.0])
