"""The OBJ3D-like generator's flow and depth (`data.with_flow_depth`):
exact from the simulator, checked against the simulator's own poses; the
default data untouched."""

from __future__ import annotations

import dataclasses

import numpy as np
import pybullet
import pytest

from dataset_fixtures import data_section
from slotformer_jax import targets
from slotformer_jax.data import flow_depth
from slotformer_jax.data.write.generate import Output
from slotformer_jax.datasets import synthetic
from slotformer_jax.data import supersample

# ss=1: every pixel is one renderer sample, so a pixel's depth is exactly
# its sample's and the checks below can be tight.
EXACT = synthetic.SyntheticConfig(
    resolution=(32, 32), num_frames=12, min_objects=2, max_objects=3,
    num_train=2, num_val=1, num_test=1, seed=0, supersample=1,
    object_scale=1.4, with_flow_depth=True)
SUPERSAMPLED = dataclasses.replace(EXACT, supersample=2)


@pytest.fixture(scope='module')
def exact_video():
  return synthetic.generate_video(EXACT, 'train', 0)


def _decoded(video, name):
  return flow_depth.decode(video[name], video[flow_depth.range_field(name)])


def _rotation(quaternion):
  """(x, y, z, w) -> 3 x 3 rotation matrix (written out here, not
  pybullet's)."""
  x, y, z, w = (float(v) for v in quaternion)
  return np.array([
      [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _camera(height, width):
  """(eye, projection @ view as numpy) straight from pybullet's matrices."""
  view = pybullet.computeViewMatrix(
      cameraEyePosition=synthetic.CAMERA_EYE,
      cameraTargetPosition=synthetic.CAMERA_TARGET,
      cameraUpVector=[0.0, 0.0, 1.0])
  projection = pybullet.computeProjectionMatrixFOV(
      fov=synthetic.CAMERA_FOV_DEG, aspect=width / height,
      nearVal=synthetic.CAMERA_NEAR, farVal=synthetic.CAMERA_FAR)
  matrix = (np.asarray(projection).reshape(4, 4).T
            @ np.asarray(view).reshape(4, 4).T)
  return np.asarray(synthetic.CAMERA_EYE, np.float64), matrix


def _to_pixels(points, matrix, height, width):
  clip = np.concatenate([points, np.ones(points.shape[:-1] + (1,))],
                        -1) @ matrix.T
  ndc = clip[..., :2] / clip[..., 3:]
  return np.stack([(1 - ndc[..., 1]) / 2 * height,
                   (ndc[..., 0] + 1) / 2 * width], -1)


def _rays(matrix, height, width):
  """Unit world directions of each pixel's sample (at row i + 1, column j:
  synthetic.SAMPLE_OFFSET)."""
  rows = (np.arange(height)[:, None] + synthetic.SAMPLE_OFFSET[0]) / height
  cols = (np.arange(width)[None, :] + synthetic.SAMPLE_OFFSET[1]) / width
  ndc = np.stack(np.broadcast_arrays(cols * 2 - 1, 1 - rows * 2,
                                     np.ones((height, width)),
                                     np.ones((height, width))), -1)
  far = ndc @ np.linalg.inv(matrix).T
  far = far[..., :3] / far[..., 3:]
  eye = np.asarray(synthetic.CAMERA_EYE)
  return (far - eye) / np.linalg.norm(far - eye, axis=-1, keepdims=True)


def test_the_default_data_are_those_of_before():
  """No option, no change: the folder name (hard-coded from the code
  before the option), the metadata and every stored field."""
  tiny = synthetic.SyntheticConfig(resolution=(32, 32), num_frames=8,
                                   num_train=4, num_val=2, num_test=2)
  assert tiny.slug == 'r32x32_t8_o3-5_s0_n4-2-2_aa2_927cbb72'
  assert 'with_flow_depth' not in tiny.params()
  assert set(synthetic.features(tiny).keys()) == {
      'video', 'segmentations', 'boxes', 'visible', 'positions',
      'num_objects', 'shapes', 'colors', 'sizes', 'index'}
  with_option = dataclasses.replace(tiny, with_flow_depth=True)
  assert with_option.slug.startswith('r32x32_t8_o3-5_s0_n4-2-2_aa2_fd_')
  plain = synthetic.generate_video(tiny, 'train', 1)
  both = synthetic.generate_video(with_option, 'train', 1)
  assert set(both) - set(plain) == {
      'forward_flow', 'backward_flow', 'depth', 'forward_flow_range',
      'backward_flow_range', 'depth_range', 'orientations'}
  for key, value in plain.items():
    assert value.tobytes() == both[key].tobytes(), key


def test_a_renderer_sample_is_at_the_lower_left_corner_of_its_pixel():
  """Back-projected through the camera at SAMPLE_OFFSET, the floor's
  samples lie on the floor (z = 0); at the pixel centre they would not."""
  client = pybullet.connect(pybullet.DIRECT)
  try:
    floor = synthetic._create_floor(client)  # pylint: disable=protected-access
    lut = np.zeros(floor + 2, np.uint8)
    view, projection = synthetic._camera_matrices(24, 40)  # pylint: disable=protected-access
    _, _, samples = synthetic._render(client, view, projection, 24, 40, 1,  # pylint: disable=protected-access
                                      lut)
  finally:
    pybullet.disconnect(physicsClientId=client)
  camera = synthetic.Camera.of_frames(24, 40)
  points = camera.back_project(samples['depth_buffer'])
  assert np.abs(points[..., 2]).max() < 1e-4
  # The same depths read at the pixel centres: well off the floor.
  eye, matrix = _camera(24, 40)
  depth = np.linalg.norm(points - eye, axis=-1)
  rows = (np.arange(24)[:, None] + 0.5) / 24
  cols = (np.arange(40)[None, :] + 0.5) / 40
  ndc = np.stack(np.broadcast_arrays(cols * 2 - 1, 1 - rows * 2,
                                     np.ones((24, 40)), np.ones((24, 40))),
                 -1)
  far = ndc @ np.linalg.inv(matrix).T
  far = far[..., :3] / far[..., 3:]
  centred = eye + depth[..., None] * (far - eye) / np.linalg.norm(
      far - eye, axis=-1, keepdims=True)
  assert np.abs(centred[..., 2]).max() > 0.05


def test_depth_is_the_distance_from_the_camera(exact_video):
  video = exact_video
  depth = _decoded(video, 'depth')[..., 0]
  seg = video['segmentations']
  assert depth.shape == seg.shape and (depth > 0).all()
  assert video['depth'].dtype == np.uint16
  # The floor recedes up the image: along every column, its depth grows
  # from the bottom row to the top one.
  floor = np.where(seg[0] == 0, depth[0], np.nan)
  column = floor[:, 16]
  column = column[~np.isnan(column)]
  assert (np.diff(column) < 0).all()  # row 0 is the top (farthest)
  # An object's pixels are nearer than the floor behind them would be,
  # and each lies within its size of its centre's distance.
  eye = np.asarray(synthetic.CAMERA_EYE)
  for k in range(1, int(video['num_objects']) + 1):
    pixels = seg[0] == k
    if not pixels.any():
      continue
    centre = np.linalg.norm(video['positions'][0, k - 1] - eye)
    radius = (synthetic.SIZE_RADII[video['sizes'][k - 1]]
              * EXACT.object_scale * np.sqrt(3))
    assert (np.abs(depth[0][pixels] - centre) <= radius).all()
    assert depth[0][pixels].min() < centre


def test_backward_flow_points_where_the_point_was(exact_video):
  """Per pixel of frame t: its surface point (the camera's ray at the
  stored depth), moved back with its object's pose of frame t - 1 (the
  simulator's own positions and orientations), projected with the same
  camera: it lands where the backward flow points. Forward flow likewise
  with frame t + 1; the floor's flows are zero."""
  video = exact_video
  height, width = EXACT.resolution
  eye, matrix = _camera(height, width)
  rays = _rays(matrix, height, width)
  depth = _decoded(video, 'depth')[..., 0]
  seg = video['segmentations']
  positions = video['positions'].astype(np.float64)
  orientations = video['orientations']
  checked = 0
  for name, step in (('backward_flow', -1), ('forward_flow', 1)):
    flow = _decoded(video, name)
    for t in range(EXACT.num_frames):
      other = t + step
      if not 0 <= other < EXACT.num_frames:
        assert np.abs(flow[t]).max() < 1e-3
        continue
      assert np.abs(flow[t][seg[t] == 0]).max() < 1e-3
      points = eye + depth[t][..., None] * rays
      here = _to_pixels(points, matrix, height, width)
      for k in range(1, int(video['num_objects']) + 1):
        pixels = seg[t] == k
        if not pixels.any():
          continue
        local = (points[pixels] - positions[t, k - 1]) @ _rotation(
            orientations[t, k - 1])
        moved = local @ _rotation(orientations[other, k - 1]).T + positions[
            other, k - 1]
        want = _to_pixels(moved, matrix, height, width) - here[pixels]
        np.testing.assert_allclose(flow[t][pixels], want, atol=0.02)
        checked += int(pixels.sum())
  assert checked > 500


def test_static_objects_have_no_flow_until_hit(exact_video):
  video = exact_video
  flow = _decoded(video, 'backward_flow')
  seg = video['segmentations']
  launched = int(video['num_objects'])
  # Frame 1: the sphere is rolling in, nothing else has moved yet.
  for k in range(1, launched):
    assert np.abs(flow[1][seg[1] == k]).max() < 1e-3
  speed = np.linalg.norm(flow[1][seg[1] == launched], axis=-1)
  assert speed.min() > 0.5  # pixels per frame


def test_supersampled_flow_and_depth_follow_the_masks():
  """With supersampling, a pixel's depth and flow are the mean of the
  samples of the surface its (voted) id names: at an object's edge they
  are the object's, not a blend with the floor."""
  video = synthetic.generate_video(SUPERSAMPLED, 'train', 0)
  exact = synthetic.generate_video(EXACT, 'train', 0)
  np.testing.assert_array_equal(video['positions'], exact['positions'])
  seg = video['segmentations']
  depth = _decoded(video, 'depth')[..., 0]
  eye = np.asarray(synthetic.CAMERA_EYE)
  for k in range(1, int(video['num_objects']) + 1):
    pixels = seg[0] == k
    centre = np.linalg.norm(video['positions'][0, k - 1] - eye)
    radius = (synthetic.SIZE_RADII[video['sizes'][k - 1]]
              * SUPERSAMPLED.object_scale * np.sqrt(3))
    assert (np.abs(depth[0][pixels] - centre) <= radius).all()
  assert np.abs(_decoded(video, 'backward_flow')[1][seg[1] == 0]).max() < 1e-3


def test_downsample_by_label_averages_the_voted_surface():
  labels = np.array([[1, 1], [1, 0]])
  values = np.array([[[2.0], [4.0]], [[6.0], [100.0]]])
  voted = supersample.downsample_segmentation(labels, 2)
  assert voted.tolist() == [[1]]
  out = supersample.downsample_by_label(values, labels, voted, 2)
  assert out.dtype == np.float32 and out.tolist() == [[[4.0]]]
  assert supersample.downsample_by_label(values, labels, labels, 1
                                         ).tolist() == values.tolist()


def test_generated_folder_serves_flow_and_depth(tmp_path):
  """Generated with the option, the dataset serves the targets' fields:
  flow = flow_to_rgb(backward flow), depth = log(1 + distance)."""
  config = dataclasses.replace(EXACT, num_train=2, num_val=0, num_test=0,
                               num_frames=6)
  path = synthetic.generate(config, Output(tmp_path, 1))
  assert config.slug in str(path) and '_fd_' in config.slug
  data = data_section(name='synthetic', data_dir=str(tmp_path),
                      resolution=(32, 32), num_frames=6, min_objects=2,
                      max_objects=3, num_train=2, num_val=0, num_test=0,
                      seed=0, supersample=1, object_scale=1.4)
  data.with_flow_depth = True
  assert synthetic.DATASET.dataset_dir(data) == path
  source = synthetic.DATASET.open(data, 'train')
  item = source[1]
  stored = synthetic.generate_video(config, 'train', 1)
  np.testing.assert_allclose(item['backward_flow'],
                             _decoded(stored, 'backward_flow'))
  np.testing.assert_allclose(item['flow'], targets.flow_to_rgb(
      item['backward_flow']))
  np.testing.assert_allclose(item['depth'], np.log1p(_decoded(stored,
                                                              'depth')),
                             rtol=1e-6)
  clip = source.clip(1, 1, 3, 2, ('video', 'flow', 'depth'))
  np.testing.assert_array_equal(clip['flow'], item['flow'][1:6:2])
  assert set(synthetic.DATASET.served_fields(data)) >= {'flow', 'depth'}


def test_a_flow_run_on_data_without_it_is_told_the_option():
  from slotformer_jax.slot_models.savi import Savi  # pylint: disable=g-import-not-at-top
  from pipeline_helpers import load_config  # pylint: disable=g-import-not-at-top
  config = load_config('synthetic', 'tiny')
  config.savi.targets = ('flow', 'depth')
  problems = Savi(config).check_config(frozenset())
  assert len(problems) == 1, problems
  assert "reconstructs 'flow', 'depth'" in problems[0]
  assert 'data.with_flow_depth=True' in problems[0]
  assert not Savi(load_config('synthetic', 'flow_tiny')).check_config(
      frozenset())
