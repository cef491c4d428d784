"""benchmarks/input_pipeline.py: the input-rate arithmetic (no timings)."""

import importlib.util
import os
import sys
import types

import numpy as np
import pytest

SCRIPT = os.path.join(os.path.dirname(__file__), '..', '..', 'benchmarks',
                      'input_pipeline.py')


def _module():
  spec = importlib.util.spec_from_file_location('input_pipeline', SCRIPT)
  module = importlib.util.module_from_spec(spec)
  sys.modules['input_pipeline'] = module  # its dataclass looks itself up
  spec.loader.exec_module(module)
  return module


def _row(dtype, floor, status='compiled', **kw):
  return dict(config='c', step='savi', topology='v5e:2x4', dtype=dtype,
              floor_seconds=floor, status=status, chips=8,
              flops=1e12, bytes_accessed=8e9, **kw)


def test_import_has_no_side_effects():
  path, environ = list(sys.path), dict(os.environ)
  _module()
  assert sys.path == path
  assert dict(os.environ) == environ


def test_need_of_one_synthetic_step():
  ip = _module()
  # 64 clips of 6 frames of 64x64x3 uint8 per 10 ms step.
  clip_bytes = 6 * 64 * 64 * 3
  at_floor = ip.need(64, 0.010, 6, clip_bytes)
  assert at_floor['clips_per_s'] == pytest.approx(6400)
  assert at_floor['frames_per_s'] == pytest.approx(38400)
  assert at_floor['mb_per_s'] == pytest.approx(6400 * 73728 / 1e6)
  twice = ip.need(64, 0.010, 6, clip_bytes, slowdown=2.0)
  assert twice['clips_per_s'] == pytest.approx(3200)
  assert twice['mb_per_s'] == pytest.approx(at_floor['mb_per_s'] / 2)
  # 3200 clips/s from a reader of 100 clips/s per core on an 8-chip host.
  assert ip.cores_per_chip(3200, 100, 8) == pytest.approx(4.0)


def test_pick_row_prefers_bfloat16_and_skips_rows_that_did_not_compile():
  ip = _module()
  rows = [_row('float32', 0.02), _row('bfloat16', 0.01)]
  assert ip.pick_row(rows, 'c', 'savi', 'v5e:2x4')['dtype'] == 'bfloat16'
  rows = [_row('float32', 0.02), _row('bfloat16', None, status='not built')]
  assert ip.pick_row(rows, 'c', 'savi', 'v5e:2x4')['dtype'] == 'float32'
  assert ip.pick_row(rows, 'c', 'savi', 'v4:2x2x1') is None
  assert ip.pick_row(rows, 'c', 'steve', 'v5e:2x4') is None


def test_gpu_floor_spreads_the_global_counts_over_the_gpus():
  ip = _module()
  row = _row('bfloat16', 0.01)  # 8 chips x (1 TFLOP, 8 GB)
  # 8 GPUs: 1 TFLOP and 8 GB each; bytes bound at 1 TB/s.
  assert ip.gpu_floor(row, 8, 1e15, 1e12) == pytest.approx(8e-3)
  # 4 GPUs: 2 TFLOP each, FLOPs bound at 100 TFLOP/s.
  assert ip.gpu_floor(row, 4, 1e14, 1e13) == pytest.approx(2e-2)


def test_clip_shape_counts_every_field_of_the_batch():
  ip = _module()
  field = lambda *shape, dtype: types.SimpleNamespace(shape=shape,
                                                      dtype=dtype)
  spec = {'video': field(48, 6, 128, 128, 3, dtype=np.uint8),
          'tokens': field(48, 6, 1024, dtype=np.uint16)}
  assert ip.clip_shape(spec, 'steve') == (
      48, 6, 6 * 128 * 128 * 3 + 6 * 1024 * 2)
  spec = {'slots': field(64, 11, 8, 128, dtype=np.float32)}
  assert ip.clip_shape(spec, 'slotformer') == (64, 11, 11 * 8 * 128 * 4)


def test_rows_from_the_paper_configs():
  ip = _module()
  savi = ip.describe('obj3d', 'savi')
  assert (savi['batch'], savi['frames_per_clip'], savi['bytes_per_clip']) == (
      64, 6, 6 * 64 * 64 * 3)
  assert savi['stream'].kind == 'clips'
  assert savi['stream'].video_frames == 50
  assert ip.describe('obj3d', 'slotformer')['variant'] == 'with L_I'
  phyre = ip.describe('phyre', 'slotformer')
  assert (phyre['variant'], phyre['stream'].kind) == ('without L_I', 'slots')
  json_rows = [dict(_row('bfloat16', 0.010), config='obj3d')]
  rate_key = savi['stream'].key
  rows = ip.build_rows(json_rows, {'obj3d'}, {rate_key: 100.0})
  obj3d_savi = rows[0]
  v5e = obj3d_savi['platforms']['v5e-8']
  assert v5e['twice']['clips_per_s'] == pytest.approx(3200)
  assert v5e['twice']['cores_per_chip'] == pytest.approx(4.0)
  assert obj3d_savi['platforms']['v4-8'] is None  # no v4 row given
  assert obj3d_savi['platforms']['gpu']['floor_ms'] == pytest.approx(
      8e9 / 3.35e12 * 1e3)
