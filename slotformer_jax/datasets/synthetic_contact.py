"""Embedded Physion-style object-contact-prediction (OCP) videos (pybullet).

Physion's OCP task (Bear et al., 2021; SlotFormer Section 4.3) shows a red
*agent* and a yellow *patient* among distractors and asks whether the two
touch at any time of the full video, given only its first part. This module
builds it (``data.name='synthetic_contact'``) on the OBJ3D-like scenes of
:mod:`slotformer_jax.datasets.synthetic`, in a folder named by
:class:`ContactConfig`. The label is a contact at any physics substep; splits
are exactly balanced, and a contact always starts after the observed frames,
so the observed part alone cannot answer. Splits as Physion: ``train`` (the
dynamics), ``readout_train``, ``readout_val``, ``readout_test``. A video is a
pure function of ``(config, split, index)``. The scenarios (front, side,
bank shot) and the rules: docs/downstream.md, "Physion-style object contact
prediction".
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pybullet
import tensorflow_datasets as tfds

from slotformer_jax.data import sources
from slotformer_jax.datasets import base
from slotformer_jax.datasets import synthetic
from slotformer_jax.datasets.synthetic import COLORS
from slotformer_jax.datasets.synthetic import SHAPES
from slotformer_jax.datasets.synthetic import SIZES

SYNTHETIC_VERSION = synthetic.GENERATOR_VERSION
GENERATOR_VERSION = 1

NAME = 'synthetic_contact'
SPLITS: tuple[str, ...] = ('train', 'readout_train', 'readout_val',
                           'readout_test')
# Where the agent starts: the front (along the camera's view) or the side.
LAUNCH_SIDES = ('front', 'side')
# 'direct': the agent is aimed at (or beside) the patient, so its heading in
# the observed frames decides the label. 'bank': it is aimed at a *bumper*
# (object row 1) that stands off the line to the patient, and reaches the
# patient (or not) only after bouncing off it, after the observed frames:
# the observed motion alone no longer answers, the collision decides.
SCENARIOS = ('direct', 'bank')


@dataclasses.dataclass(frozen=True)
class ContactConfig:
  """Generation parameters; together they identify a cached dataset.

  Attributes:
    resolution: (H, W) of the output frames.
    num_frames: T, frames per video (20 per simulated second).
    observed_frames: frames a model observes; contacts start after them.
    min_distractors, max_distractors: other static objects per video.
    seed: base seed; video ``i`` of split ``s`` uses ``(seed, s, i)``.
    num_train, num_readout_train, num_readout_val, num_readout_test: videos
      per split.
    supersample: anti-aliasing factor (see synthetic.py).
    object_scale: multiplies every object's size.
    launch_side: where the agent starts: 'front' (the camera's side, moving
      along the view direction) or 'side' (the left / right edge, moving
      across it).
  """

  resolution: tuple[int, int] = (64, 64)
  num_frames: int = 24
  observed_frames: int = 8
  min_distractors: int = 1
  max_distractors: int = 2
  seed: int = 0
  num_train: int = 1000
  num_readout_train: int = 400
  num_readout_val: int = 100
  num_readout_test: int = 200
  supersample: int = 2
  object_scale: float = 1.0
  launch_side: str = 'front'
  scenario: str = 'direct'

  def __post_init__(self):
    object.__setattr__(self, 'resolution',
                       tuple(int(r) for r in self.resolution))
    if len(self.resolution) != 2 or min(self.resolution) < 8:
      raise ValueError(f'resolution must be (H, W) >= 8, got {self.resolution}')
    if not 1 <= self.observed_frames < self.num_frames:
      raise ValueError('need 1 <= observed_frames < num_frames, got '
                       f'{self.observed_frames}, {self.num_frames}')
    if not 0 <= self.min_distractors <= self.max_distractors <= 4:
      raise ValueError('need 0 <= min_distractors <= max_distractors <= 4')
    if min(self.num_videos(s) for s in SPLITS) < 0 or self.seed < 0:
      raise ValueError('split sizes and seed must be >= 0')
    if self.launch_side not in LAUNCH_SIDES:
      raise ValueError(f'launch_side must be one of {LAUNCH_SIDES}, got '
                       f'{self.launch_side!r}')
    if self.scenario not in SCENARIOS:
      raise ValueError(f'scenario must be one of {SCENARIOS}, got '
                       f'{self.scenario!r}')
    if self.scenario == 'bank' and (self.launch_side != 'side'
                                    or self.min_distractors < 1):
      raise ValueError("scenario='bank' needs launch_side='side' and "
                       'min_distractors >= 1 (the bumper is a distractor)')

  @property
  def max_objects_total(self) -> int:
    """O: rows of the per-object arrays (patient + distractors + agent)."""
    return self.max_distractors + 2

  def num_videos(self, split: str) -> int:
    return {'train': self.num_train, 'readout_train': self.num_readout_train,
            'readout_val': self.num_readout_val,
            'readout_test': self.num_readout_test}[split]

  @property
  def slug(self) -> str:
    h, w = self.resolution
    fields = dataclasses.asdict(self)
    if fields['launch_side'] == 'front':  # the datasets made before the option
      del fields['launch_side']
    if fields['scenario'] == 'direct':  # ... and before this one
      del fields['scenario']
    payload = json.dumps(
        {**fields, 'generator_version': GENERATOR_VERSION,
         'synthetic_version': SYNTHETIC_VERSION}, sort_keys=True)
    digest = hashlib.sha256(payload.encode()).hexdigest()[:8]
    return (f'r{h}x{w}_t{self.num_frames}_obs{self.observed_frames}'
            f'_d{self.min_distractors}-{self.max_distractors}_s{self.seed}'
            f'_n{self.num_train}-{self.num_readout_train}-'
            f'{self.num_readout_val}-{self.num_readout_test}_{digest}')



def config_from_data_config(data_config: Any) -> ContactConfig:
  """The generation parameters named in a run's ``config.data``."""
  fields = {f.name for f in dataclasses.fields(ContactConfig)}
  return ContactConfig(**{key: data_config[key] for key in fields
                          if key in data_config})


def dataset_dir(config: ContactConfig,
                data_dir: str | os.PathLike[str]) -> Path:
  """The TFDS version folder of ``config`` under cache root ``data_dir``."""
  return sources.generated_dir(data_dir, NAME, config.slug)


AGENT_COLOR = COLORS.index('red')
PATIENT_COLOR = COLORS.index('yellow')
DISTRACTOR_COLORS = tuple(i for i in range(len(COLORS))
                          if i not in (AGENT_COLOR, PATIENT_COLOR))

# The patient stands in the middle of the scene, distractors around it.
PATIENT_X_RANGE = (-1.2, 1.2)
PATIENT_Y_RANGE = (0.3, 1.6)
# Slower than OBJ3D's launch (5-7 m/s) so that the agent reaches the patient
# after the observed window.
AGENT_SPEED_RANGE = (3.0, 4.5)
# Positives aim at the patient within +-HIT_NOISE; negatives aim beside it,
# MISS_ANGLE_RANGE away, so they are near misses rather than trivial ones.
HIT_NOISE = 0.05                  # [rad]
MISS_ANGLE_RANGE = (0.15, 0.45)   # [rad]
# 'side' launches start this far [m] from the scene's centre line, on the
# side away from the patient (the longer run keeps onsets after the observed
# frames), at the patient's depth +- SIDE_LAUNCH_DEPTH_NOISE.
SIDE_LAUNCH_X = 2.6
SIDE_LAUNCH_DEPTH_NOISE = 0.3
# 'bank' geometry: the bumper stands BANK_GAP [m] (surface to surface) from
# the patient, in a direction BANK_ANGLE [rad] off the line from the patient
# back to the agent's start (to either side); the agent aims at the bumper's
# centre with a sideways offset of up to BANK_OFFSET * (sum of the two
# radii), i.e. anything from a head-on to a grazing hit. Whether the bounce
# reaches the patient is decided by simulation.
BANK_GAP = (0.3, 1.2)
BANK_ANGLE = (0.5, 1.3)
BANK_OFFSET = 0.9
BANK_SPEED_RANGE = (3.0, 4.5)     # [m/s]: as AGENT_SPEED_RANGE
# Surfaces closer than this [m] touch (bullet keeps a small collision margin).
CONTACT_DISTANCE = 1e-3
_MAX_SCENE_ATTEMPTS = 200


def video_rng(seed: int, split: str, index: int) -> np.random.Generator:
  return np.random.default_rng([seed, 1000 + SPLITS.index(split), index])


def _place(rng: np.random.Generator, placed: list[tuple[float, float, float]],
           footprint: float, x_range: tuple[float, float],
           y_range: tuple[float, float]) -> tuple[float, float] | None:
  for _ in range(200):
    x, y = rng.uniform(*x_range), rng.uniform(*y_range)
    if all(np.hypot(x - px, y - py) > footprint + pr + synthetic.MIN_GAP
           for px, py, pr in placed):
      return x, y
  return None


def sample_contact_scene(rng: np.random.Generator, config: ContactConfig,
                         want_contact: bool) -> synthetic.Scene:
  """One candidate scene; the agent aims at (or beside) the patient.

  Whether the agent really touches the patient is decided by simulation
  (:func:`simulate`), not by this aim.
  """
  if config.scenario == 'bank':
    return _sample_bank_scene(rng, config)
  scale = config.object_scale
  num_distractors = int(rng.integers(config.min_distractors,
                                     config.max_distractors + 1))
  side = config.launch_side == 'side'
  if side:  # its size first: the distractors keep clear of its start
    agent_size = int(rng.integers(0, len(SIZES)))
    agent_radius = synthetic.SIZE_RADII[agent_size] * scale
  for _ in range(_MAX_SCENE_ATTEMPTS):
    shapes = rng.integers(0, len(SHAPES), num_distractors + 1)
    sizes = rng.integers(0, len(SIZES), num_distractors + 1)
    placed: list[tuple[float, float, float]] = []
    keep_clear: list[tuple[float, float, float]] = []
    for k, (shape, size) in enumerate(zip(shapes, sizes)):
      footprint = synthetic._footprint_radius(  # pylint: disable=protected-access
          int(shape), synthetic.SIZE_RADII[size] * scale)
      ranges = ((PATIENT_X_RANGE, PATIENT_Y_RANGE) if k == 0 else
                (synthetic.STATIC_X_RANGE, synthetic.STATIC_Y_RANGE))
      xy = _place(rng, placed + keep_clear, footprint, *ranges)
      if xy is None:
        break
      placed.append((*xy, footprint))
      if side and k == 0:  # the start depends on where the patient is
        start = _side_start(rng, xy)
        if np.hypot(*(start - np.asarray(xy))) <= (
            footprint + agent_radius + synthetic.MIN_GAP):
          break  # the agent would start inside the patient: re-sample
        keep_clear = [(*start, agent_radius)]
    if len(placed) == num_distractors + 1:
      break
  else:
    raise ValueError('could not place the objects; use fewer distractors')
  colors = _scene_colors(rng, num_distractors)
  if not side:  # (draw order of the datasets made before launch_side)
    start = np.array([rng.uniform(*synthetic.LAUNCH_X_RANGE),
                      synthetic.LAUNCH_Y])
  direction = np.array(placed[0][:2]) - start
  angle = np.arctan2(direction[1], direction[0])
  if want_contact:
    angle += rng.uniform(-HIT_NOISE, HIT_NOISE)
  else:
    angle += rng.choice([-1.0, 1.0]) * rng.uniform(*MISS_ANGLE_RANGE)
  speed = rng.uniform(*AGENT_SPEED_RANGE)
  if not side:
    agent_size = int(rng.integers(0, len(SIZES)))
  return synthetic.Scene(
      shapes=np.append(shapes, SHAPES.index('sphere')).astype(
          np.int32),
      colors=colors.astype(np.int32),
      sizes=np.append(sizes, agent_size).astype(np.int32),
      xy=np.concatenate([np.array([p[:2] for p in placed]), start[None]], 0),
      yaw=rng.uniform(0.0, 2.0 * np.pi, num_distractors + 2),
      launch_velocity=speed * np.array([np.cos(angle), np.sin(angle)]))


def _scene_colors(rng: np.random.Generator, num_distractors: int
                  ) -> np.ndarray:
  """Colour ids: patient, distinct distractor colours, agent (last)."""
  return np.concatenate([
      [PATIENT_COLOR],
      rng.choice(DISTRACTOR_COLORS, num_distractors, replace=False),
      [AGENT_COLOR]])


def _sample_bank_scene(rng: np.random.Generator, config: ContactConfig
                       ) -> synthetic.Scene:
  """A 'bank' scene: patient (row 0), bumper (row 1), other distractors,
  agent (last row) launched from the side at the bumper. The label does not
  steer the sampling: the collision decides it, :func:`accept` keeps the
  scenes with the wanted one."""
  scale = config.object_scale
  num_distractors = int(rng.integers(config.min_distractors,
                                     config.max_distractors + 1))
  agent_size = int(rng.integers(0, len(SIZES)))
  agent_radius = synthetic.SIZE_RADII[agent_size] * scale
  for _ in range(_MAX_SCENE_ATTEMPTS):
    shapes = rng.integers(0, len(SHAPES), num_distractors + 1)
    sizes = rng.integers(0, len(SIZES), num_distractors + 1)
    footprints = [synthetic._footprint_radius(  # pylint: disable=protected-access
        int(shape), synthetic.SIZE_RADII[size] * scale)
                  for shape, size in zip(shapes, sizes)]
    patient = np.array([rng.uniform(*PATIENT_X_RANGE),
                        rng.uniform(*PATIENT_Y_RANGE)])
    start = _side_start(rng, tuple(patient))
    back = np.arctan2(*(start - patient)[::-1])
    angle = back + rng.choice([-1.0, 1.0]) * rng.uniform(*BANK_ANGLE)
    distance = footprints[0] + footprints[1] + rng.uniform(*BANK_GAP)
    bumper = patient + distance * np.array([np.cos(angle), np.sin(angle)])
    placed = [(*patient, footprints[0]), (*bumper, footprints[1])]
    clear = [(*start, agent_radius)]
    pairs = ((placed[0], placed[1]), (placed[0], clear[0]),
             (placed[1], clear[0]))
    if any(np.hypot(a[0] - b[0], a[1] - b[1]) <= a[2] + b[2] + synthetic.MIN_GAP
           for a, b in pairs):
      continue  # overlapping patient / bumper / agent: re-sample
    for footprint in footprints[2:]:
      xy = _place(rng, placed + clear, footprint, synthetic.STATIC_X_RANGE,
                  synthetic.STATIC_Y_RANGE)
      if xy is None:
        break
      placed.append((*xy, footprint))
    if len(placed) == num_distractors + 1:
      break
  else:
    raise ValueError('could not place the objects; use fewer distractors')
  colors = _scene_colors(rng, num_distractors)
  to_bumper = bumper - start
  heading = to_bumper / np.linalg.norm(to_bumper)
  # A sideways offset b of the aim line from the bumper's centre: the
  # impact parameter of the collision (0: head-on; r_agent + r_bumper:
  # grazing), which sets the direction of the bounce.
  offset = rng.uniform(-BANK_OFFSET, BANK_OFFSET) * (
      agent_radius + footprints[1])
  aim = bumper + offset * np.array([-heading[1], heading[0]])
  direction = (aim - start) / np.linalg.norm(aim - start)
  speed = rng.uniform(*BANK_SPEED_RANGE)
  return synthetic.Scene(
      shapes=np.append(shapes, SHAPES.index('sphere')).astype(
          np.int32),
      colors=colors.astype(np.int32),
      sizes=np.append(sizes, agent_size).astype(np.int32),
      xy=np.concatenate([np.array([p[:2] for p in placed]), start[None]], 0),
      yaw=rng.uniform(0.0, 2.0 * np.pi, num_distractors + 2),
      launch_velocity=speed * direction)


def _side_start(rng: np.random.Generator,
                patient_xy: tuple[float, float]) -> np.ndarray:
  """float [2]: a 'side' launch's start, on the side away from the patient."""
  edge = -SIDE_LAUNCH_X if patient_xy[0] > 0 else SIDE_LAUNCH_X
  depth = patient_xy[1] + rng.uniform(-SIDE_LAUNCH_DEPTH_NOISE,
                                      SIDE_LAUNCH_DEPTH_NOISE)
  return np.array([edge, depth])


def simulate(scene: synthetic.Scene, config: ContactConfig, *,
             render: bool) -> dict[str, np.ndarray]:
  """Simulates ``scene`` (row 0 patient, last row agent), optionally renders.

  Frame 0 is the initial state; frame t+1 is SUBSTEPS_PER_FRAME bullet steps
  after frame t. Contacts are checked after every one of those steps.

  Returns (O = config.max_objects_total, N = scene.num_objects):
    contact: bool [], agent and patient touched at some substep.
    bump_frame: int32 [], only for scenario 'bank': as contact_frame, for
      the agent and the bumper (row 1).
    contact_frame: int32 [], the first frame at or after the first touching
      substep (-1 without contact).
    positions, velocities: float32 [T, O, 3] centres [m] / linear velocities
      [m/s] at every frame; zero rows for padding.
    num_objects: int32 [] = N; agent_index, patient_index: int32 [] rows.
    shapes, colors, sizes: int32 [O], -1 for padding.
    With ``render``: video uint8 [T, H, W, 3], segmentations uint8 [T, H, W]
      (k = object row k-1), boxes float32 [T, O, 4], visible bool [T, O].
  """
  height, width = config.resolution
  ss = config.supersample
  num_rows = config.max_objects_total
  n = scene.num_objects
  if n > num_rows:
    raise ValueError(f'scene has {n} objects but config allows {num_rows}')
  client = pybullet.connect(pybullet.DIRECT)
  try:
    pybullet.setPhysicsEngineParameter(
        fixedTimeStep=synthetic.PHYSICS_DT, numSubSteps=0,
        numSolverIterations=synthetic.SOLVER_ITERATIONS,
        deterministicOverlappingPairs=1, physicsClientId=client)
    pybullet.setGravity(0.0, 0.0, -synthetic.GRAVITY, physicsClientId=client)
    # pylint: disable=protected-access
    floor = synthetic._create_floor(client)
    bodies = [
        synthetic._create_object(
            client, int(scene.shapes[i]),
            synthetic.SIZE_RADII[scene.sizes[i]] * config.object_scale,
            int(scene.colors[i]), scene.xy[i], float(scene.yaw[i]))
        for i in range(n)]
    agent, patient = bodies[-1], bodies[0]
    vx, vy = (float(v) for v in scene.launch_velocity)
    radius = synthetic.SIZE_RADII[scene.sizes[-1]] * config.object_scale
    pybullet.resetBaseVelocity(
        agent, linearVelocity=[vx, vy, 0.0],
        angularVelocity=[-vy / radius, vx / radius, 0.0],
        physicsClientId=client)
    if render:
      lut = np.zeros(max(bodies + [floor]) + 2, np.uint8)
      for k, body in enumerate(bodies, start=1):
        lut[body + 1] = k
      view, projection = synthetic._camera_matrices(height, width)
    # pylint: enable=protected-access
    frames, segs = [], []
    positions = np.zeros((config.num_frames, num_rows, 3), np.float32)
    velocities = np.zeros((config.num_frames, num_rows, 3), np.float32)
    contact_frame = -1
    bump_frame = -1   # 'bank': the agent's first touch of the bumper (row 1)
    bank = config.scenario == 'bank'
    for t in range(config.num_frames):
      if render:
        rgb, seg = synthetic.render_frame(client, view, projection, height,
                                          width, ss, lut)
        frames.append(rgb)
        segs.append(seg)
      for k, body in enumerate(bodies):
        positions[t, k] = pybullet.getBasePositionAndOrientation(
            body, physicsClientId=client)[0]
        velocities[t, k] = pybullet.getBaseVelocity(
            body, physicsClientId=client)[0]
      if t + 1 < config.num_frames:
        for _ in range(synthetic.SUBSTEPS_PER_FRAME):
          pybullet.stepSimulation(physicsClientId=client)
          if contact_frame < 0 and touching(client, agent, patient):
            contact_frame = t + 1
          if bank and bump_frame < 0 and touching(client, agent, bodies[1]):
            bump_frame = t + 1
  finally:
    pybullet.disconnect(physicsClientId=client)

  def pad(values: np.ndarray) -> np.ndarray:
    out = np.full((num_rows,), -1, np.int32)
    out[:n] = values
    return out

  example = {
      'contact': np.array(contact_frame >= 0),
      'contact_frame': np.array(contact_frame, np.int32),
      'positions': positions,
      'velocities': velocities,
      'num_objects': np.array(n, np.int32),
      'agent_index': np.array(n - 1, np.int32),
      'patient_index': np.array(0, np.int32),
      'shapes': pad(scene.shapes),
      'colors': pad(scene.colors),
      'sizes': pad(scene.sizes),
  }
  if bank:
    example['bump_frame'] = np.array(bump_frame, np.int32)
  if render:
    segmentations = np.stack(segs)
    boxes, visible = synthetic.boxes_from_segmentation(segmentations, num_rows)
    example.update(video=np.stack(frames), segmentations=segmentations,
                   boxes=boxes, visible=visible)
  return example


def touching(client: int, body_a: int, body_b: int) -> bool:
  """Whether ``body_a`` and ``body_b`` touch in the current state.

  Closest points are computed on the current poses; the contact manifold of
  ``getContactPoints`` comes from the collision pass *before* the last
  integration, which reports a touch one substep late.
  """
  points = pybullet.getClosestPoints(bodyA=body_a, bodyB=body_b,
                                     distance=CONTACT_DISTANCE,
                                     physicsClientId=client)
  return any(point[8] <= CONTACT_DISTANCE for point in points)


def accept(outcome: dict[str, np.ndarray], config: ContactConfig,
           want_contact: bool) -> bool:
  """A scene is kept if it has the wanted label and a late-enough onset;
  a 'bank' scene also needs the agent to hit the bumper after the observed
  frames and before any touch of the patient."""
  if bool(outcome['contact']) != want_contact:
    return False
  if config.scenario == 'bank':
    bump = int(outcome['bump_frame'])
    if bump < config.observed_frames:
      return False
    if want_contact and int(outcome['contact_frame']) <= bump:
      return False
  return not want_contact or int(
      outcome['contact_frame']) >= config.observed_frames


def accepted_scene(config: ContactConfig, split: str, index: int
                   ) -> tuple[synthetic.Scene, dict[str, np.ndarray]]:
  """(scene, physics-only outcome) of video ``index`` of ``split``; the
  wanted label is ``index % 2``."""
  if split not in SPLITS:
    raise ValueError(f'split must be one of {SPLITS}, got {split!r}')
  rng = video_rng(config.seed, split, index)
  want_contact = bool(index % 2)
  for _ in range(_MAX_SCENE_ATTEMPTS):
    scene = sample_contact_scene(rng, config, want_contact)
    outcome = simulate(scene, config, render=False)
    if accept(outcome, config, want_contact):
      return scene, outcome
  raise RuntimeError(f'no scene with contact={want_contact} after '
                     f'{_MAX_SCENE_ATTEMPTS} attempts (video {index} of '
                     f'{split}); check the launch / layout ranges')


def generate_states(config: ContactConfig, split: str, index: int
                    ) -> dict[str, np.ndarray]:
  """The simulator ground truth of video ``index`` without its frames (the
  dict of :func:`simulate` with ``render=False``): what
  experiments/contact_state_ceiling.py trains on."""
  return accepted_scene(config, split, index)[1]


def generate_video(config: ContactConfig, split: str, index: int
                   ) -> dict[str, np.ndarray]:
  """Video ``index`` of ``split``; its label is ``index % 2``.

  Returns the dict of :func:`simulate` (rendered) plus ``index``: int32 [].
  """
  scene, _ = accepted_scene(config, split, index)
  example = simulate(scene, config, render=True)
  if not accept(example, config, bool(index % 2)):
    raise RuntimeError('the rendered simulation disagrees with the '
                       'physics-only pass; bullet is not deterministic here')
  example['index'] = np.array(index, np.int32)
  return example


# ----------------------------------------------------------------------------
# TFDS storage (same layout and reader as the OBJ3D-like dataset)
# ----------------------------------------------------------------------------


def features(config: ContactConfig) -> tfds.features.FeaturesDict:
  h, w = config.resolution
  t, o = config.num_frames, config.max_objects_total
  tensor, scalar = base.tensor, tfds.features.Scalar
  return tfds.features.FeaturesDict({
      'video': tensor((t, h, w, 3), np.uint8),
      'segmentations': tensor((t, h, w), np.uint8),
      'boxes': tensor((t, o, 4), np.float32),
      'visible': tensor((t, o), np.bool_),
      'positions': tensor((t, o, 3), np.float32),
      'velocities': tensor((t, o, 3), np.float32),
      'contact': scalar(np.bool_),
      'contact_frame': scalar(np.int32),
      'num_objects': scalar(np.int32),
      'agent_index': scalar(np.int32),
      'patient_index': scalar(np.int32),
      'shapes': tensor((o,), np.int32),
      'colors': tensor((o,), np.int32),
      'sizes': tensor((o,), np.int32),
      'index': scalar(np.int32),
      **({'bump_frame': scalar(np.int32)}
         if config.scenario == 'bank' else {}),
  })


def generate(config: ContactConfig, out: base.Output) -> Path:
  """Generates the four splits of ``config`` unless they are there."""
  return out.tfds_folder(
      dataset_dir(config, out.data_dir), name=NAME, features=features(config),
      description=json.dumps(dataclasses.asdict(config)),
      split_sizes={split: config.num_videos(split) for split in SPLITS},
      make=functools.partial(generate_video, config))


DATASET = base.register(base.Generated(
    names=(NAME,), label='object-contact (OCP)', splits=SPLITS,
    features=functools.partial(features, ContactConfig()),
    what='the contact dataset', parameters=config_from_data_config,
    folder=dataset_dir, generate=generate))
