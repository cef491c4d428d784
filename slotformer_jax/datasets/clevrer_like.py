"""A CLEVRER-like scenario family with an event log from the simulator
(``data.name='clevrer_like'``).

CLEVRER (Yi et al., 2020) videos show objects sliding, colliding and entering
the scene, with the events that happened, from which its questions are
generated. This module builds such videos on the OBJ3D-like pybullet world
(:mod:`slotformer_jax.datasets.synthetic`): :func:`sample_scene` draws a
scene, :func:`simulate` runs it (``removed=k``: the same world without object
``k``, deterministically), :func:`event_log` gives the :class:`EventLog` that
:mod:`slotformer_jax.datasets.clevrer_like_questions` reads, and
:func:`generate` writes a dataset into the folder its
:class:`ClevrerLikeConfig` names, which :class:`NpyVideoSource` reads.

Object ids are 0-based rows of the per-object arrays (mask id = row + 1); a
collision's onset frame is the first frame that shows it. The family, its
events, frames and folder layout: docs/vqa.md, "The CLEVRER-like family".
"""

from __future__ import annotations

import collections
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
from slotformer_jax.data import vqa
from slotformer_jax.data.events import NUM_GAP_BINS
from slotformer_jax.data.events import Collision
from slotformer_jax.data.events import EventLog
from slotformer_jax.datasets import base
from slotformer_jax.datasets import clevrer_like_questions as question_generator
from slotformer_jax.datasets import synthetic
from slotformer_jax.datasets.synthetic import COLORS
from slotformer_jax.datasets.synthetic import SHAPES
from slotformer_jax.datasets.synthetic import SIZES
from slotformer_jax.errors import MissingInputError

# The videos and event logs (the questions have their own version,
# QUESTIONS_VERSION; the event-log types are in data/events.py).
# 2: future_collision_fraction.
GENERATOR_VERSION = 2
# The questions generated from the event logs (datasets/clevrer_like_questions.py).
# Not part of the folder name: a dataset whose complete.json names an older
# version gets new questions from its stored event logs (its videos do not
# change), so the readers refuse it until the data stage has done that.
# 1: the first generator; 2: explanatory labels by re-simulation, balanced
# per choice kind, count templates over objects in view, up to 2
# predictive / explanatory questions per video.
QUESTIONS_VERSION = 2

# predictive_design: 'direct', objects aimed roughly at each other (most
# future collisions are objects already heading at each other: extrapolating
# the observed end answers ~85% of the predictive options, experiments/
# vqa_state_extrapolation.py); 'deflected', bank-shot scenes drawn
# until the future has an event that extrapolation gets wrong, and every
# pair in view at the end carries the extrapolation's verdict
# (EventLog.extrapolated) so that the questions balance the labels within
# each verdict (docs/vqa.md, "Issue 12, round 4"); see
# datasets/clevrer_like.py.
PREDICTIVE_DESIGNS = ('direct', 'deflected')

DATASET_NAME = 'clevrer_like'
ARRAY_FIELDS = ('video', 'segmentations', 'boxes', 'visible', 'num_objects')
# scene_index = offset + video index, as CLEVRER numbers its splits.
SCENE_OFFSETS = {'train': 0, 'val': 10000, 'test': 15000}
COMPLETE = 'complete.json'


@dataclasses.dataclass(frozen=True)
class ClevrerLikeConfig:
  """Generation parameters; together they identify a generated dataset.

  Attributes:
    resolution: (H, W) of rendered frames.
    observed_frames: frames of the video shown to models.
    predicted_frames: frames simulated after the video (predictive questions
      ask about them; a dynamics model has to roll out to see them).
    min_objects, max_objects: objects present from frame 0.
    max_entering: objects entering later (0..max_entering per video).
    moving_fraction: probability that an object present at frame 0 moves.
    future_collision_fraction: probability that a video is drawn among
      scenes where two objects in view at the last observed frame collide
      after it (rejection sampling over physics-only simulations): without
      it only ~1/3 of the videos have anything to predict. With the
      'deflected' design: among scenes with a predictive question balanced
      within the extrapolation's verdict (:func:`has_deflected_question`).
    seed: base seed; video ``i`` of split ``s`` uses ``(seed, s, i)``.
    num_train, num_val, num_test: videos per split.
    supersample, object_scale: as in
      :class:`slotformer_jax.datasets.synthetic.SyntheticConfig`.
    predictive_design: one of PREDICTIVE_DESIGNS ('direct' is the generator
      of version 2; the field enters the slug only when not 'direct', so the
      datasets built before it keep their slugs and contents).
  """

  resolution: tuple[int, int] = (32, 32)
  observed_frames: int = 24
  predicted_frames: int = 16
  min_objects: int = 2
  max_objects: int = 4
  max_entering: int = 1
  moving_fraction: float = 0.5
  future_collision_fraction: float = 0.0
  seed: int = 0
  num_train: int = 1000
  num_val: int = 100
  num_test: int = 200
  supersample: int = 2
  object_scale: float = 1.0
  predictive_design: str = 'direct'

  def __post_init__(self):
    object.__setattr__(self, 'resolution', tuple(int(r) for r in self.resolution))
    if self.observed_frames < 2 or self.predicted_frames < 0:
      raise ValueError('need observed_frames >= 2 and predicted_frames >= 0')
    if not 1 <= self.min_objects <= self.max_objects:
      raise ValueError('need 1 <= min_objects <= max_objects')
    if self.max_objects + self.max_entering > len(COLORS):
      # Objects are named by colour in questions: colours must be distinct.
      raise ValueError(f'at most {len(COLORS)} objects per video')
    if self.max_entering < 0:
      raise ValueError('max_entering must be >= 0')
    if not 0.0 <= self.future_collision_fraction <= 1.0:
      raise ValueError('future_collision_fraction must be in [0, 1]')
    if self.predictive_design == 'deflected' and (
        self.max_objects < 3 or self.predicted_frames < 2):
      # A bank shot needs three objects, a verdict a few future frames.
      raise ValueError("predictive_design='deflected' needs max_objects >= 3 "
                       'and predicted_frames >= 2')
    if self.predictive_design not in PREDICTIVE_DESIGNS:
      raise ValueError(f'predictive_design must be one of '
                       f'{PREDICTIVE_DESIGNS}, got {self.predictive_design!r}')

  @property
  def num_frames(self) -> int:
    return self.observed_frames + self.predicted_frames

  @property
  def max_objects_total(self) -> int:
    return self.max_objects + self.max_entering

  def num_videos(self, split: str) -> int:
    return {'train': self.num_train, 'val': self.num_val,
            'test': self.num_test}[split]

  def identity(self) -> dict[str, Any]:
    """The fields that identify the dataset: all of them, except
    ``predictive_design`` when it is 'direct' (as before the field)."""
    fields = dataclasses.asdict(self)
    if fields['predictive_design'] == 'direct':
      del fields['predictive_design']
    return fields

  @property
  def slug(self) -> str:
    h, w = self.resolution
    payload = json.dumps({**self.identity(),
                          'generator_version': GENERATOR_VERSION},
                         sort_keys=True)
    digest = hashlib.sha256(payload.encode()).hexdigest()[:8]
    return (f'r{h}x{w}_t{self.observed_frames}+{self.predicted_frames}'
            f'_o{self.min_objects}-{self.max_objects}+{self.max_entering}'
            f'_s{self.seed}_{digest}')


def video_filename(split: str, index: int) -> str:
  return f'video_{SCENE_OFFSETS[split] + index:05d}.mp4'


def dataset_dir(config: ClevrerLikeConfig, data_dir: str | os.PathLike[str]
                ) -> Path:
  return Path(data_dir) / DATASET_NAME / config.slug


def completion(config: ClevrerLikeConfig) -> dict[str, Any]:
  """What complete.json of a finished, current dataset holds."""
  return {**config.identity(), 'questions_version': QUESTIONS_VERSION}


def is_complete(root: str | os.PathLike[str]) -> bool:
  """Whether the dataset folder ``root`` is finished and its questions are
  the current generator's (one small read)."""
  path = Path(root) / COMPLETE
  if not path.is_file():
    return False
  with open(path) as f:
    return json.load(f).get('questions_version') == QUESTIONS_VERSION


def complete_dataset_dir(data_config: Any, data_dir: str | os.PathLike[str]
                         ) -> Path:
  """The folder of the dataset ``config.data`` names.

  Raises:
    MissingInputError: it is not generated, or its questions are older
      than the generator's (names the command that makes them).
  """
  root = dataset_dir(config_from_data_config(data_config), data_dir)
  if not (root / COMPLETE).is_file():
    raise sources.not_generated('the CLEVRER-like dataset', root / COMPLETE)
  if not is_complete(root):
    raise MissingInputError(
        f'the CLEVRER-like dataset {root} holds questions of an older '
        f'generator; {sources.PREPARE_COMMAND} writes new ones from its '
        'event logs (every --mode runs that stage first)')
  return root


class NpyVideoSource:
  """The videos of one split of a built dataset (frames memory-mapped).

  Items: video uint8 [T, H, W, 3], segmentations uint8 [T, H, W], boxes
  float32 [T, O, 4], visible bool [T, O], num_objects int32 [], index.
  """

  def __init__(self, root: str | os.PathLike[str], split: str):
    folder = Path(root) / split
    self._arrays = {field: np.load(folder / f'{field}.npy', mmap_mode='r')
                    for field in ARRAY_FIELDS}

  def __len__(self) -> int:
    return len(self._arrays['video'])

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    if not 0 <= index < len(self):
      raise IndexError(index)
    item = {k: np.asarray(v[index]) for k, v in self._arrays.items()}
    item['index'] = np.array(index, np.int32)
    return item


def config_from_data_config(data_config: Any) -> ClevrerLikeConfig:
  """The generation parameters named by a data config (defaults filled in)."""
  fields = {f.name for f in dataclasses.fields(ClevrerLikeConfig)}
  values = {k: data_config[k] for k in fields if k in data_config}
  if 'resolution' in values:
    values['resolution'] = tuple(values['resolution'])
  return ClevrerLikeConfig(**values)


SPLITS = synthetic.SPLITS
SUBSTEPS_PER_FRAME = synthetic.SUBSTEPS_PER_FRAME

# CLEVRER's objects slide far; the OBJ3D-like friction (0.5) stops a cube
# ~0.5 s after a hit, which leaves little to predict after the observed window.
LATERAL_FRICTION = 0.15
ROLLING_FRICTION_PER_RADIUS = 0.15
# A pair must be apart for this many substeps (0.1 s) before a new contact
# counts as a new collision: resting or sliding contacts flicker.
MIN_SEPARATION_SUBSTEPS = 24
# Speed [m/s] above which an object counts as moving.
MOVING_SPEED = 0.1
# Objects present from frame 0 sit in this region (inside the view).
START_X_RANGE = (-2.0, 2.0)
START_Y_RANGE = (-1.0, 2.0)
MIN_GAP = 0.25
MOVING_SPEED_RANGE = (1.0, 3.0)       # [m/s] of objects moving at frame 0
AIM_NOISE = 0.15                      # [rad] around the exact aim
# Entering objects appear just outside the left/right edge of the view
# (|x| = ENTER_X; the view's edge is at |x| ~ 3 near the middle) and roll in.
ENTER_X = 4.3
ENTER_Y_RANGE = (-0.5, 2.0)
ENTER_SPEED_RANGE = (2.5, 4.0)
# In view: the projected centre lies inside the image, with this margin of the
# normalised device coordinates (so an object is "in" once mostly visible).
VIEW_MARGIN = 0.05
# Scenes drawn (physics only, ~20 ms each) to find one whose future has a
# collision, when a video should have one (future_collision_fraction).
MAX_SCENE_TRIES = 30
# predictive_design (PREDICTIVE_DESIGNS): 'direct', the scenes above;
# 'deflected', the bank-shot scenes below.
# The extrapolation's verdict on a pair (extrapolation_verdict): the bin of
# its extrapolated_clearance [m], 3 "a clear hit" (< EXTRAPOLATION_BINS[0]),
# 2 "a close call", 1 "a near miss", 0 "far apart" (>= the last bin edge),
# and how the two move relative to each other: not, apart, or closing in
# and meeting early or late in the predicted frames. A plain hit / miss
# verdict was not enough: how deep the overlap was, how close the miss,
# whether the pair rests, or how soon they meet still told the label (on
# the bank-shot scenes a threshold on the clearance scored 61-72% per
# option, a logistic regression on the pair's end state 67-73%; docs/
# vqa.md, round 4).
EXTRAPOLATION_BINS = (-0.5, 0.05, 0.5)
# events.NUM_GAP_BINS counts these bins.
assert NUM_GAP_BINS == len(EXTRAPOLATION_BINS) + 1
# 'deflected' scenes are built around a bank shot: a mover A slides at a
# resting blocker C with a resting target B just behind it, all in view,
# and reaches C only after the video (BANK_CONTACT_DELAY after it).
# Extrapolation says A hits C (and B when A is fast); what happens depends
# on the hit: A stops or glances off, C is pushed into B or past it.
# Objects barely slow down when sliding (SLIDING_DECELERATION at
# LATERAL_FRICTION; measured).
BANK_GAP = (1.5, 3.0)            # [m] A's surface to C's at frame 0
BANK_CONTACT_DELAY = (0.0, 5.0)  # [frames] after the last observed one
SLIDING_DECELERATION = 0.2       # [m/s^2] (spheres ~0.16)
BANK_TARGET_GAP = (0.05, 0.35)   # [m] C's surface to B's
# Sideways offsets, as fractions of the two radii: A's impact parameter on
# C, B's offset from the line A -> C (both set how C is pushed).
BANK_IMPACT = 0.7
BANK_TARGET_OFFSET = 0.6
# C is drawn in this region; B, C and A at the last observed frame must
# project inside BANK_VIEW of the normalised device coordinates (the floor
# in view is a trapezoid, wider at the back: a bank shot needs ~4 m).
BANK_X_RANGE = (-2.5, 2.5)
BANK_Y_RANGE = (-1.0, 3.0)
BANK_VIEW = 0.8


@dataclasses.dataclass(frozen=True)
class Scene:
  """The initial state of one video (N objects, entering ones last).

  Attributes:
    shapes, colors, sizes: int32 [N] indices into SHAPES / COLORS / SIZES;
      colours are distinct (questions name objects by colour and shape).
    xy: float64 [N, 2] ground position when the object appears.
    yaw: float64 [N] rotation about z [rad].
    velocity: float64 [N, 2] ground velocity when the object appears [m/s].
    enter_frame: int32 [N]; 0 for objects present from the start, else the
      frame at which the object is added (just outside the view).
  """

  shapes: np.ndarray
  colors: np.ndarray
  sizes: np.ndarray
  xy: np.ndarray
  yaw: np.ndarray
  velocity: np.ndarray
  enter_frame: np.ndarray

  @property
  def num_objects(self) -> int:
    return int(self.shapes.shape[0])


def _aim(rng: np.random.Generator, start: np.ndarray, target: np.ndarray,
         speed_range: tuple[float, float]) -> np.ndarray:
  direction = target - start
  angle = np.arctan2(direction[1], direction[0]) + rng.uniform(-AIM_NOISE,
                                                               AIM_NOISE)
  return rng.uniform(*speed_range) * np.array([np.cos(angle), np.sin(angle)])


def sample_scene(rng: np.random.Generator, config: ClevrerLikeConfig) -> Scene:
  """Samples the objects of one video; a pure function of ``rng``'s state."""
  if config.predictive_design == 'deflected':
    return _sample_bank_scene(rng, config)
  num_start = int(rng.integers(config.min_objects, config.max_objects + 1))
  num_enter = int(rng.integers(0, config.max_entering + 1))
  n = num_start + num_enter
  for _ in range(1000):
    shapes = rng.integers(0, len(SHAPES), n)
    sizes = rng.integers(0, len(SIZES), n)
    placed: list[tuple[float, float, float]] = []
    for shape, size in zip(shapes[:num_start], sizes[:num_start]):
      footprint = synthetic._footprint_radius(  # pylint: disable=protected-access
          int(shape), synthetic.SIZE_RADII[size] * config.object_scale)
      for _ in range(200):
        x, y = rng.uniform(*START_X_RANGE), rng.uniform(*START_Y_RANGE)
        if all(np.hypot(x - px, y - py) > footprint + pr + MIN_GAP
               for px, py, pr in placed):
          placed.append((x, y, footprint))
          break
      else:
        break
    if len(placed) == num_start:
      break
  else:
    raise ValueError(f'could not place {num_start} objects; lower max_objects')
  colors = rng.permutation(len(COLORS))[:n]
  yaw = rng.uniform(0.0, 2.0 * np.pi, n)
  xy = np.zeros((n, 2))
  xy[:num_start] = np.array([p[:2] for p in placed])
  velocity = np.zeros((n, 2))
  enter_frame = np.zeros(n, np.int32)
  # At least one object moves, so that (almost) every video has events.
  moving = rng.uniform(size=num_start) < config.moving_fraction
  moving[int(rng.integers(0, num_start))] = True
  for i in np.flatnonzero(moving):
    others = [j for j in range(num_start) if j != i]
    target = (xy[int(rng.choice(others))] if others
              else np.array([0.0, 0.5]))
    velocity[i] = _aim(rng, xy[i], target, MOVING_SPEED_RANGE)
  for i in range(num_start, n):
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    xy[i] = (side * ENTER_X, rng.uniform(*ENTER_Y_RANGE))
    # Aim at an object already there (or the middle): entering objects
    # cause collisions, some of them after the observed window.
    target = xy[int(rng.integers(0, num_start))]
    velocity[i] = _aim(rng, xy[i], target, ENTER_SPEED_RANGE)
    # Entering takes ~0.3-0.5 s (6-10 frames) from outside the view: early
    # enough that the object is seen before the video ends.
    enter_frame[i] = int(rng.integers(1, max(2, config.observed_frames - 8)))
  return Scene(shapes=shapes.astype(np.int32), colors=colors.astype(np.int32),
               sizes=sizes.astype(np.int32), xy=xy, yaw=yaw, velocity=velocity,
               enter_frame=enter_frame)


def _in_view(project, points: np.ndarray, margin: float) -> bool:
  """Whether ground points [K, 2] (at object-centre height) project inside
  ``margin`` of the normalised device coordinates."""
  centres = np.concatenate([points, np.full((len(points), 1), 0.5)], -1)
  return bool(np.all(np.abs(project(centres)) < margin))


def _place_bank(rng: np.random.Generator, radii: np.ndarray, project,
                observed_frames: int, enters: bool
                ) -> tuple[np.ndarray, np.ndarray, int] | None:
  """A bank shot: ground positions [3, 2] of mover A, target B, blocker C
  (footprint radii ``radii`` [3]), A's velocity [2] and the frame it
  appears at; None if they do not fit the view.

  A present from frame 0 starts BANK_GAP from C; an entering A (``enters``)
  comes from the side as entering objects do (ENTER_X, ENTER_SPEED_RANGE),
  appearing early enough to be seen for 8 frames: faster, so that its
  extrapolated path also reaches B within the predicted frames.
  """
  r_a, r_b, r_c = radii
  blocker = np.array([rng.uniform(*BANK_X_RANGE), rng.uniform(*BANK_Y_RANGE)])
  impact = rng.uniform(-BANK_IMPACT, BANK_IMPACT) * (r_a + r_c)
  offset = rng.uniform(-BANK_TARGET_OFFSET, BANK_TARGET_OFFSET) * (r_c + r_b)
  target_gap = rng.uniform(*BANK_TARGET_GAP)
  fps = 1.0 / (SUBSTEPS_PER_FRAME * synthetic.PHYSICS_DT)
  # [s] after frame 0
  contact = (observed_frames + rng.uniform(*BANK_CONTACT_DELAY)) / fps
  if enters:
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    start = np.array([side * ENTER_X, rng.uniform(*ENTER_Y_RANGE)])
    speed = rng.uniform(*ENTER_SPEED_RANGE)
  else:
    angle = rng.uniform(0.0, 2.0 * np.pi)
    start = blocker - (rng.uniform(*BANK_GAP) + r_a + r_c) * np.array(
        [np.cos(angle), np.sin(angle)])
  towards = (blocker - start) / np.linalg.norm(blocker - start)
  aim = blocker + impact * np.array([-towards[1], towards[0]])
  along = (aim - start) / np.linalg.norm(aim - start)
  across = np.array([-along[1], along[0]])
  gap = max(float(np.dot(blocker - start, along)) - r_a - r_c, 0.0)
  target = blocker + (r_c + r_b + target_gap) * along + offset * across
  if enters:
    # Appears at enter_frame, reaches C's surface `contact` s after frame 0.
    enter_frame = int(round((contact - gap / speed) * fps))
    if not 1 <= enter_frame <= observed_frames - 8:
      return None
    mover_at_end = start + along * speed * (observed_frames - 1
                                            - enter_frame) / fps
  else:
    speed = gap / contact + 0.5 * SLIDING_DECELERATION * contact
    enter_frame = 0
    mover_at_end = start
  xy = np.stack([start, target, blocker])
  if not (_in_view(project, xy[1:], BANK_VIEW)
          and _in_view(project, mover_at_end[None], BANK_VIEW)):
    return None
  if np.hypot(*(start - target)) <= r_a + r_b + MIN_GAP:
    return None
  return xy, speed * along, enter_frame


def _sample_bank_scene(rng: np.random.Generator, config: ClevrerLikeConfig
                       ) -> Scene:
  """A 'deflected' scene: a bank shot (mover A, target B, blocker C; see
  BANK_GAP) and the other objects placed, moving and entering as
  :func:`sample_scene` does. A is the entering object when the video has
  one (so that "how many objects enter" keeps its answers), else an object
  present from frame 0. The outcome is not steered: the simulation decides
  it, and :func:`sample_video_scene` keeps the scenes that ask something
  (:func:`has_deflected_question`)."""
  project = _projector(*config.resolution)
  num_start = int(rng.integers(max(3, config.min_objects),
                               config.max_objects + 1))
  num_enter = int(rng.integers(0, config.max_entering + 1))
  n = num_start + num_enter
  # Rows of A, B, C before the shuffle below.
  roles = [num_start if num_enter else 2, 0, 1]
  for _ in range(1000):
    shapes = rng.integers(0, len(SHAPES), n)
    sizes = rng.integers(0, len(SIZES), n)
    footprints = np.array([synthetic._footprint_radius(  # pylint: disable=protected-access
        int(shape), synthetic.SIZE_RADII[size] * config.object_scale)
                           for shape, size in zip(shapes, sizes)])
    bank = _place_bank(rng, footprints[roles], project,
                       config.observed_frames, enters=num_enter > 0)
    if bank is None:
      continue
    bank_xy, bank_velocity, bank_enter = bank
    placed = [(x, y, r) for (x, y), r in zip(bank_xy, footprints[roles])]
    others = [i for i in range(num_start) if i not in roles]
    for i in others:
      for _ in range(200):
        x, y = rng.uniform(*START_X_RANGE), rng.uniform(*START_Y_RANGE)
        if all(np.hypot(x - px, y - py) > footprints[i] + pr + MIN_GAP
               for px, py, pr in placed):
          placed.append((x, y, footprints[i]))
          break
      else:
        break
    if len(placed) == 3 + len(others):
      break
  else:
    raise ValueError(f'could not place {num_start} objects; lower max_objects')
  colors = rng.permutation(len(COLORS))[:n]
  yaw = rng.uniform(0.0, 2.0 * np.pi, n)
  xy = np.zeros((n, 2))
  xy[roles + others] = np.array([p[:2] for p in placed])
  velocity = np.zeros((n, 2))
  velocity[roles[0]] = bank_velocity
  enter_frame = np.zeros(n, np.int32)
  enter_frame[roles[0]] = bank_enter
  # The others move as in sample_scene (aimed at another object), so the
  # video has its own collisions for the other question types.
  moving = rng.uniform(size=num_start) < config.moving_fraction
  for i in others:
    if moving[i]:
      velocity[i] = _aim(rng, xy[i], xy[int(rng.choice(
          [j for j in range(num_start) if j != i]))], MOVING_SPEED_RANGE)
  for i in range(num_start + 1, n):
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    xy[i] = (side * ENTER_X, rng.uniform(*ENTER_Y_RANGE))
    velocity[i] = _aim(rng, xy[i], xy[int(rng.integers(0, num_start))],
                       ENTER_SPEED_RANGE)
    enter_frame[i] = int(rng.integers(1, max(2, config.observed_frames - 8)))
  # The roles get random rows among the objects present from frame 0.
  order = np.concatenate([rng.permutation(num_start),
                          np.arange(num_start, n)])
  return Scene(shapes=shapes[order].astype(np.int32),
               colors=colors.astype(np.int32),
               sizes=sizes[order].astype(np.int32), xy=xy[order],
               yaw=yaw, velocity=velocity[order],
               enter_frame=enter_frame[order])


def _projector(height: int, width: int):
  """World points [..., 3] -> normalised device coordinates [..., 2]."""
  view, projection = synthetic._camera_matrices(height, width)  # pylint: disable=protected-access
  matrix = (np.asarray(projection, np.float64).reshape(4, 4).T
            @ np.asarray(view, np.float64).reshape(4, 4).T)

  def project(points: np.ndarray) -> np.ndarray:
    homogeneous = np.concatenate([points, np.ones_like(points[..., :1])], -1)
    clip = homogeneous @ matrix.T
    return clip[..., :2] / clip[..., 3:4]
  return project


def simulate(scene: Scene, config: ClevrerLikeConfig, *,
             removed: int | None = None, render: bool = False
             ) -> dict[str, Any]:
  """Simulates ``scene`` (without object ``removed``) for ``num_frames``.

  Returns (T = config.num_frames, O = config.max_objects_total, N objects):
    positions: float32 [T, O, 3] object centres (zeros before an object
      appears, and for the removed object).
    speeds: float32 [T, O] ground speed [m/s].
    present: bool [T, O] the object exists in the world.
    in_view: bool [T, O] present and its centre projects into the image.
    collisions: list of (i, j, onset_frame, onset_substep), i < j, in onset
      order; substeps are 1-based global physics step counts.
    and, with ``render=True``: video uint8 [T, H, W, 3], segmentations uint8
    [T, H, W], boxes float32 [T, O, 4], visible bool [T, O].
  """
  n = scene.num_objects
  num_slots = config.max_objects_total
  if n > num_slots:
    raise ValueError(f'scene has {n} objects, config allows {num_slots}')
  if removed is not None and not 0 <= removed < n:
    raise ValueError(f'removed={removed} is not an object of the scene')
  height, width = config.resolution
  ss = config.supersample
  project = _projector(height, width)
  t_total = config.num_frames
  client = pybullet.connect(pybullet.DIRECT)
  bodies: dict[int, int] = {}  # object id -> body id
  try:
    pybullet.setPhysicsEngineParameter(
        fixedTimeStep=synthetic.PHYSICS_DT, numSubSteps=0,
        numSolverIterations=synthetic.SOLVER_ITERATIONS,
        deterministicOverlappingPairs=1, physicsClientId=client)
    pybullet.setGravity(0.0, 0.0, -synthetic.GRAVITY, physicsClientId=client)
    floor = synthetic._create_floor(client)  # pylint: disable=protected-access
    pybullet.changeDynamics(floor, -1, lateralFriction=LATERAL_FRICTION,
                            physicsClientId=client)

    def add(i: int) -> None:
      radius = synthetic.SIZE_RADII[scene.sizes[i]] * config.object_scale
      body = synthetic._create_object(  # pylint: disable=protected-access
          client, int(scene.shapes[i]), radius, int(scene.colors[i]),
          scene.xy[i], float(scene.yaw[i]))
      pybullet.changeDynamics(
          body, -1, lateralFriction=LATERAL_FRICTION,
          rollingFriction=ROLLING_FRICTION_PER_RADIUS * radius,
          spinningFriction=ROLLING_FRICTION_PER_RADIUS * radius,
          physicsClientId=client)
      vx, vy = (float(v) for v in scene.velocity[i])
      # Spheres start rolling (w = z x v / r), other shapes sliding.
      spin = ([-vy / radius, vx / radius, 0.0]
              if SHAPES[scene.shapes[i]] == 'sphere' else [0.0, 0.0, 0.0])
      pybullet.resetBaseVelocity(body, linearVelocity=[vx, vy, 0.0],
                                 angularVelocity=spin, physicsClientId=client)
      bodies[i] = body

    view, projection = synthetic._camera_matrices(height, width)  # pylint: disable=protected-access
    positions = np.zeros((t_total, num_slots, 3), np.float32)
    speeds = np.zeros((t_total, num_slots), np.float32)
    present = np.zeros((t_total, num_slots), bool)
    frames, segs = [], []
    collisions: list[tuple[int, int, int, int]] = []
    touching: set[tuple[int, int]] = set()
    last_contact: dict[tuple[int, int], int] = {}
    substep = 0
    for t in range(t_total):
      for i in range(n):
        if i != removed and scene.enter_frame[i] == t:
          add(i)
      body_to_object = {b: i for i, b in bodies.items()}
      for i, body in bodies.items():
        positions[t, i] = pybullet.getBasePositionAndOrientation(
            body, physicsClientId=client)[0]
        speeds[t, i] = np.hypot(*pybullet.getBaseVelocity(
            body, physicsClientId=client)[0][:2])
        present[t, i] = True
      if render:
        # Objects enter during the video: this frame's bodies.
        lut = np.zeros(max(list(bodies.values()) + [floor]) + 2, np.uint8)
        for i, body in bodies.items():
          lut[body + 1] = i + 1
        rgb, seg = synthetic.render_frame(client, view, projection, height,
                                          width, ss, lut)
        frames.append(rgb)
        segs.append(seg)
      if t + 1 == t_total:
        break
      for _ in range(SUBSTEPS_PER_FRAME):
        pybullet.stepSimulation(physicsClientId=client)
        substep += 1
        now: set[tuple[int, int]] = set()
        for contact in pybullet.getContactPoints(physicsClientId=client):
          a, b = body_to_object.get(contact[1]), body_to_object.get(contact[2])
          if a is None or b is None or a == b or contact[8] > 0.0:
            continue  # the floor, or not touching
          now.add((min(a, b), max(a, b)))
        for pair in sorted(now - touching):
          if substep - last_contact.get(pair, -10**9) > MIN_SEPARATION_SUBSTEPS:
            collisions.append((pair[0], pair[1],
                               -(-substep // SUBSTEPS_PER_FRAME), substep))
        for pair in now:
          last_contact[pair] = substep
        touching = now
  finally:
    pybullet.disconnect(physicsClientId=client)
  ndc = project(positions.astype(np.float64))
  in_view = present & np.all(np.abs(ndc) < 1.0 - VIEW_MARGIN, axis=-1)
  out: dict[str, Any] = {'positions': positions, 'speeds': speeds,
                         'present': present, 'in_view': in_view,
                         'collisions': collisions}
  if render:
    segmentations = np.stack(segs)
    boxes, visible = synthetic.boxes_from_segmentation(segmentations, num_slots)
    out.update(video=np.stack(frames), segmentations=segmentations,
               boxes=boxes, visible=visible)
  return out


def _view_events(in_view: np.ndarray, present: np.ndarray
                 ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
  """(object, frame) of entering (out -> in, after frame 0) and exiting."""
  entering, exiting = [], []
  for i in range(in_view.shape[1]):
    for t in range(1, in_view.shape[0]):
      if in_view[t, i] and not in_view[t - 1, i]:
        entering.append((i, t))
      elif in_view[t - 1, i] and not in_view[t, i] and present[t, i]:
        exiting.append((i, t))
  return (sorted(entering, key=lambda e: (e[1], e[0])),
          sorted(exiting, key=lambda e: (e[1], e[0])))


def event_log(scene: Scene, simulation: dict[str, Any],
              config: ClevrerLikeConfig,
              counterfactuals: dict[int, dict[str, Any]] | None = None
              ) -> EventLog:
  """The event log of one simulated video (+ its counterfactual worlds)."""
  n = scene.num_objects
  entering, exiting = _view_events(simulation['in_view'][:, :n],
                                   simulation['present'][:, :n])
  last = config.observed_frames - 1
  final = []
  for i in range(n):
    seen = np.flatnonzero(simulation['present'][:, i])
    final.append(simulation['positions'][-1, i].round(4).tolist()
                 if seen.size else None)
  return EventLog(
      objects=[{'color': COLORS[scene.colors[i]],
                'shape': SHAPES[scene.shapes[i]],
                'size': SIZES[scene.sizes[i]]} for i in range(n)],
      observed_frames=config.observed_frames,
      num_frames=config.num_frames,
      collisions=[Collision((a, b), f) for a, b, f, _ in
                  simulation['collisions']],
      entering=entering, exiting=exiting,
      moving_at_end=[bool(simulation['present'][last, i]
                          and simulation['speeds'][last, i] > MOVING_SPEED)
                     for i in range(n)],
      in_view_at_end=[bool(simulation['in_view'][last, i]) for i in range(n)],
      final_positions=final,
      counterfactual={k: [Collision((a, b), f) for a, b, f, _ in
                          sim['collisions']]
                      for k, sim in (counterfactuals or {}).items()},
      extrapolated=([(a, b, verdict) for a, b, _, verdict in
                     end_pairs(scene, simulation, config)]
                    if config.predictive_design == 'deflected' else None),
  )


def end_pairs(scene: Scene, simulation: dict[str, Any],
              config: ClevrerLikeConfig
              ) -> list[tuple[int, int, bool, int]]:
  """(a, b, collides after the video, the extrapolation's verdict) for
  every pair a < b of objects in view at the last observed frame (the pairs
  a predictive question can offer)."""
  last = config.observed_frames - 1
  in_view = np.flatnonzero(simulation['in_view'][last, :scene.num_objects])
  radii = np.array([object_radius(SHAPES[scene.shapes[i]],
                                  SIZES[scene.sizes[i]], config.object_scale)
                    for i in range(scene.num_objects)])
  future = {(a, b) for a, b, f, _ in simulation['collisions']
            if f >= config.observed_frames}
  out = []
  for k, a in enumerate(in_view):
    for b in in_view[k + 1:]:
      approach = extrapolated_approach(
          simulation['positions'], radii, int(a), int(b),
          config.observed_frames, config.predicted_frames)
      out.append((int(a), int(b), (a, b) in future,
                  extrapolation_verdict(*approach, config.predicted_frames)))
  return out


def extrapolation_verdict(gap: float, frame: int, relative_speed: float,
                          closing: bool, horizon: int) -> int:
  """What the observed end says of a pair (:func:`extrapolated_approach`):
  ``bin + NUM_GAP_BINS * motion``, ``bin`` the clearance's
  (EXTRAPOLATION_BINS: 0 far apart .. 3 a clear hit), ``motion`` 0 if the
  two do not move relative to each other (below MOVING_SPEED), 1 if they
  move apart, else 2 if they meet in the first half of the ``horizon``, 3
  in the second.
  """
  gap_bin = int(len(EXTRAPOLATION_BINS)
                - np.searchsorted(EXTRAPOLATION_BINS, gap, side='right'))
  fps = 1.0 / (SUBSTEPS_PER_FRAME * synthetic.PHYSICS_DT)
  if relative_speed * fps < MOVING_SPEED:
    motion = 0
  elif not closing:
    motion = 1
  else:
    motion = 2 if 2 * frame <= horizon else 3
  return gap_bin + NUM_GAP_BINS * motion


def has_deflected_question(scene: Scene, simulation: dict[str, Any],
                           config: ClevrerLikeConfig) -> bool:
  """Whether a predictive question can be asked with labels balanced
  within the extrapolation's verdict: among the pairs in view at the end,
  two with the same verdict of which one collides after the video and one
  does not (a hit that gets deflected, a miss turned into a collision by
  an event after the video, or such a pair beside a plain one)."""
  labels: dict[int, set[bool]] = collections.defaultdict(set)
  for _, _, collides, verdict in end_pairs(scene, simulation, config):
    labels[verdict].add(collides)
  return any(len(v) == 2 for v in labels.values())


def has_future_collision(simulation: dict[str, Any],
                         config: ClevrerLikeConfig) -> bool:
  """Whether two objects in view at the last observed frame collide after
  it (what a predictive question can ask about)."""
  in_view = simulation['in_view'][config.observed_frames - 1]
  return any(f >= config.observed_frames and in_view[a] and in_view[b]
             for a, b, f, _ in simulation['collisions'])


def object_radius(shape: str, size: str, object_scale: float) -> float:
  """Radius [m] of the circle covering an object's ground footprint."""
  return synthetic._footprint_radius(  # pylint: disable=protected-access
      SHAPES.index(shape), synthetic.SIZE_RADII[SIZES.index(size)]
      * object_scale)


def extrapolated_clearance(positions: np.ndarray, radii: np.ndarray, a: int,
                           b: int, observed_frames: int, horizon: int
                           ) -> float:
  """Smallest gap [m] between objects a and b over the ``horizon`` frames
  after the video if both kept the velocity of their last two observed
  frames: min_t |centre_a(t) - centre_b(t)| - (radii[a] + radii[b]).

  What "who meets whom" looks like from the observed end alone (on the
  ground plane; friction and other objects ignored). A gap below a small
  margin is this rule's "they will collide".

  Args:
    positions: float [T, O, 2 or 3] object centres of a simulation.
    radii: float [O] footprint radii (:func:`object_radius`).
  """
  return extrapolated_approach(positions, radii, a, b, observed_frames,
                               horizon)[0]


def extrapolated_approach(positions: np.ndarray, radii: np.ndarray, a: int,
                          b: int, observed_frames: int, horizon: int
                          ) -> tuple[float, int, float, bool]:
  """(:func:`extrapolated_clearance`, the frame after the video (1-based)
  when they meet, the pair's relative speed [m / frame] at the end of the
  video, whether they are closing in then). "Meet": the first frame with a
  gap below the contact margin EXTRAPOLATION_BINS[1], or, for a pair that
  stays apart, the frame of the smallest gap."""
  p = np.asarray(positions, np.float64)[..., :2]
  last, velocity = p[observed_frames - 1], (p[observed_frames - 1]
                                            - p[observed_frames - 2])
  steps = np.arange(1, horizon + 1, dtype=np.float64)[:, None]
  gap = np.linalg.norm((last[a] - last[b]) + steps * (velocity[a]
                                                      - velocity[b]), axis=-1)
  gap = gap - radii[a] - radii[b]
  smallest = float(gap.min())
  k = int(np.argmax(gap <= max(smallest, EXTRAPOLATION_BINS[1])))
  relative = velocity[a] - velocity[b]
  return (smallest, k + 1, float(np.linalg.norm(relative)),
          bool(np.dot(last[a] - last[b], relative) < 0.0))


def future_clearance(positions: np.ndarray, radii: np.ndarray, a: int, b: int,
                     observed_frames: int) -> float:
  """As :func:`extrapolated_clearance` over the simulated frames after the
  video (what a perfect dynamics model shows)."""
  p = np.asarray(positions, np.float64)[observed_frames:, :, :2]
  gap = np.linalg.norm(p[:, a] - p[:, b], axis=-1)
  return float(gap.min() - radii[a] - radii[b])


def sample_video_scene(rng: np.random.Generator, config: ClevrerLikeConfig
                       ) -> Scene:
  """The scene of one video: with probability
  ``config.future_collision_fraction`` the first of up to MAX_SCENE_TRIES
  draws whose future has a collision (:func:`has_future_collision`; with
  the 'deflected' design, a balanced predictive question:
  :func:`has_deflected_question`), else the first draw. A pure function of
  ``rng``'s state."""
  # No extra draw at fraction 0: the scenes are those of generator version 1.
  wants_future = (config.future_collision_fraction > 0.0
                  and rng.uniform() < config.future_collision_fraction)
  scene = sample_scene(rng, config)
  if config.predictive_design == 'deflected':
    accept = functools.partial(has_deflected_question, config=config)
  else:
    accept = lambda scene, sim: has_future_collision(sim, config)
  if wants_future:
    for _ in range(MAX_SCENE_TRIES - 1):
      if accept(scene, simulate(scene, config)):
        break
      scene = sample_scene(rng, config)
  return scene


def video_rng(seed: int, split: str, index: int) -> np.random.Generator:
  # A different stream from the OBJ3D-like family for the same seed.
  return np.random.default_rng([seed, SPLITS.index(split), index, 12])


def generate_video(config: ClevrerLikeConfig, split: str, index: int, *,
                   render: bool = True) -> dict[str, Any]:
  """Video ``index`` of ``split`` with its event log (+ counterfactuals).

  Returns the arrays of :func:`simulate` (rendered unless ``render=False``),
  ``shapes``/``colors``/``sizes`` int32 [O] (-1 padding), ``num_objects``,
  ``index``, and ``events``: the :class:`EventLog`, whose counterfactual
  worlds (one per object, physics only) are simulated here too.
  """
  if split not in SPLITS:
    raise ValueError(f'split must be one of {SPLITS}, got {split!r}')
  scene = sample_video_scene(video_rng(config.seed, split, index), config)
  sim = simulate(scene, config, render=render)
  counterfactuals = {k: simulate(scene, config, removed=k)
                     for k in range(scene.num_objects)}
  out = {k: v for k, v in sim.items() if k != 'collisions'}

  def pad(values: np.ndarray) -> np.ndarray:
    padded = np.full((config.max_objects_total,), -1, np.int32)
    padded[:scene.num_objects] = values
    return padded

  out.update(shapes=pad(scene.shapes), colors=pad(scene.colors),
             sizes=pad(scene.sizes),
             num_objects=np.array(scene.num_objects, np.int32),
             index=np.array(index, np.int32),
             events=event_log(scene, sim, config, counterfactuals))
  return out


# ----------------------------------------------------------------------------
# Storage: frames as .npy per split (memory-mapped when read), event logs,
# questions in CLEVRER's layout and the vocabulary (the layout: the module
# docstring)
# ----------------------------------------------------------------------------


def _video_for_worker(config: ClevrerLikeConfig, split: str, index: int
                      ) -> dict[str, Any]:
  video = generate_video(config, split, index)
  video['events'] = video['events'].to_dict()
  return {k: video[k] for k in ARRAY_FIELDS + ('events',)}


def _write_questions(config: ClevrerLikeConfig, root: Path,
                     out: base.Output) -> None:
  """Questions of every split (from its stored event logs) and vocabulary."""
  for split in SPLITS:
    with open(root / split / 'events.jsonl') as f:
      logs = [EventLog.from_dict(json.loads(line)) for line in f]
    scenes = question_generator.generate_split(
        logs, config.seed, split,
        video_filenames=[video_filename(split, i) for i in range(len(logs))],
        scene_offset=SCENE_OFFSETS[split])
    out.write_text(root / 'questions' / vqa.CLEVRER_SPLIT_FILES[split],
                   json.dumps(scenes))
  out.write_text(root / 'vocab.json', vqa.Vocabulary(
      vqa.make_vocabulary(question_generator.template_words()),
      vqa.make_vocabulary(question_generator.template_answers()),
  ).to_json())


def generate(config: ClevrerLikeConfig, out: base.Output) -> Path:
  """Generates videos, event logs, questions and vocabulary unless present.

  A dataset built by an older question generator (``QUESTIONS_VERSION``)
  gets new questions from its stored event logs; its videos are kept.
  Returns the dataset folder. Deterministic: a pure function of ``config``
  (the worker count does not matter).
  """
  root = dataset_dir(config, out.data_dir)
  if is_complete(root):
    return root
  if not (root / COMPLETE).is_file():
    _write_videos(config, root, out)
  _write_questions(config, root, out)
  out.write_text(root / COMPLETE, json.dumps(completion(config)))
  return root


def _write_videos(config: ClevrerLikeConfig, root: Path,
                  out: base.Output) -> None:
  """Frames and event logs of every split."""
  for split in SPLITS:
    count = config.num_videos(split)
    videos = list(out.map(
        functools.partial(_video_for_worker, config, split), count))
    folder = root / split
    if count:
      for field in ARRAY_FIELDS:
        out.save_array(folder / f'{field}.npy',
                       np.stack([v[field] for v in videos]))
    out.write_text(folder / 'events.jsonl',
                   ''.join(json.dumps(v['events']) + '\n' for v in videos))


def features(config: ClevrerLikeConfig) -> tfds.features.FeaturesDict:
  """What :class:`NpyVideoSource` hands out per video (its .npy arrays)."""
  h, w = config.resolution
  t, o = config.num_frames, config.max_objects_total
  return tfds.features.FeaturesDict({
      'video': base.tensor((t, h, w, 3), np.uint8),
      'segmentations': base.tensor((t, h, w), np.uint8),
      'boxes': base.tensor((t, o, 4), np.float32),
      'visible': base.tensor((t, o), np.bool_),
      'num_objects': tfds.features.Scalar(np.int32),
      'index': tfds.features.Scalar(np.int32),
  })


@dataclasses.dataclass(frozen=True)
class ClevrerLike(base.Generated):
  """The CLEVRER-like dataset: .npy folders (no checksums), its questions
  and vocabulary in its folder."""

  def open(self, data_config, split):
    return NpyVideoSource(self.complete_dir(data_config), split)

  def complete_dir(self, data_config) -> Path:
    return complete_dataset_dir(data_config,
                                sources.resolve_data_dir(data_config.data_dir))

  def questions_root(self, data_config) -> Path:
    return self.complete_dir(data_config)

  def video_names(self, data_config, split) -> list[str]:
    count = len(NpyVideoSource(self.complete_dir(data_config), split))
    return [video_filename(split, i) for i in range(count)]


DATASET = base.register(ClevrerLike(
    names=(DATASET_NAME,), label='CLEVRER-like', splits=SPLITS,
    features=functools.partial(features, ClevrerLikeConfig()),
    what='the CLEVRER-like dataset', parameters=config_from_data_config,
    folder=dataset_dir, generate=generate, checksummed=False))
