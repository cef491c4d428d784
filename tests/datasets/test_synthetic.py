"""Tests of the OBJ3D-like synthetic generator and its TFDS cache."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest

from slotformer_jax.data.write.generate import Output
from slotformer_jax.data import sources
from slotformer_jax.datasets import synthetic
from slotformer_jax.data import supersample

TINY = synthetic.SyntheticConfig(resolution=(32, 32), num_frames=8,
                                      num_train=4, num_val=2, num_test=2,
                                      seed=0)
# Long enough for the launched sphere to reach the static objects.
LONG = dataclasses.replace(TINY, num_frames=30)


def _interior(seg: np.ndarray) -> np.ndarray:
  """bool [T, H, W]: pixels whose 4 neighbours share their id.

  Object edges are blended with the background by anti-aliasing, so colour
  checks only look at interior pixels.
  """
  p = np.pad(seg, ((0, 0), (1, 1), (1, 1)), mode='edge')
  c = p[:, 1:-1, 1:-1]
  return ((c == p[:, :-2, 1:-1]) & (c == p[:, 2:, 1:-1])
          & (c == p[:, 1:-1, :-2]) & (c == p[:, 1:-1, 2:]))


def _closest_color(mean_rgb: np.ndarray) -> tuple[int, float]:
  """Palette entry matching ``mean_rgb`` up to a brightness factor (shading)."""
  palette = np.asarray(synthetic.COLOR_RGB, np.float64)
  scale = palette @ mean_rgb / (palette * palette).sum(1)
  residual = np.linalg.norm(mean_rgb[None] - scale[:, None] * palette, axis=1)
  best = int(residual.argmin())
  return best, float(scale[best])


@pytest.fixture(scope='module')
def long_videos() -> list[dict[str, np.ndarray]]:
  return [synthetic.generate_video(LONG, 'train', i) for i in range(6)]


@pytest.fixture(scope='module')
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
  root = tmp_path_factory.mktemp('data')
  return root, synthetic.generate(TINY, Output(root, 1))


def test_generator_is_deterministic():
  a = synthetic.generate_video(TINY, 'train', 1)
  b = synthetic.generate_video(TINY, 'train', 1)
  assert a.keys() == b.keys()
  for key in a:
    assert a[key].dtype == b[key].dtype
    assert a[key].tobytes() == b[key].tobytes(), key
  other_seed = synthetic.generate_video(
      dataclasses.replace(TINY, seed=1), 'train', 1)
  other_index = synthetic.generate_video(TINY, 'train', 2)
  other_split = synthetic.generate_video(TINY, 'val', 1)
  for other in (other_seed, other_index, other_split):
    assert other['video'].tobytes() != a['video'].tobytes()


def test_shapes_and_dtypes():
  ex = synthetic.generate_video(TINY, 'test', 0)
  t, (h, w), o = TINY.num_frames, TINY.resolution, TINY.max_objects_total
  expected = {
      'video': ((t, h, w, 3), np.uint8),
      'segmentations': ((t, h, w), np.uint8),
      'boxes': ((t, o, 4), np.float32),
      'visible': ((t, o), np.bool_),
      'positions': ((t, o, 3), np.float32),
      'num_objects': ((), np.int32),
      'shapes': ((o,), np.int32),
      'colors': ((o,), np.int32),
      'sizes': ((o,), np.int32),
      'index': ((), np.int32),
  }
  assert set(ex) == set(expected)
  for key, (shape, dtype) in expected.items():
    assert ex[key].shape == shape, key
    assert ex[key].dtype == dtype, key
  n = int(ex['num_objects'])
  assert TINY.min_objects + 1 <= n <= TINY.max_objects + 1
  for key in ('shapes', 'colors', 'sizes'):
    assert (ex[key][:n] >= 0).all() and (ex[key][n:] == -1).all(), key
  # The launched sphere.
  assert synthetic.SHAPES[ex['shapes'][n - 1]] == 'sphere'
  assert ex['segmentations'].max() <= n


@pytest.mark.parametrize('resolution', [(32, 32), (64, 64), (128, 128),
                                        (48, 64)])
def test_resolutions(resolution: tuple[int, int]):
  config = dataclasses.replace(TINY, resolution=resolution, num_frames=2)
  ex = synthetic.generate_video(config, 'train', 0)
  assert ex['video'].shape == (2, *resolution, 3)
  assert ex['segmentations'].shape == (2, *resolution)
  n = int(ex['num_objects'])
  # Every object (launched sphere included) is in view at the start.
  assert ex['visible'][0, :n].all()


def test_all_objects_visible_at_start_and_padding_empty(long_videos):
  for ex in long_videos:
    n = int(ex['num_objects'])
    seg = ex['segmentations']
    for k in range(1, n + 1):
      assert (seg[0] == k).sum() > 0, k
    assert ex['visible'][0, :n].all()
    assert not ex['visible'][:, n:].any()
    assert (ex['boxes'][:, n:] == 0).all()


def test_masks_match_object_colors(long_videos):
  checked = 0
  for ex in long_videos:
    seg, video = ex['segmentations'], ex['video'].astype(np.float64)
    interior = _interior(seg)
    for t in range(LONG.num_frames):
      for k in range(1, int(ex['num_objects']) + 1):
        pixels = (seg[t] == k) & interior[t]
        if pixels.sum() < 3:
          continue
        color, scale = _closest_color(video[t][pixels].mean(0))
        assert color == ex['colors'][k - 1], (t, k)
        assert 0.5 < scale < 1.3, (t, k, scale)
        checked += 1
    # Background is the floor: gray, not an object colour.
    floor = video[(seg == 0) & interior].mean(0)
    np.testing.assert_allclose(floor, synthetic.FLOOR_RGB, atol=25)
  # Ids are stable over time: the check above ran on every frame.
  assert checked > len(long_videos) * LONG.num_frames * 2


def test_boxes_agree_with_masks(long_videos):
  for ex in long_videos:
    seg = ex['segmentations']
    _, h, w = seg.shape
    for t in range(seg.shape[0]):
      for k in range(1, ex['boxes'].shape[1] + 1):
        rows, cols = np.nonzero(seg[t] == k)
        visible = rows.size > 0
        assert ex['visible'][t, k - 1] == visible
        if visible:
          expected = [rows.min() / h, cols.min() / w, (rows.max() + 1) / h,
                      (cols.max() + 1) / w]
          np.testing.assert_allclose(ex['boxes'][t, k - 1], expected,
                                     atol=1e-6)
        else:
          assert (ex['boxes'][t, k - 1] == 0).all()
  assert all(((b >= 0) & (b <= 1)).all() for b in
             (ex['boxes'] for ex in long_videos))


def test_launched_sphere_rolls_in_and_hits_something(long_videos):
  collisions = 0
  for ex in long_videos:
    n = int(ex['num_objects'])
    pos = ex['positions'][:, :n, :2]
    sphere_path = np.linalg.norm(pos[-1, -1] - pos[0, -1])
    assert sphere_path > 1.0  # launched sphere travels
    assert pos[0, -1, 1] < pos[0, :-1, 1].min()  # starts in front
    static_moves = np.linalg.norm(pos[-1, :-1] - pos[0, :-1], axis=-1)
    collisions += bool((static_moves > 0.05).any())
    # The static objects are at rest before anything reaches them.
    np.testing.assert_allclose(pos[1, :-1], pos[0, :-1], atol=1e-3)
  assert collisions >= len(long_videos) - 1


def test_downsample_segmentation_majority():
  seg = np.array([[1, 1, 0, 2],
                  [1, 0, 2, 2],
                  [3, 0, 0, 0],
                  [0, 3, 0, 0]], np.uint8)
  out = supersample.downsample_segmentation(seg, 2)
  # Majorities 1 and 2; the 2-2 tie takes the first id in raster order.
  np.testing.assert_array_equal(out, [[1, 2], [3, 0]])
  assert out.dtype == np.uint8


def test_downsample_rgb_is_area_mean():
  image = np.arange(4 * 4 * 3, dtype=np.uint8).reshape(4, 4, 3)
  out = supersample.downsample_rgb(image, 2)
  expected = image.reshape(2, 2, 2, 2, 3).astype(float).mean((1, 3))
  np.testing.assert_allclose(out, np.round(expected + 1e-9), atol=0.5)
  assert out.dtype == np.uint8


def test_boxes_from_segmentation_example():
  seg = np.zeros((1, 4, 8), np.uint8)
  seg[0, 1:3, 2:5] = 2
  boxes, visible = synthetic.boxes_from_segmentation(seg, 3)
  np.testing.assert_array_equal(visible, [[False, True, False]])
  np.testing.assert_allclose(boxes[0, 1], [0.25, 0.25, 0.75, 0.625])
  assert (boxes[0, [0, 2]] == 0).all() and boxes.dtype == np.float32


def test_build_writes_all_splits_in_order(built):
  _, path = built
  assert path.is_dir() and TINY.slug in os.fspath(path)
  for split in synthetic.SPLITS:
    source = sources.TfdsVideoSource(path, split)
    assert len(source) == TINY.num_videos(split)
    for i in range(len(source)):
      got, want = source[i], synthetic.generate_video(TINY, split, i)
      assert got.keys() == want.keys()
      for key in want:
        assert got[key].dtype == want[key].dtype, key
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_cache_is_reused(built, monkeypatch):
  root, path = built
  stamps = {p: p.stat().st_mtime_ns for p in path.iterdir()}

  def fail(*args, **kwargs):
    raise AssertionError('generator called although the cache exists')

  monkeypatch.setattr(synthetic, 'generate_video', fail)
  assert synthetic.generate(TINY, Output(root, 1)) == path
  assert {p: p.stat().st_mtime_ns for p in path.iterdir()} == stamps


def test_parameter_change_builds_a_new_folder(built):
  root, path = built
  changed = dataclasses.replace(TINY, seed=1, num_train=2, num_val=1,
                                num_test=1)
  new_path = synthetic.generate(changed, Output(root, 1))
  assert new_path != path and new_path.is_dir() and path.is_dir()
  assert len(sources.TfdsVideoSource(new_path, 'train')) == 2
  # Each parameter alone changes the folder name.
  for field, value in [('resolution', (64, 64)), ('num_frames', 9),
                       ('min_objects', 2), ('max_objects', 4), ('seed', 3),
                       ('num_train', 5), ('num_val', 3), ('num_test', 3),
                       ('supersample', 1)]:
    assert dataclasses.replace(TINY, **{field: value}).slug != TINY.slug


def test_failed_build_is_not_reused(tmp_path, monkeypatch):
  config = dataclasses.replace(TINY, num_val=0, num_test=0)
  original = synthetic.generate_video

  def flaky(config, split, index):
    if index == 2:
      raise RuntimeError('boom')
    return original(config, split, index)

  monkeypatch.setattr(synthetic, 'generate_video', flaky)
  with pytest.raises(RuntimeError, match='boom'):
    synthetic.generate(config, Output(tmp_path, 1))
  path = synthetic.dataset_dir(config, tmp_path)
  assert not (path / 'dataset_info.json').exists()
  monkeypatch.setattr(synthetic, 'generate_video', original)
  assert synthetic.generate(config, Output(tmp_path, 1)) == path
  assert len(sources.TfdsVideoSource(path, 'train')) == config.num_train


def test_parallel_build_matches_serial(built, tmp_path):
  _, serial = built
  config = dataclasses.replace(TINY, num_val=0, num_test=0)  # train only
  parallel = synthetic.generate(config, Output(tmp_path, 2))
  a = sources.TfdsVideoSource(serial, 'train')
  b = sources.TfdsVideoSource(parallel, 'train')
  assert len(a) == len(b) == TINY.num_train
  for i in range(len(a)):
    for key in a[i]:
      assert a[i][key].tobytes() == b[i][key].tobytes(), (i, key)


def test_invalid_configs():
  with pytest.raises(ValueError):
    synthetic.SyntheticConfig(min_objects=4, max_objects=3)
  with pytest.raises(ValueError):
    synthetic.SyntheticConfig(resolution=(4, 4))
  with pytest.raises(ValueError):
    synthetic.generate_video(TINY, 'training', 0)
