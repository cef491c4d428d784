"""experiments/target_signal.py: the part of a target only objects explain."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline_helpers import load_experiment


def _probe():
  return load_experiment('target_signal')


def test_signal_by_hand():
  # 3 one-channel frames of 2 pixels: a background of 0 (left) and 1
  # (right); an object of value 3 on the left pixel of the last frame.
  values = np.array([[[0.0, 1.0]], [[0.0, 1.0]], [[3.0, 1.0]]])
  values = values.reshape(1, 3, 1, 2, 1)
  objects = np.zeros((1, 3, 1, 2), bool)
  objects[0, 2, 0, 0] = True
  out = _probe().signal(values, objects)
  # The median background is (0, 1): only the object pixel errs, by 3.
  assert out['background_only_mse'] == pytest.approx(9 / 6)
  assert out['background_only_mse_objects'] == pytest.approx(9.0)
  assert out['background_only_mse_background'] == 0.0
  assert out['object_share'] == 1.0
  # Per frame: variances 0.25, 0.25, 1.0.
  assert out['per_frame_variance'] == pytest.approx(0.5)
  # Over all 6 values (mean 1): variance (1 + 0 + 1 + 0 + 4 + 0) / 6 = 1.
  assert out['objects_part'] == pytest.approx(1.5)
