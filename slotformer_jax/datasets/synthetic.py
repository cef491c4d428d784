"""An embedded OBJ3D-like synthetic video dataset (pybullet), stored as TFDS.

OBJ3D (G-SWM; SlotFormer appendix "Dataset Details") shows CLEVR-like scenes:
3 to 5 static objects, then a sphere launched from the front of the scene that
collides with them; the objects are large and all visible in the first frame.
This module reproduces that recipe so the whole stack runs without a
download: `sample_scene` draws a scene, `simulate_and_render` runs it in
pybullet and renders it with the TinyRenderer, `generate_video` is
deterministic per (seed, split, index), and `generate` writes the splits
into a folder named by every parameter (`SyntheticConfig`). The CLEVRER-like
and contact datasets reuse SHAPES / COLORS / SIZES.

Coordinates: world x right, y away from the camera, z up; metres, seconds.
Object k (1-based) in the masks is row k - 1 of every per-object array;
the launched sphere is the last real object; later rows are padding.
`data.with_flow_depth=True` adds exact depth and optical flow from the
simulator (off by default: the data and folder are those of before;
docs/datasets.md, "Optical flow and depth").
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pybullet
import tensorflow_datasets as tfds

from slotformer_jax import targets
from slotformer_jax.data import flow_depth
from slotformer_jax.data import sources
from slotformer_jax.datasets import base
from slotformer_jax.data.supersample import downsample_by_label
from slotformer_jax.data.supersample import downsample_rgb
from slotformer_jax.data.supersample import downsample_segmentation

# Bump whenever the generator's output changes for identical parameters: it is
# part of the cache folder name, so stale caches are never reused.
GENERATOR_VERSION = 1

# The TFDS builder's name: the family's folder under the data dir.
NAME = 'synthetic_obj3d'
SPLITS: tuple[str, ...] = ('train', 'val', 'test')

# What the stored ids mean: shapes[k], colors[k], sizes[k] index these.
SHAPES: tuple[str, ...] = ('cube', 'sphere', 'cylinder')
COLORS: tuple[str, ...] = (
    'gray', 'red', 'blue', 'green', 'brown', 'purple', 'cyan', 'yellow')
SIZES: tuple[str, ...] = ('small', 'large')


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
  """Generation parameters; together they identify a cached dataset.

  Attributes:
    resolution: (H, W) of the output frames.
    num_frames: T, frames per video.
    min_objects: minimum number of static objects per video.
    max_objects: maximum number of static objects (the launched sphere comes on
      top, so per-object arrays have ``max_objects + 1`` rows). Up to 7 fit
      the layout region comfortably; 8 is slow to place, 10 does not fit.
    seed: base seed; video ``i`` of split ``s`` uses ``(seed, s, i)``.
    num_train, num_val, num_test: videos per split (0 skips a split).
    supersample: render at ``supersample`` x the resolution and area-average
      (anti-aliasing); masks are downsampled by majority vote.
    object_scale: multiplies every object's size (larger objects cover more
      pixels, which matters at low resolution).
    distinct_colors: no two objects of a video share a colour (at most
      len(COLORS) objects).
    with_flow_depth: also store the optical flows, depth and the objects'
      orientations (the module docstring); part of the folder name only
      when set, so the default data are those of before the option.
  """

  resolution: tuple[int, int] = (64, 64)
  num_frames: int = 40
  min_objects: int = 3
  max_objects: int = 5
  seed: int = 0
  num_train: int = 1000
  num_val: int = 100
  num_test: int = 100
  supersample: int = 2
  object_scale: float = 1.0
  distinct_colors: bool = False
  with_flow_depth: bool = False

  def __post_init__(self):
    # Accept lists (e.g. from ml_collections) but store a hashable tuple.
    object.__setattr__(self, 'resolution', tuple(int(r) for r in self.resolution))
    if len(self.resolution) != 2 or min(self.resolution) < 8:
      raise ValueError(f'resolution must be (H, W) >= 8, got {self.resolution}')
    if self.num_frames < 1:
      raise ValueError(f'num_frames must be >= 1, got {self.num_frames}')
    if not 1 <= self.min_objects <= self.max_objects:
      raise ValueError('need 1 <= min_objects <= max_objects, got '
                       f'{self.min_objects}..{self.max_objects}')
    if self.max_objects + 1 > 254:
      raise ValueError('uint8 masks hold at most 254 objects')
    if min(self.num_train, self.num_val, self.num_test) < 0:
      raise ValueError('split sizes must be >= 0')
    if self.seed < 0:
      raise ValueError(f'seed must be >= 0, got {self.seed}')
    if self.supersample < 1:
      raise ValueError(f'supersample must be >= 1, got {self.supersample}')
    if self.distinct_colors and self.max_objects + 1 > len(COLORS):
      raise ValueError(f'distinct_colors allows at most {len(COLORS) - 1} '
                       f'static objects, got max_objects={self.max_objects}')
    if not 0.25 <= self.object_scale <= 2.0:
      raise ValueError(
          f'object_scale must be in [0.25, 2], got {self.object_scale}')

  @property
  def max_objects_total(self) -> int:
    """O: rows of the per-object arrays (static objects + launched sphere)."""
    return self.max_objects + 1

  def num_videos(self, split: str) -> int:
    return {'train': self.num_train, 'val': self.num_val,
            'test': self.num_test}[split]

  def params(self) -> dict[str, Any]:
    """The parameters as recorded and hashed: ``with_flow_depth`` only when
    set (the folder and metadata of the default data are those of before
    the option)."""
    params = dataclasses.asdict(self)
    if not self.with_flow_depth:
      del params['with_flow_depth']
    return params

  @property
  def slug(self) -> str:
    """A readable, unique folder name for these parameters (+ code version)."""
    h, w = self.resolution
    payload = json.dumps(
        {**self.params(), 'generator_version': GENERATOR_VERSION},
        sort_keys=True)
    digest = hashlib.sha256(payload.encode()).hexdigest()[:8]
    flow = '_fd' if self.with_flow_depth else ''
    return (f'r{h}x{w}_t{self.num_frames}_o{self.min_objects}-{self.max_objects}'
            f'_s{self.seed}_n{self.num_train}-{self.num_val}-{self.num_test}'
            f'_aa{self.supersample}{flow}_{digest}')



def config_from_data_config(data_config: Any) -> SyntheticConfig:
  """The generation parameters named by a data config (the dataclass's
  defaults for those it does not name)."""
  defaults = SyntheticConfig()
  values = {}
  for field in dataclasses.fields(SyntheticConfig):
    if field.name in data_config:
      # As the default's type (an int given for object_scale is a float):
      # the dataset's folder name hashes these values.
      kind = type(getattr(defaults, field.name))
      values[field.name] = kind(data_config[field.name])
  return SyntheticConfig(**values)


def dataset_dir(config: SyntheticConfig,
                data_dir: str | os.PathLike[str]) -> Path:
  """The TFDS version folder of ``config`` under cache root ``data_dir``."""
  return sources.generated_dir(data_dir, NAME, config.slug)


# CLEVR's palette (in the order of COLORS); green and brown are lifted a
# little because CLEVR's are so dark that, under TinyRenderer's flat
# lighting, they read as near-black at 32x32. The floor (FLOOR_RGB) is a
# lighter gray than the gray object.
COLOR_RGB: tuple[tuple[int, int, int], ...] = (
    (87, 87, 87),      # gray
    (173, 35, 35),     # red
    (42, 75, 215),     # blue
    (40, 140, 30),     # green
    (150, 90, 35),     # brown
    (129, 38, 192),    # purple
    (41, 208, 208),    # cyan
    (255, 238, 51),    # yellow
)
FLOOR_RGB: tuple[int, int, int] = (165, 165, 160)
# Radius of spheres/cylinders (cylinder height = 2 * radius). OBJ3D objects are
# larger than CLEVR's (0.35 / 0.7) relative to the frame; we get that mostly
# from a closer camera.
SIZE_RADII: tuple[float, ...] = (0.5, 0.8)  # by SIZES
# Cube half-side = radius * CUBE_SCALE (CLEVR uses 1/sqrt(2), which makes cubes
# look small next to spheres of the same nominal size).
CUBE_SCALE = 0.8

# --- physics (fixed, so a video is a pure function of its scene) -------------
PHYSICS_DT = 1.0 / 240.0          # bullet step [s]
SUBSTEPS_PER_FRAME = 12           # -> 20 frames per second of simulated time
GRAVITY = 9.81                    # [m / s^2]
LATERAL_FRICTION = 0.5            # cubes/cylinders stop ~0.5 s after a hit
# Bullet's rolling/spinning friction torque is coefficient * normal force, so a
# coefficient proportional to the radius gives every sphere the same rolling
# deceleration (~2 m/s^2 here): a hit sphere comes to rest within the video.
ROLLING_FRICTION_PER_RADIUS = 0.6
RESTITUTION = 0.6                 # lively object-object collisions
FLOOR_RESTITUTION = 0.0           # ... but nothing bounces off the floor
DENSITY = 1.0                     # mass = DENSITY * volume
SOLVER_ITERATIONS = 50

# --- scene layout ------------------------------------------------------------
STATIC_X_RANGE = (-2.1, 2.1)      # static objects: middle / back of the scene
STATIC_Y_RANGE = (-0.5, 2.2)
MIN_GAP = 0.25                    # between footprints of static objects [m]
LAUNCH_X_RANGE = (-1.5, 1.5)      # launched sphere starts at the front
LAUNCH_Y = -2.4
LAUNCH_SPEED_RANGE = (5.0, 7.0)   # [m/s]: reaches its target after ~10 frames
AIM_NOISE = 0.08                  # [rad] uniform noise around the exact aim
_MAX_LAYOUT_ATTEMPTS = 1000

# --- camera / light (CLEVR-like elevated front view, zoomed in as in OBJ3D) --
CAMERA_EYE = (0.0, -8.5, 7.0)
CAMERA_TARGET = (0.0, 1.2, 0.0)
CAMERA_FOV_DEG = 32.0             # vertical field of view
CAMERA_NEAR, CAMERA_FAR = 0.5, 60.0
LIGHT_DIRECTION = (-3.0, -5.0, 10.0)
LIGHT_AMBIENT, LIGHT_DIFFUSE, LIGHT_SPECULAR = 0.55, 0.55, 0.05
FLOOR_HALF_EXTENT = 40.0          # large enough that the camera never sees sky

@dataclasses.dataclass(frozen=True)
class Scene:
  """The initial state of one video; N = static objects + 1 launched sphere.

  Attributes:
    shapes: int32 [N] index into SHAPES; the last entry is the launched sphere.
    colors: int32 [N] index into COLORS.
    sizes: int32 [N] index into SIZES.
    xy: float64 [N, 2] initial ground position of each object.
    yaw: float64 [N] initial rotation about z [rad].
    launch_velocity: float64 [2] initial ground velocity of the sphere [m/s].
  """

  shapes: np.ndarray
  colors: np.ndarray
  sizes: np.ndarray
  xy: np.ndarray
  yaw: np.ndarray
  launch_velocity: np.ndarray

  @property
  def num_objects(self) -> int:
    return int(self.shapes.shape[0])


def video_rng(seed: int, split: str, index: int) -> np.random.Generator:
  """The generator of video ``index`` of ``split``; independent across videos."""
  return np.random.default_rng([seed, SPLITS.index(split), index])


def _footprint_radius(shape: int, radius: float) -> float:
  """Radius of the circle covering the object's ground footprint (any yaw)."""
  if SHAPES[shape] == 'cube':
    return radius * CUBE_SCALE * np.sqrt(2.0)
  return radius


def sample_scene(rng: np.random.Generator, config: SyntheticConfig) -> Scene:
  """Samples static objects without overlap, then the launched sphere.

  Placement is rejection sampling in the middle/back of the scene; if a layout
  gets stuck (rare with up to ~6 objects) it restarts from scratch, which
  keeps the result a pure function of ``rng``'s state.

  Raises:
    ValueError: if the objects do not fit (``max_objects`` too large).
  """
  num_static = int(rng.integers(config.min_objects, config.max_objects + 1))
  for _ in range(_MAX_LAYOUT_ATTEMPTS):
    shapes = rng.integers(0, len(SHAPES), num_static)
    sizes = rng.integers(0, len(SIZES), num_static)
    placed: list[tuple[float, float, float]] = []   # (x, y, footprint radius)
    for shape, size in zip(shapes, sizes):
      footprint = _footprint_radius(
          int(shape), SIZE_RADII[size] * config.object_scale)
      for _ in range(200):
        x = rng.uniform(*STATIC_X_RANGE)
        y = rng.uniform(*STATIC_Y_RANGE)
        if all(np.hypot(x - px, y - py) > footprint + pr + MIN_GAP
               for px, py, pr in placed):
          placed.append((x, y, footprint))
          break
      else:
        break
    if len(placed) == num_static:
      break
  else:
    raise ValueError(f'could not place {num_static} static objects without '
                     'overlap; use a smaller max_objects')
  if config.distinct_colors:
    colors = rng.permutation(len(COLORS))[:num_static + 1]
  else:
    colors = rng.integers(0, len(COLORS), num_static + 1)
  yaw = rng.uniform(0.0, 2.0 * np.pi, num_static + 1)
  launch_size = rng.integers(0, len(SIZES))
  start = np.array([rng.uniform(*LAUNCH_X_RANGE), LAUNCH_Y])
  # Aim (roughly) at one static object so that most videos have a collision.
  target = np.array(placed[int(rng.integers(0, num_static))][:2])
  direction = target - start
  angle = np.arctan2(direction[1], direction[0]) + rng.uniform(-AIM_NOISE,
                                                               AIM_NOISE)
  speed = rng.uniform(*LAUNCH_SPEED_RANGE)
  return Scene(
      shapes=np.append(shapes, SHAPES.index('sphere')).astype(np.int32),
      colors=colors.astype(np.int32),
      sizes=np.append(sizes, launch_size).astype(np.int32),
      xy=np.concatenate([np.array([p[:2] for p in placed]), start[None]], 0),
      yaw=yaw,
      launch_velocity=speed * np.array([np.cos(angle), np.sin(angle)]),
  )


def _rgba(rgb: Sequence[int]) -> list[float]:
  return [c / 255.0 for c in rgb] + [1.0]


def _create_object(client: int, shape: int, radius: float, color: int,
                   xy: np.ndarray, yaw: float) -> int:
  """Adds one resting object to the pybullet world; returns its body id."""
  rgba = _rgba(COLOR_RGB[color])
  name = SHAPES[shape]
  if name == 'cube':
    half = radius * CUBE_SCALE
    col = pybullet.createCollisionShape(
        pybullet.GEOM_BOX, halfExtents=[half] * 3, physicsClientId=client)
    vis = pybullet.createVisualShape(
        pybullet.GEOM_BOX, halfExtents=[half] * 3, rgbaColor=rgba,
        physicsClientId=client)
    height, volume = half, 8.0 * half**3
  elif name == 'sphere':
    col = pybullet.createCollisionShape(
        pybullet.GEOM_SPHERE, radius=radius, physicsClientId=client)
    vis = pybullet.createVisualShape(
        pybullet.GEOM_SPHERE, radius=radius, rgbaColor=rgba,
        physicsClientId=client)
    height, volume = radius, 4.0 / 3.0 * np.pi * radius**3
  else:
    col = pybullet.createCollisionShape(
        pybullet.GEOM_CYLINDER, radius=radius, height=2 * radius,
        physicsClientId=client)
    vis = pybullet.createVisualShape(
        pybullet.GEOM_CYLINDER, radius=radius, length=2 * radius,
        rgbaColor=rgba, physicsClientId=client)
    height, volume = radius, 2.0 * np.pi * radius**3
  body = pybullet.createMultiBody(
      baseMass=DENSITY * volume, baseCollisionShapeIndex=col,
      baseVisualShapeIndex=vis, basePosition=[float(xy[0]), float(xy[1]), height],
      baseOrientation=pybullet.getQuaternionFromEuler([0.0, 0.0, float(yaw)]),
      physicsClientId=client)
  pybullet.changeDynamics(
      body, -1, lateralFriction=LATERAL_FRICTION,
      rollingFriction=ROLLING_FRICTION_PER_RADIUS * radius,
      spinningFriction=ROLLING_FRICTION_PER_RADIUS * radius,
      restitution=RESTITUTION, linearDamping=0.0, angularDamping=0.0,
      physicsClientId=client)
  return body


def _create_floor(client: int) -> int:
  """A static plane (collision) drawn as a huge flat box (TinyRenderer)."""
  col = pybullet.createCollisionShape(pybullet.GEOM_PLANE,
                                      physicsClientId=client)
  vis = pybullet.createVisualShape(
      pybullet.GEOM_BOX, halfExtents=[FLOOR_HALF_EXTENT, FLOOR_HALF_EXTENT, 0.01],
      rgbaColor=_rgba(FLOOR_RGB), visualFramePosition=[0.0, 0.0, -0.01],
      physicsClientId=client)
  floor = pybullet.createMultiBody(
      baseMass=0.0, baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
      physicsClientId=client)
  pybullet.changeDynamics(
      floor, -1, lateralFriction=LATERAL_FRICTION, rollingFriction=0.0,
      spinningFriction=0.0, restitution=FLOOR_RESTITUTION,
      physicsClientId=client)
  return floor


def boxes_from_segmentation(
    segmentations: np.ndarray, num_slots: int) -> tuple[np.ndarray, np.ndarray]:
  """Tight boxes of every object id from instance masks.

  Args:
    segmentations: integer [T, H, W]; 0 = background, k = object k (1-based).
    num_slots: O, number of object rows to return (ids 1..O).

  Returns:
    boxes: float32 [T, O, 4] normalised (ymin, xmin, ymax, xmax) in [0, 1];
      pixel edges, so a box covering rows 2..5 of H=8 has ymin=2/8, ymax=6/8.
      Rows of objects without any pixel are zeros.
    visible: bool [T, O], whether the object has any pixel in that frame.
  """
  _, h, w = segmentations.shape
  onehot = segmentations[..., None] == np.arange(1, num_slots + 1,
                                                 dtype=segmentations.dtype)
  rows = onehot.any(axis=2)   # [T, H, O]
  cols = onehot.any(axis=1)   # [T, W, O]
  visible = rows.any(axis=1)  # [T, O]
  ymin = rows.argmax(axis=1)
  ymax = h - rows[:, ::-1].argmax(axis=1)
  xmin = cols.argmax(axis=1)
  xmax = w - cols[:, ::-1].argmax(axis=1)
  boxes = np.stack([ymin / h, xmin / w, ymax / h, xmax / w], axis=-1)
  boxes = np.where(visible[..., None], boxes, 0.0).astype(np.float32)
  return boxes, visible


def _camera_matrices(height: int, width: int) -> tuple[list[float], list[float]]:
  view = pybullet.computeViewMatrix(
      cameraEyePosition=CAMERA_EYE, cameraTargetPosition=CAMERA_TARGET,
      cameraUpVector=[0.0, 0.0, 1.0])
  projection = pybullet.computeProjectionMatrixFOV(
      fov=CAMERA_FOV_DEG, aspect=width / height, nearVal=CAMERA_NEAR,
      farVal=CAMERA_FAR)
  return view, projection


def render_frame(client: int, view: list[float], projection: list[float],
                 height: int, width: int, ss: int, lut: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
  """One frame of every embedded family: TinyRenderer at ``ss`` times the
  size, then averaged down.

  No shadows: TinyRenderer's shadow map drew a dark wedge across the floor
  and hardly any object shadows, at twice the rendering cost.

  Returns:
    rgb: uint8 [height, width, 3].
    segmentation: [height, width], ``lut[body id + 1]`` of the pixels
      (pybullet's background is -1), downsampled.
  """
  rgb, seg, _ = _render(client, view, projection, height, width, ss, lut)
  return rgb, seg


def _render(client: int, view: list[float], projection: list[float],
            height: int, width: int, ss: int, lut: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
  """`render_frame`'s (rgb, segmentation) and the samples they come from:
  {'ids': lut ids [height * ss, width * ss], 'depth_buffer': float64 of
  the same size, in [0, 1]}."""
  _, _, rgba, depth, seg = pybullet.getCameraImage(
      width * ss, height * ss, viewMatrix=view, projectionMatrix=projection,
      lightDirection=LIGHT_DIRECTION, lightColor=[1.0, 1.0, 1.0],
      shadow=0, lightAmbientCoeff=LIGHT_AMBIENT,
      lightDiffuseCoeff=LIGHT_DIFFUSE, lightSpecularCoeff=LIGHT_SPECULAR,
      renderer=pybullet.ER_TINY_RENDERER, physicsClientId=client)
  rgb = np.asarray(rgba, np.uint8).reshape(height * ss, width * ss, 4)
  seg = lut[np.asarray(seg, np.int64).reshape(height * ss, width * ss) + 1]
  samples = {'ids': seg, 'depth_buffer': np.asarray(
      depth, np.float64).reshape(height * ss, width * ss)}
  return (downsample_rgb(rgb[..., :3], ss),
          downsample_segmentation(seg, ss), samples)


# TinyRenderer samples pixel (i, j) of a frame at its lower left corner, row
# i + 1 and column j in coordinates where pixel i spans [i, i + 1) (measured:
# the floor's pixels back-project onto the floor to 1e-7 so, and to 0.07-0.14
# units off at the pixel's centre or upper corner;
# tests/datasets/test_synthetic.py checks it).
SAMPLE_OFFSET = (1.0, 0.0)


@dataclasses.dataclass(frozen=True)
class Camera:
  """The renderer's camera as matrices: world points <-> frame pixels.

  Attributes:
    matrix: float64 [4, 4], projection @ view (OpenGL clip coordinates).
    height, width: the frame (H, W) whose pixels `project` counts in.
  """

  matrix: np.ndarray
  height: int
  width: int

  @classmethod
  def of_frames(cls, height: int, width: int) -> 'Camera':
    view, projection = _camera_matrices(height, width)
    matrix = (np.asarray(projection, np.float64).reshape(4, 4).T
              @ np.asarray(view, np.float64).reshape(4, 4).T)
    return cls(matrix=matrix, height=height, width=width)

  def project(self, points: np.ndarray) -> np.ndarray:
    """World points [..., 3] -> (row, column) [..., 2] in pixels of the
    frame (pixel i spans [i, i + 1))."""
    points = np.asarray(points, np.float64)
    clip = points @ self.matrix[:3, :3].T + self.matrix[:3, 3]
    w = points @ self.matrix[3, :3] + self.matrix[3, 3]
    ndc_x, ndc_y = clip[..., 0] / w, clip[..., 1] / w
    return np.stack([(1.0 - ndc_y) * 0.5 * self.height,
                     (ndc_x + 1.0) * 0.5 * self.width], axis=-1)

  def back_project(self, depth_buffer: np.ndarray) -> np.ndarray:
    """A rendered depth buffer [h, w] in [0, 1] (any multiple of the
    frame) -> the world point each pixel samples, float64 [h, w, 3]."""
    h, w = depth_buffer.shape
    rows = (np.arange(h)[:, None] + SAMPLE_OFFSET[0]) / h
    cols = (np.arange(w)[None, :] + SAMPLE_OFFSET[1]) / w
    ndc = np.stack(np.broadcast_arrays(
        cols * 2.0 - 1.0, 1.0 - rows * 2.0, depth_buffer * 2.0 - 1.0,
        np.ones_like(depth_buffer)), axis=-1)
    world = ndc @ np.linalg.inv(self.matrix).T
    return world[..., :3] / world[..., 3:]


def rigid_flow(points: np.ndarray, ids: np.ndarray,
               poses: tuple[np.ndarray, np.ndarray],
               other: tuple[np.ndarray, np.ndarray], camera: Camera
               ) -> np.ndarray:
  """Optical flow of the samples of one frame to another: float64 [h, w, 2]
  (delta row, delta column) in pixels of the camera's frame.

  Args:
    points: world points [h, w, 3] the samples see.
    ids: [h, w] 0 for the static floor (no flow), k for object k.
    poses, other: (positions [N, 3], rotation matrices [N, 3, 3]) of the
      objects in this frame and the other one (row k - 1: object k).
    camera: projects both.
  """
  flow = np.zeros(points.shape[:2] + (2,), np.float64)
  here = camera.project(points)
  for k in np.unique(ids):
    if k == 0:
      continue
    mask = ids == k
    position, rotation = poses[0][k - 1], poses[1][k - 1]
    local = (points[mask] - position) @ rotation  # R^T (p - x), row-wise
    moved = local @ other[1][k - 1].T + other[0][k - 1]
    flow[mask] = camera.project(moved) - here[mask]
  return flow


def simulate_and_render(scene: Scene, config: SyntheticConfig
                        ) -> dict[str, np.ndarray]:
  """Simulates ``scene`` for ``config.num_frames`` frames and renders them.

  Frame 0 is the initial state; each following frame is SUBSTEPS_PER_FRAME
  fixed bullet steps later. Each call uses its own pybullet DIRECT client, so
  calls are independent (and safe in worker processes).

  Returns:
    A dict (O = config.max_objects_total, N = scene.num_objects):
      video: uint8 [T, H, W, 3].
      segmentations: uint8 [T, H, W]; 0 background, k object k.
      boxes: float32 [T, O, 4]; visible: bool [T, O] (see
        :func:`boxes_from_segmentation`).
      positions: float32 [T, O, 3] world position of each object's centre.
      num_objects: int32 [] = N.
      shapes, colors, sizes: int32 [O]; -1 for padding rows.
  """
  height, width = config.resolution
  ss = config.supersample
  num_slots = config.max_objects_total
  n = scene.num_objects
  if n > num_slots:
    raise ValueError(f'scene has {n} objects but config allows {num_slots}')
  client = pybullet.connect(pybullet.DIRECT)
  try:
    pybullet.setPhysicsEngineParameter(
        fixedTimeStep=PHYSICS_DT, numSubSteps=0,
        numSolverIterations=SOLVER_ITERATIONS,
        deterministicOverlappingPairs=1, physicsClientId=client)
    pybullet.setGravity(0.0, 0.0, -GRAVITY, physicsClientId=client)
    floor = _create_floor(client)
    bodies = [
        _create_object(client, int(scene.shapes[i]),
                       SIZE_RADII[scene.sizes[i]] * config.object_scale,
                       int(scene.colors[i]),
                       scene.xy[i], float(scene.yaw[i])) for i in range(n)
    ]
    # Launch the sphere already rolling (w = z x v / r) so it does not skid.
    vx, vy = (float(v) for v in scene.launch_velocity)
    radius = SIZE_RADII[scene.sizes[-1]] * config.object_scale
    pybullet.resetBaseVelocity(
        bodies[-1], linearVelocity=[vx, vy, 0.0],
        angularVelocity=[-vy / radius, vx / radius, 0.0],
        physicsClientId=client)
    # pybullet ids (-1 = nothing hit) -> our ids; floor and sky are 0.
    lut = np.zeros(max(bodies + [floor]) + 2, np.uint8)
    for k, body in enumerate(bodies, start=1):
      lut[body + 1] = k
    view, projection = _camera_matrices(height, width)
    frames, segs, samples = [], [], []
    positions = np.zeros((config.num_frames, num_slots, 3), np.float32)
    # Exact poses (float64) for the flows: positions and quaternions.
    poses = np.zeros((config.num_frames, n, 7), np.float64)
    for t in range(config.num_frames):
      rgb, seg, sample = _render(client, view, projection, height, width, ss,
                                 lut)
      frames.append(rgb)
      segs.append(seg)
      if config.with_flow_depth:
        samples.append(sample)
      for k, body in enumerate(bodies):
        position, orientation = pybullet.getBasePositionAndOrientation(
            body, physicsClientId=client)
        positions[t, k] = position
        poses[t, k] = (*position, *orientation)
      if t + 1 < config.num_frames:
        for _ in range(SUBSTEPS_PER_FRAME):
          pybullet.stepSimulation(physicsClientId=client)
  finally:
    pybullet.disconnect(physicsClientId=client)
  segmentations = np.stack(segs)
  boxes, visible = boxes_from_segmentation(segmentations, num_slots)

  def pad(values: np.ndarray) -> np.ndarray:
    out = np.full((num_slots,), -1, np.int32)
    out[:n] = values
    return out

  example = {
      'video': np.stack(frames),
      'segmentations': segmentations,
      'boxes': boxes,
      'visible': visible,
      'positions': positions,
      'num_objects': np.array(n, np.int32),
      'shapes': pad(scene.shapes),
      'colors': pad(scene.colors),
      'sizes': pad(scene.sizes),
  }
  if config.with_flow_depth:
    example.update(flows_and_depth(samples, segmentations, poses, config))
  return example


def flows_and_depth(samples: Sequence[dict[str, np.ndarray]],
                    segmentations: np.ndarray, poses: np.ndarray,
                    config: SyntheticConfig) -> dict[str, np.ndarray]:
  """The stored flows and depth of a video (data/flow_depth.py's encoding)
  and its objects' orientations, from the rendered samples of each frame
  and the objects' poses.

  Each is computed per sample (supersampled), then a pixel takes the mean
  of its samples that show the surface its mask shows (the vote of
  `downsample_segmentation`; `downsample_by_label`), so depth and flow at
  an object's edge are the object's or the floor's, as its id says.

  Args:
    samples: per frame {'ids', 'depth_buffer'} of `_render`.
    segmentations: uint8 [T, H, W], the voted ids.
    poses: float64 [T, N, 7] position and quaternion (x, y, z, w) of each
      object (row k - 1: object k).
    config: the generation parameters (resolution, supersample, rows).

  Returns:
    forward_flow, backward_flow: uint16 [T, H, W, 2]; depth: uint16 [T, H,
    W, 1]; each with its '<name>_range' float32 [2]; orientations: float32
    [T, O, 4] (x, y, z, w), zeros for padding rows.
  """
  height, width = config.resolution
  ss = config.supersample
  camera = Camera.of_frames(height, width)
  eye = np.asarray(CAMERA_EYE, np.float64)
  num_frames, n = poses.shape[:2]
  rotations = np.asarray([
      [np.asarray(pybullet.getMatrixFromQuaternion(q[3:]), np.float64
                  ).reshape(3, 3) for q in frame] for frame in poses]
                         ).reshape(num_frames, n, 3, 3)
  pose = [(poses[t, :, :3], rotations[t]) for t in range(num_frames)]
  distance, forward, backward = [], [], []
  for t, sample in enumerate(samples):
    points = camera.back_project(sample['depth_buffer'])
    ids = sample['ids']
    voted = segmentations[t]
    still = np.zeros(ids.shape + (2,))

    def down(values, ids=ids, voted=voted):
      return downsample_by_label(values, ids, voted, ss)

    distance.append(down(np.linalg.norm(points - eye, axis=-1)[..., None]))
    forward.append(down(still if t + 1 == num_frames else rigid_flow(
        points, ids, pose[t], pose[t + 1], camera)))
    backward.append(down(still if t == 0 else rigid_flow(
        points, ids, pose[t], pose[t - 1], camera)))
  out = {}
  for name, values in ((flow_depth.FORWARD_FLOW, forward),
                       (flow_depth.BACKWARD_FLOW, backward),
                       (flow_depth.DEPTH, distance)):
    out[name], out[flow_depth.range_field(name)] = flow_depth.encode(
        np.stack(values))
  orientations = np.zeros((num_frames, config.max_objects_total, 4),
                          np.float32)
  orientations[:, :n] = poses[..., 3:]
  out['orientations'] = orientations
  return out


def generate_video(config: SyntheticConfig, split: str, index: int
                   ) -> dict[str, np.ndarray]:
  """Video ``index`` of ``split``: a pure function of (config, split, index).

  Returns the dict of :func:`simulate_and_render` plus ``index``: int32 [].
  """
  if split not in SPLITS:
    raise ValueError(f'split must be one of {SPLITS}, got {split!r}')
  scene = sample_scene(video_rng(config.seed, split, index), config)
  example = simulate_and_render(scene, config)
  example['index'] = np.array(index, np.int32)
  return example


# ----------------------------------------------------------------------------
# TFDS storage
# ----------------------------------------------------------------------------


DESCRIPTION = ('OBJ3D-like synthetic videos rendered with pybullet: static '
               'CLEVR objects hit by a launched sphere.')


def features(g: SyntheticConfig) -> tfds.features.FeaturesDict:
  """The fields of :func:`generate_video` (tensors stored as raw bytes)."""
  h, w = g.resolution
  t, o = g.num_frames, g.max_objects_total
  tensor = base.tensor
  stored = {}
  if g.with_flow_depth:
    for name, channels in flow_depth.STORED.items():
      stored[name] = tensor((t, h, w, channels), np.uint16)
      stored[flow_depth.range_field(name)] = tensor((2,), np.float32)
    stored['orientations'] = tensor((t, o, 4), np.float32)
  return tfds.features.FeaturesDict({
      **stored,
      'video': tensor((t, h, w, 3), np.uint8),
      'segmentations': tensor((t, h, w), np.uint8),
      'boxes': tensor((t, o, 4), np.float32),
      'visible': tensor((t, o), np.bool_),
      'positions': tensor((t, o, 3), np.float32),
      'num_objects': tfds.features.Scalar(np.int32),
      'shapes': tensor((o,), np.int32),
      'colors': tensor((o,), np.int32),
      'sizes': tensor((o,), np.int32),
      'index': tfds.features.Scalar(np.int32),
  })


def generate(config: SyntheticConfig, out: base.Output) -> Path:
  """Generates the dataset into the cache unless it is already there.

  Args:
    config: generation parameters; they determine the folder
      ``<data_dir>/synthetic_obj3d/<config.slug>/2.0.0``.
    out: what to write with (the data stage's).

  Returns:
    The TFDS version folder, readable with ``tfds.builder_from_directory``.
  """
  path = dataset_dir(config, out.data_dir)
  splits = [s for s in SPLITS if config.num_videos(s) > 0]
  # One generator per dataset: processes sharing a data dir make it once.
  return out.tfds_folder(
      path, name=NAME, features=features(config), description=DESCRIPTION,
      split_sizes={s: config.num_videos(s) for s in splits},
      make=functools.partial(generate_video, config),
      metadata={'generation': json.loads(json.dumps(config.params()))},
      lock=f'the synthetic dataset {path}')


def _generate_them(dataset: base.Generated, data_config: Any) -> str:
  del dataset
  return ('the OBJ3D-like videos hold flow and depth only when generated '
          f'with them: set data.with_flow_depth=True (configs/synthetic.py'
          f':flow and :flow_tiny do; data.name={data_config.name!r})')


DATASET = base.register(base.Generated(
    names=('synthetic',), label='OBJ3D-like', splits=SPLITS,
    features=functools.partial(features, SyntheticConfig()),
    what='the synthetic dataset', parameters=config_from_data_config,
    folder=dataset_dir, generate=generate,
    split_sizes=lambda config: {s: config.num_videos(s) for s in SPLITS},
    stored=features,
    field_fixes={field: _generate_them for field in (
        targets.FLOW.field, targets.DEPTH.field, flow_depth.BACKWARD_FLOW,
        flow_depth.FORWARD_FLOW)}))
