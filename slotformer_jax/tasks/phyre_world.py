"""The world of the embedded PHYRE-like 2-D planning benchmark (pymunk).

PHYRE (Bakhtin et al., 2019; SlotFormer Section 4.4) asks for one action, a
red ball ``(x, y, r)`` in [0, 1]^3 placed in the first frame, that makes the
green object touch the goal for long enough. ``phyre`` has no wheel for this
Python, so this module builds a look-alike on pymunk: a *template* is a scene
recipe, a *task* one instance of it (:func:`make_task`, a pure function of
``(seed, template, task index)``); an action is INVALID when the ball leaves
the scene or overlaps a body, SOLVED when green and goal touch for
``success_seconds`` without a break. Every task is scored on one fixed set of
candidate actions, and tasks are split within each template by ``fold``.

Planning uses it at run time (tasks/phyre_planning.py); the data stage
writes the labels and training videos with it (datasets/synthetic_phyre.py,
folders named by :class:`PhyreLikeConfig`). The world, its templates and
renderer: docs/downstream.md, "PHYRE-style planning".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
import pymunk

from slotformer_jax.data.supersample import downsample_rgb
from slotformer_jax.data.supersample import downsample_segmentation

# The first templates (the default set: their tasks and cached datasets must
# not change) and templates added later, which a config selects by name.
TEMPLATES: tuple[str, ...] = ('ledge', 'tower', 'stack')
ALL_TEMPLATES: tuple[str, ...] = TEMPLATES + ('ramp',)


@dataclasses.dataclass(frozen=True)
class PhyreLikeConfig:
  """Generation parameters.

  Attributes:
    resolution: (H, W) of rendered frames.
    fps: rendered frames per simulated second (PHYRE/SlotFormer: 1).
    sim_seconds: simulated time; frames = fps * sim_seconds + 1.
    success_seconds: continuous green-goal contact needed to solve.
    templates: which templates to use.
    tasks_per_template: tasks drawn per template.
    num_candidates: size of the fixed candidate action set.
    train_share: share of each template's tasks used for training.
    fold: which within-template train/test shuffle.
    seed: base seed of tasks and candidate actions.
    max_instances: mask ids 1..max_instances (bodies of a task + red ball).
  """

  resolution: tuple[int, int] = (64, 64)
  fps: int = 2
  sim_seconds: float = 5.0
  success_seconds: float = 1.0
  templates: tuple[str, ...] = TEMPLATES
  tasks_per_template: int = 25
  num_candidates: int = 200
  train_share: float = 0.8
  fold: int = 0
  seed: int = 0
  max_instances: int = 8

  def __post_init__(self):
    object.__setattr__(self, 'resolution',
                       tuple(int(r) for r in self.resolution))
    object.__setattr__(self, 'templates', tuple(self.templates))
    unknown = set(self.templates) - set(ALL_TEMPLATES)
    if unknown:
      raise ValueError(f'unknown templates {sorted(unknown)}; '
                       f'choose from {ALL_TEMPLATES}')
    if self.success_seconds > self.sim_seconds:
      raise ValueError('success_seconds must be <= sim_seconds')
    if not 0.0 < self.train_share < 1.0:
      raise ValueError(f'train_share must be in (0, 1), got {self.train_share}')

  @property
  def num_frames(self) -> int:
    return int(round(self.fps * self.sim_seconds)) + 1


def config_from_data_config(data_config: Any) -> PhyreLikeConfig:
  fields = {f.name for f in dataclasses.fields(PhyreLikeConfig)}
  return PhyreLikeConfig(**{key: data_config[key] for key in fields
                            if key in data_config})

WORLD = 10.0                    # [m], the scene is WORLD x WORLD
GRAVITY = 9.8                   # [m/s^2]
PHYSICS_DT = 1.0 / 60.0         # [s]
SOLVER_ITERATIONS = 20
COLLISION_SLOP = 0.005          # [m]; pymunk's default 0.1 is for pixels
FRICTION = 0.6
ELASTICITY = 0.2
DENSITY = 1.0                   # mass = DENSITY * area
MIN_ACTION_RADIUS, MAX_ACTION_RADIUS = 0.3, 1.0   # [m]
GOAL_THICKNESS = 0.15           # [m]

# Kinds of body, in drawing order (later ones are drawn on top).
STATIC, DYNAMIC, GOAL, GREEN, ACTION = 'static', 'dynamic', 'goal', 'green', 'red'
KIND_RGB: dict[str, tuple[int, int, int]] = {
    STATIC: (0, 0, 0),
    DYNAMIC: (128, 128, 128),
    GOAL: (128, 0, 160),
    GREEN: (40, 180, 40),
    ACTION: (220, 30, 30),
}
BACKGROUND_RGB = (255, 255, 255)

SOLVED, NOT_SOLVED, INVALID = 1, 0, -1   # as tasks/planning.py


@dataclasses.dataclass(frozen=True)
class Body:
  """One body of a task. ``shape`` 'ball' uses ``radius``; 'box' uses
  ``size`` (width, height); position is the centre [m], y up."""

  kind: str
  shape: str
  position: tuple[float, float]
  radius: float = 0.0
  size: tuple[float, float] = (0.0, 0.0)
  angle: float = 0.0              # [rad], counter-clockwise (ramps)


@dataclasses.dataclass(frozen=True)
class Task:
  """A template instance: its bodies (the goal, the green one among them)."""

  template: str
  index: int
  bodies: tuple[Body, ...]


# ----------------------------------------------------------------------------
# Templates
# ----------------------------------------------------------------------------


def _goal_strip(side: int, start_x: float) -> Body:
  """A purple strip on the floor from ``start_x`` to the wall of ``side``
  (-1 left, +1 right)."""
  end = WORLD if side > 0 else 0.0
  lo, hi = sorted((start_x, end))
  return Body(GOAL, 'box', ((lo + hi) / 2, GOAL_THICKNESS / 2),
              size=(hi - lo, GOAL_THICKNESS))


def _ledge(rng: np.random.Generator) -> list[Body]:
  """Green ball resting on a static ledge; push it off towards the goal."""
  width, height = rng.uniform(2.0, 3.5), rng.uniform(3.0, 6.0)
  cx = rng.uniform(3.5, 6.5)
  radius = rng.uniform(0.4, 0.7)
  side = int(rng.choice([-1, 1]))
  edge = cx + side * width / 2
  # The ball sits nearer the goal's edge: a push that way solves the task,
  # a push the other way drops it on the wrong side.
  ball_x = edge - side * rng.uniform(0.2, 0.6)
  return [
      Body(STATIC, 'box', (cx, height), size=(width, 0.3)),
      _goal_strip(side, edge + side * rng.uniform(0.0, 1.0)),
      Body(GREEN, 'ball', (ball_x, height + 0.15 + radius), radius=radius),
  ]


def _tower(rng: np.random.Generator) -> list[Body]:
  """A tall green bar standing on the floor; tip it onto the goal."""
  width, height = rng.uniform(0.4, 0.6), rng.uniform(2.0, 3.2)
  x = rng.uniform(3.5, 6.5)
  side = int(rng.choice([-1, 1]))
  bodies = [
      _goal_strip(side, x + side * rng.uniform(0.6, 0.9) * height),
      Body(GREEN, 'box', (x, height / 2),
           size=(width, height)),
  ]
  # A static block on the other side so that not every push works.
  if rng.random() < 0.5:
    bodies.insert(0, Body(STATIC, 'box', (x - side * 1.5, 0.5),
                          size=(0.4, 1.0)))
  return bodies


def _stack(rng: np.random.Generator) -> list[Body]:
  """A green ball on a gray box on the floor; knock it onto the goal."""
  box_w, box_h = rng.uniform(0.8, 1.4), rng.uniform(1.0, 2.5)
  x = rng.uniform(3.5, 6.5)
  radius = rng.uniform(0.35, 0.6)
  side = int(rng.choice([-1, 1]))
  return [
      _goal_strip(side, x + side * rng.uniform(0.8, 1.6)),
      Body(DYNAMIC, 'box', (x, box_h / 2), size=(box_w, box_h)),
      Body(GREEN, 'ball', (x + rng.uniform(-0.2, 0.2) * box_w,
                           box_h + radius), radius=radius),
  ]


def _mirror(bodies: list[Body], side: int) -> list[Body]:
  """Bodies built with the goal on the right, mirrored when ``side`` < 0."""
  if side > 0:
    return bodies
  return [dataclasses.replace(b, position=(WORLD - b.position[0],
                                           b.position[1]), angle=-b.angle)
          for b in bodies]


def _ramp_box(low_end: tuple[float, float], length: float, angle: float,
              thickness: float = 0.3) -> Body:
  """A static plank whose top surface descends at ``angle`` (rad, > 0: down
  to the right) to its lower end ``low_end`` (the top-right corner)."""
  c, s = np.cos(angle), np.sin(angle)
  # From the top-right corner to the centre: half a length up the slope
  # (-c, s), half a thickness down the normal (-s, -c).
  cx = low_end[0] - c * length / 2 - s * thickness / 2
  cy = low_end[1] + s * length / 2 - c * thickness / 2
  return Body(STATIC, 'box', (cx, cy), size=(length, thickness), angle=-angle)


def _first_floor_touch(bodies: Sequence[Body], limit_s: float = 5.0
                       ) -> float | None:
  """x [m] where the green ball of ``bodies`` (simulated alone, no action)
  first comes within 5 cm of the floor; None if it does not in ``limit_s``."""
  space, shapes = _build_space(bodies)
  green = next(s for s, b in zip(shapes, bodies) if b.kind == GREEN)
  for _ in range(int(round(limit_s / PHYSICS_DT))):
    space.step(PHYSICS_DT)
    if green.body.position.y <= green.radius + 0.05:
      return float(green.body.position.x)
  return None


def _ramp(rng: np.random.Generator) -> list[Body]:
  """The green ball starts at the top of a static ramp and rolls at once;
  launched off the ramp's end it flies OVER a goal basket (a purple strip
  with a static lip at its far end) and lands beyond it.

  Nothing in the first frame is in contact: the red ball must meet the
  moving green ball (block it on the ramp, knock it down in flight, ...) so
  that it ends in the basket. Where the green ball will be, and when, is what
  the frames after the first show.
  """
  side = int(rng.choice([-1, 1]))
  for _ in range(100):  # until the unperturbed ball lands in the open
    angle = np.deg2rad(rng.uniform(20.0, 35.0))
    length = rng.uniform(2.5, 3.5)
    low_end = (rng.uniform(2.0, 3.5), rng.uniform(2.0, 3.5))
    ramp = _ramp_box(low_end, length, angle)
    radius = rng.uniform(0.4, 0.55)
    c, s = np.cos(angle), np.sin(angle)
    along = length - radius - 0.1  # from the lower end, up the slope
    green = Body(GREEN, 'ball', (low_end[0] - c * along + s * radius,
                                 low_end[1] + s * along + c * radius),
                 radius=radius)
    landing = _first_floor_touch([ramp, green])
    if landing is None:
      continue
    lip_x = landing - rng.uniform(0.4, 0.9)
    lip_h = rng.uniform(0.5, 0.9)
    goal_w = rng.uniform(2.0, 3.5)
    if lip_x - goal_w < 0.3 or lip_x > WORLD - 1.0:
      continue
    lo = lip_x - 0.15 - goal_w
    bodies = [ramp,
              Body(STATIC, 'box', (lip_x, lip_h / 2), size=(0.3, lip_h)),
              Body(GOAL, 'box', (lo + goal_w / 2, GOAL_THICKNESS / 2),
                   size=(goal_w, GOAL_THICKNESS)),
              green]
    return _mirror(bodies, side)
  raise RuntimeError('no ramp layout found')


_TEMPLATE_BUILDERS = {'ledge': _ledge, 'tower': _tower, 'stack': _stack,
                      'ramp': _ramp}


def make_task(config: PhyreLikeConfig, template: str, index: int) -> Task:
  """Task ``index`` of ``template``; a pure function of its arguments."""
  rng = np.random.default_rng(
      [config.seed, 7, ALL_TEMPLATES.index(template), index])
  bodies = tuple(_TEMPLATE_BUILDERS[template](rng))
  if len(bodies) + 1 > config.max_instances:
    raise ValueError(f'{template} needs {len(bodies) + 1} mask ids, '
                     f'max_instances is {config.max_instances}')
  return Task(template, index, bodies)


def all_tasks(config: PhyreLikeConfig) -> list[Task]:
  return [make_task(config, template, i) for template in config.templates
          for i in range(config.tasks_per_template)]


def split_tasks(config: PhyreLikeConfig) -> dict[str, list[Task]]:
  """Within-template folds: a share of every template's tasks for training.

  Returns {'train': [...], 'test': [...]}; the shuffle depends on ``fold``.
  """
  splits: dict[str, list[Task]] = {'train': [], 'test': []}
  for template in config.templates:
    order = np.random.default_rng(
        [config.seed, 11, ALL_TEMPLATES.index(template), config.fold]).permutation(
            config.tasks_per_template)
    num_train = int(round(config.train_share * config.tasks_per_template))
    for rank, i in enumerate(order):
      task = make_task(config, template, int(i))
      splits['train' if rank < num_train else 'test'].append(task)
  return splits


def candidate_actions(config: PhyreLikeConfig) -> np.ndarray:
  """float64 [num_candidates, 3]: the fixed action set, (x, y, r) in [0, 1]."""
  return np.random.default_rng([config.seed, 13]).random(
      (config.num_candidates, 3))


def action_ball(action: Sequence[float]) -> Body:
  x, y, r = (float(a) for a in action)
  radius = MIN_ACTION_RADIUS + r * (MAX_ACTION_RADIUS - MIN_ACTION_RADIUS)
  return Body(ACTION, 'ball', (x * WORLD, y * WORLD), radius=radius)


# ----------------------------------------------------------------------------
# Physics
# ----------------------------------------------------------------------------


def _add_body(space: pymunk.Space, body: Body) -> pymunk.Shape:
  static = body.kind in (STATIC, GOAL)
  if static:
    handle = pymunk.Body(body_type=pymunk.Body.STATIC)
  elif body.shape == 'ball':
    mass = DENSITY * np.pi * body.radius**2
    handle = pymunk.Body(mass, pymunk.moment_for_circle(mass, 0, body.radius))
  else:
    mass = DENSITY * body.size[0] * body.size[1]
    handle = pymunk.Body(mass, pymunk.moment_for_box(mass, body.size))
  handle.position = body.position
  handle.angle = body.angle
  if body.shape == 'ball':
    shape = pymunk.Circle(handle, body.radius)
  else:
    shape = pymunk.Poly.create_box(handle, body.size)
  shape.friction, shape.elasticity = FRICTION, ELASTICITY
  space.add(handle, shape)
  return shape


def _build_space(bodies: Sequence[Body]) -> tuple[pymunk.Space,
                                                  list[pymunk.Shape]]:
  space = pymunk.Space()
  space.gravity = (0.0, -GRAVITY)
  space.iterations = SOLVER_ITERATIONS
  space.collision_slop = COLLISION_SLOP
  # Invisible floor and walls, as PHYRE's scene borders.
  border = space.static_body
  for a, b in (((0, 0), (WORLD, 0)), ((0, 0), (0, 3 * WORLD)),
               ((WORLD, 0), (WORLD, 3 * WORLD))):
    segment = pymunk.Segment(border, a, b, 0.0)
    segment.friction, segment.elasticity = FRICTION, ELASTICITY
    space.add(segment)
  return space, [_add_body(space, body) for body in bodies]


def is_valid(task: Task, action: Sequence[float]) -> bool:
  """The red ball lies inside the scene and overlaps no body."""
  ball = action_ball(action)
  (x, y), r = ball.position, ball.radius
  if not (r <= x <= WORLD - r and r <= y <= WORLD - r):
    return False
  space, _ = _build_space(task.bodies)
  holder = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
  holder.position = (x, y)
  probe = pymunk.Circle(holder, r)
  probe.cache_bb()
  return not [hit for hit in space.shape_query(probe)
              if hit.shape.body is not space.static_body]


def _touching(a: pymunk.Shape, b: pymunk.Shape) -> bool:
  """Whether the last step left a contact between shapes ``a`` and ``b``
  (an arbiter of ``a``'s body with contact points on ``b``)."""
  found = []

  def check(arbiter: pymunk.Arbiter) -> None:
    if b in arbiter.shapes and a in arbiter.shapes and (
        arbiter.contact_point_set.points):
      found.append(True)

  a.body.each_arbiter(check)
  return bool(found)


def simulate(task: Task, action: Sequence[float] | None,
             config: PhyreLikeConfig, *, record: bool = False) -> dict:
  """Simulates a task with the red ball of ``action`` (None: no ball).

  Returns:
    outcome: SOLVED / NOT_SOLVED / INVALID (no simulation when invalid).
    With ``record`` (and a valid action): ``states``, per rendered frame the
      list of (position, angle) of every body (task bodies then the ball).
  """
  if action is not None and not is_valid(task, action):
    return {'outcome': INVALID}
  bodies = list(task.bodies) + ([action_ball(action)] if action is not None
                                else [])
  space, shapes = _build_space(bodies)
  kinds = [b.kind for b in bodies]
  green, goal = shapes[kinds.index(GREEN)], shapes[kinds.index(GOAL)]
  steps_per_frame = int(round(1.0 / (config.fps * PHYSICS_DT)))
  num_steps = (config.num_frames - 1) * steps_per_frame
  needed = int(round(config.success_seconds / PHYSICS_DT))
  run, solved = 0, False
  states = []

  def snapshot():
    states.append([(tuple(s.body.position), float(s.body.angle))
                   for s in shapes])

  if record:
    snapshot()
  for step in range(1, num_steps + 1):
    space.step(PHYSICS_DT)
    run = run + 1 if _touching(green, goal) else 0
    solved = solved or run >= needed
    if record and step % steps_per_frame == 0:
      snapshot()
    elif solved and not record:
      break
  result = {'outcome': SOLVED if solved else NOT_SOLVED}
  if record:
    result['states'] = states
    result['bodies'] = bodies
  return result


def label_candidates(task: Task, actions: np.ndarray,
                     config: PhyreLikeConfig) -> np.ndarray:
  """int8 [num_candidates]: the simulated outcome of every candidate."""
  return np.array([simulate(task, a, config)['outcome'] for a in actions],
                  np.int8)


# ----------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------


def _box_corners(center, size, angle) -> np.ndarray:
  w, h = size[0] / 2, size[1] / 2
  local = np.array([[-w, -h], [w, -h], [w, h], [-w, h]])
  c, s = np.cos(angle), np.sin(angle)
  return local @ np.array([[c, s], [-s, c]]) + np.asarray(center)


def _inside(body: Body, center, angle, px: np.ndarray, py: np.ndarray
            ) -> np.ndarray:
  """bool mask of world points (px, py) covered by ``body`` at this pose."""
  if body.shape == 'ball':
    return (px - center[0])**2 + (py - center[1])**2 <= body.radius**2
  corners = _box_corners(center, body.size, angle)
  inside = np.ones(px.shape, bool)
  for i in range(4):  # counter-clockwise: inside = left of every edge
    (x0, y0), (x1, y1) = corners[i], corners[(i + 1) % 4]
    inside &= (x1 - x0) * (py - y0) - (y1 - y0) * (px - x0) >= 0
  return inside


def render_state(bodies: Sequence[Body], poses, resolution: tuple[int, int],
                 supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
  """One frame: uint8 [H, W, 3] RGB and uint8 [H, W] ids (body k -> k + 1)."""
  height, width = resolution
  hs, ws = height * supersample, width * supersample
  # Pixel centres in world coordinates; row 0 is the top of the scene.
  ys = (hs - 0.5 - np.arange(hs)) / hs * WORLD
  xs = (np.arange(ws) + 0.5) / ws * WORLD
  px, py = np.meshgrid(xs, ys)
  ids = np.zeros((hs, ws), np.uint8)
  order = sorted(range(len(bodies)),
                 key=lambda k: list(KIND_RGB).index(bodies[k].kind))
  palette = np.array([BACKGROUND_RGB] + [KIND_RGB[b.kind] for b in bodies],
                     np.uint8)
  for k in order:
    center, angle = poses[k]
    ids[_inside(bodies[k], center, angle, px, py)] = k + 1
  rgb = downsample_rgb(palette[ids], supersample)
  return rgb, downsample_segmentation(ids, supersample)


def render_video(task: Task, action: Sequence[float] | None,
                 config: PhyreLikeConfig) -> dict[str, np.ndarray]:
  """The rollout of a valid action as a video.

  Returns:
    video: uint8 [T, H, W, 3]; segmentations: uint8 [T, H, W] (body k of the
    task -> k + 1, the red ball -> len(task.bodies) + 1); outcome: int8 [].
  """
  result = simulate(task, action, config, record=True)
  if result['outcome'] == INVALID:
    raise ValueError('cannot render an invalid action')
  frames, masks = zip(*(render_state(result['bodies'], poses,
                                     config.resolution)
                        for poses in result['states']))
  return {'video': np.stack(frames), 'segmentations': np.stack(masks),
          'outcome': np.array(result['outcome'], np.int8)}


def layout_tasks(config: PhyreLikeConfig, count: int) -> list[Task]:
  """``count`` extra layouts of every template, never a labelled task.

  Their indices start at ``tasks_per_template``, so no fold's train, dev or
  test task is among them; they do not depend on the fold."""
  return [make_task(config, template, config.tasks_per_template + j)
          for template in config.templates for j in range(count)]
