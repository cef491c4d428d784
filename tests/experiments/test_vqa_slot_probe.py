"""experiments/vqa_slot_probe.py: slot -> object assignment and the probes."""

from __future__ import annotations

import numpy as np

from pipeline_helpers import load_experiment


def _probe():
  return load_experiment('vqa_slot_probe')


def test_assign_slots_by_hand():
  probe = _probe()
  seg = np.zeros((4, 4), np.int64)
  seg[0, :2] = 1          # object 0: two pixels
  seg[2:, 2:] = 2         # object 1: four pixels
  winner = np.zeros((4, 4), np.int64)   # slot 0: background + object 0
  winner[0, :2] = 3       # slot 3 wins exactly object 0's pixels
  winner[2:, 2:] = 1      # slot 1: object 1 ...
  winner[1, 3] = 1        # ... plus one background pixel (4 of 5: kept)
  winner[3, 0] = 2        # slot 2: one background pixel only
  assert probe.assign_slots(winner, seg, num_objects=2) == {3: 0, 1: 1}
  # A slot mostly on background is not an object slot.
  winner[:2, :] = 1
  winner[0, :2] = 3
  assert probe.assign_slots(winner, seg, num_objects=2) == {3: 0}


def test_probes_recover_a_linear_signal():
  probe = _probe()
  rng = np.random.default_rng(0)
  x = rng.normal(size=(400, 5))
  label = (x[:, 0] > 0).astype(np.int64) + 2 * (x[:, 1] > 0)
  _, test_acc, majority = probe.logistic_probe(x[:300], label[:300], x[300:],
                                               label[300:], 4)
  assert test_acc > 0.85 and majority < 0.4
  y = np.stack([x[:, 2] * 2 + 1, -x[:, 3]], -1)
  np.testing.assert_allclose(probe.ridge_r2(x[:300], y[:300], x[300:],
                                            y[300:]), 1.0, atol=1e-3)
  noise = rng.normal(size=(400, 1))
  assert probe.ridge_r2(x[:300], noise[:300], x[300:], noise[300:])[0] < 0.1
