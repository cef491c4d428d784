"""PHYRE: pre-rendered rollouts (documented layout) and their conversion.

The ``phyre`` simulator has no wheel for Python 3.11, so the project does not
simulate; ``tools/render_phyre.py`` (run where ``pip install phyre`` works)
renders the rollouts once (``train``: the fold's train + dev tasks, ``val``:
its test tasks, 1 frame per simulated second). Stored per rollout (in id
order): ``video`` uint8 [T, H, W, 3] (T = ``Options.num_frames`` = 15,
shorter rollouts padded with their last frame, as officially),
``num_frames``, ``num_moving_frames``, ``label`` (1: the action solves the
task), ``action`` float32 [3], ``task``, ``template``, ``rollout_id``. The
layout and each field: docs/datasets.md, "PHYRE".
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import media
from slotformer_jax.datasets import base
from slotformer_jax.errors import shown
from slotformer_jax.files import UntrustedFileError
from slotformer_jax.files import confined
from slotformer_jax.files import int_in_range
from slotformer_jax.files import read_untrusted_json

logger = logging.getLogger(__name__)

NAME = 'phyre'
SPLITS: tuple[str, ...] = ('train', 'val')
DEFAULT_RESOLUTION = (128, 128)
FORMAT = 'slotformer-phyre-rollouts'
FORMAT_VERSION = 1
META_FILE = 'meta.json'
# rollouts.jsonl of a split: ~150 bytes a rollout.
MAX_INDEX_BYTES = 1 << 30
INDEX_FILE = 'rollouts.jsonl'
FRAMES_DIR = 'frames'
CONVERTER_VERSION = 1
# meta.json fields that change the stored content (part of the folder name).
_META_KEYS = ('tier', 'eval_setup', 'fold', 'fps', 'max_frames', 'background',
              'frame_size', 'data_ratio', 'pos_ratio', 'seed')

LAYOUT = """\
<source>/meta.json
<source>/{train,val}/rollouts.jsonl   (one {"id", "task", "action",
                                        "success", "num_frames"} per line)
<source>/{train,val}/frames/<id>.png  (frames stacked vertically, RGB)
(written by tools/render_phyre.py; see docs/datasets.md)"""


@dataclasses.dataclass(frozen=True)
class Options(base.ConversionOptions):
  """Conversion parameters.

  Attributes:
    resolution: (H, W) of the stored frames.
    num_frames: stored frames per rollout (padded / cut).
  """

  resolution: tuple[int, int] = DEFAULT_RESOLUTION
  num_frames: int = 15
  version = CONVERTER_VERSION


@dataclasses.dataclass(frozen=True)
class RolloutJob:
  """One rollout.

  Attributes:
    key: the rollout id.
    frames: its PNG.
    task: 'TTTTT:VVV'.
    action: (x, y, r).
    success: simulation outcome.
    num_frames: frames the PNG holds.
    frame_size: (h, w) of one frame, from meta.json.
    problem: why the index line is unusable (the rollout is skipped), or
      None.
  """

  key: str
  frames: Path
  task: str = ''
  action: tuple[float, float, float] = (0.0, 0.0, 0.0)
  success: bool = False
  num_frames: int = 0
  frame_size: tuple[int, int] = (256, 256)
  problem: str | None = None


layout_error = functools.partial(
    base.layout_error, 'PHYRE', LAYOUT,
    what='the layout written by tools/render_phyre.py')


def read_meta(source: Path) -> dict[str, Any]:
  """meta.json, checked.

  Raises:
    FileNotFoundError: no meta.json.
    ValueError: not this format, or a field is missing.
  """
  path = source / META_FILE
  if not path.is_file():
    raise layout_error(source, path)
  meta = read_untrusted_json(path, what='PHYRE meta file', max_bytes=1 << 20,
                             max_depth=4)
  if not isinstance(meta, dict):
    raise UntrustedFileError(f'{path} is a {type(meta).__name__}, not an '
                             'object')
  if meta.get('format') != FORMAT:
    raise UntrustedFileError(f'{path}: "format" is '
                             f'{shown(repr(meta.get("format")), 80)}, '
                             f'expected {FORMAT!r}')
  if meta.get('format_version') != FORMAT_VERSION:
    raise UntrustedFileError(
        f'{path}: format_version '
        f'{shown(repr(meta.get("format_version")), 40)} is not supported '
        f'(expected {FORMAT_VERSION})')
  missing = [k for k in ('frame_size', 'fps', 'eval_setup', 'fold')
             if k not in meta]
  if missing:
    raise UntrustedFileError(f'{path}: missing fields {missing}')
  size = meta['frame_size']
  if not (isinstance(size, list) and len(size) == 2 and all(
      isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 4096
      for v in size)):
    raise UntrustedFileError(f'{path}: frame_size '
                             f'{shown(repr(size), 60)} is not [h, w] in '
                             '1..4096')
  # Both name the output folder (`dataset_spec`): plain names only.
  if not (isinstance(meta['eval_setup'], str)
          and re.fullmatch(r'[A-Za-z0-9_]{1,64}', meta['eval_setup'])):
    raise UntrustedFileError(f'{path}: eval_setup '
                             f'{shown(repr(meta["eval_setup"]), 80)} is not '
                             'a PHYRE eval setup name')
  int_in_range(meta['fold'], 0, 2**31 - 1, what=f'{path}: fold')
  return meta


def _field(entry: dict[str, Any], key: str, kinds: tuple[type, ...]) -> Any:
  value = entry[key]
  if isinstance(value, bool) and bool not in kinds or not isinstance(
      value, kinds):
    raise TypeError(f'{key} is {shown(repr(value), 60)}')
  return value


def _job_from_line(line: str, number: int, split_dir: Path,
                   frame_size: tuple[int, int]) -> RolloutJob:
  """A rollout of the index; a line that is not one (bad JSON or fields, an
  id that would lead out of the frames folder) becomes a job that is
  skipped, naming the line."""
  try:
    entry = json.loads(line)
    if not isinstance(entry, dict):
      raise TypeError('the line is not a JSON object')
    key = _field(entry, 'id', (str, int))
    key = str(key)
    frames = confined(split_dir / FRAMES_DIR, f'{key}.png',
                      what='the rollout id')
    action = _field(entry, 'action', (list,))
    if len(action) != 3 or not all(
        isinstance(a, (int, float)) and not isinstance(a, bool)
        for a in action):
      raise ValueError(f'action {shown(repr(action), 60)} is not 3 numbers')
    num_frames = _field(entry, 'num_frames', (int,))
    if not 1 <= num_frames <= 10_000:
      raise ValueError(f'num_frames {num_frames} is not in 1..10000')
    task = _field(entry, 'task', (str,))
    template = task.split(':')[0]
    if re.fullmatch('[0-9]+', template):  # stored as int32
      int_in_range(int(template), 0, 2**31 - 1,
                   what='the task\'s template number')
    return RolloutJob(
        key=key, frames=frames, task=task,
        action=tuple(float(a) for a in action),
        success=_field(entry, 'success', (bool,)), num_frames=num_frames,
        frame_size=frame_size)
  except (KeyError, TypeError, ValueError, RecursionError,
          OverflowError) as error:  # OverflowError: an action of 10**400
    return RolloutJob(key=f'line_{number}', frames=split_dir / FRAMES_DIR,
                      problem=f'{split_dir / INDEX_FILE}:{number}: '
                      f'{type(error).__name__}: {shown(str(error), 200)}')


def discover(source: Path, split: str, options: Options) -> list[RolloutJob]:
  """The rollouts of ``split``, in id order.

  Raises:
    FileNotFoundError: meta.json, the split folder or its index is missing.
  """
  del options
  meta = read_meta(source)
  frame_size = tuple(int(v) for v in meta['frame_size'])
  split_dir = source / split
  index = split_dir / INDEX_FILE
  if not index.is_file():
    raise layout_error(source, index)
  if not (split_dir / FRAMES_DIR).is_dir():
    raise layout_error(source, split_dir / FRAMES_DIR)
  if index.stat().st_size > MAX_INDEX_BYTES:
    raise UntrustedFileError(f'{index} holds {index.stat().st_size} bytes, '
                             f'more than the {MAX_INDEX_BYTES} an index may '
                             'have')
  jobs = []
  with open(index, encoding='utf-8', errors='replace') as f:
    for number, line in enumerate(f, start=1):
      if line.strip():
        jobs.append(_job_from_line(line, number, split_dir, frame_size))
  if not jobs:
    raise layout_error(source, index, ' (it lists no rollout)')
  return sorted(jobs, key=lambda job: media.natural_key(job.key))


def num_moving_frames(frames: np.ndarray) -> int:
  """Frames up to the first one identical to its successor (all if none).

  Counted within the stored frames (the rollout cut to ``num_frames``), so
  it is ``min(moving frames of the whole simulation, num_frames)``. The
  official helper has one quirk we do not copy: when frames 0 and 1 are
  already identical it reports every frame as moving; here that gives 1.
  """
  same = (frames[1:] == frames[:-1]).reshape(len(frames) - 1, -1).all(axis=1)
  return int(same.argmax()) + 1 if same.any() else len(frames)


def convert_rollout(job: RolloutJob, options: Options) -> dict[str, Any]:
  """Splits a rollout's PNG into frames, pads / cuts them and resizes.

  Raises:
    media.SkipVideo: broken index line, unreadable PNG, wrong size / count.
  """
  if job.problem is not None:
    raise media.SkipVideo('bad_annotation', job.problem)
  strip = media.read_image(job.frames)
  height, width = job.frame_size
  if strip.shape[1] != width or strip.shape[0] % height:
    raise media.SkipVideo(
        'frame_size_mismatch',
        f'{job.frames} is {strip.shape[1]}x{strip.shape[0]} (WxH); expected '
        f'frames of {width}x{height} stacked vertically')
  count = strip.shape[0] // height
  if count != job.num_frames or count < 1:
    raise media.SkipVideo(
        'frame_count_mismatch',
        f'{job.frames} holds {count} frames, its index line says '
        f'{job.num_frames}')
  frames = strip.reshape(count, height, width, 3)[:options.num_frames]
  moving = num_moving_frames(frames)
  real = len(frames)
  if real < options.num_frames:
    frames = np.concatenate(
        [frames, np.repeat(frames[-1:], options.num_frames - real, axis=0)])
  template = job.task.split(':')[0]
  return {
      'video': media.resize_frames(frames, options.resolution),
      'num_frames': real,
      'num_moving_frames': moving,
      'label': int(job.success),
      'action': np.asarray(job.action, np.float32),
      'task': job.task,
      'template': (int(template) if re.fullmatch('[0-9]+', template)
                   else -1),
      'rollout_id': job.key,
  }


def features(options: Options) -> tfds.features.FeaturesDict:
  h, w = options.resolution
  return tfds.features.FeaturesDict({
      'video': base.tensor((options.num_frames, h, w, 3), np.uint8),
      'num_frames': tfds.features.Scalar(np.int32),
      'num_moving_frames': tfds.features.Scalar(np.int32),
      'label': tfds.features.Scalar(np.int32),
      'action': base.tensor((3,), np.float32),
      'task': tfds.features.Text(),
      'template': tfds.features.Scalar(np.int32),
      'rollout_id': tfds.features.Text(),
  })


def _meta_params(meta: Mapping[str, Any]) -> dict[str, Any]:
  return {k: meta[k] for k in _META_KEYS if k in meta}


def conversion(options: Options, source: Path) -> base.Conversion:
  """Reads meta.json: the rollouts' parameters are part of the folder name."""
  meta = _meta_params(read_meta(source))
  params = {**dataclasses.asdict(options), 'rollouts': meta,
            'converter_version': CONVERTER_VERSION}
  h, w = options.resolution
  readable = (f'{meta.get("eval_setup", "unknown")}_fold{meta.get("fold")}'
              f'_r{h}x{w}_t{options.num_frames}')
  return base.Conversion(
      name=NAME, config_name=base.digest_name(readable, params),
      description=(f'PHYRE rollouts ({json.dumps(meta, sort_keys=True)}), '
                   f'{options.num_frames} frames at {h}x{w}, success labels.'),
      params=params,
      features_fn=functools.partial(features, options),
      convert_fn=functools.partial(convert_rollout, options=options))


DATASET = base.register(base.Converted(
    names=(NAME,), label='PHYRE', command=NAME, splits=SPLITS, layout=LAYOUT,
    features=functools.partial(features, Options()),
    # The official models read the rendered frames as RGB.
    official_channel_order='rgb',
    options=Options, discover=discover, conversion=conversion))
