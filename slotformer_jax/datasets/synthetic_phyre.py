"""The PHYRE-like embedded dataset ('synthetic_phyre'): the simulated label
of every candidate action on every task, and the SAVi / SlotFormer training
videos.

The tasks, physics, rendering and their parameters
(:class:`PhyreLikeConfig`) are the world's (tasks/phyre_world.py); here, the
files they name under ``<data_dir>/synthetic_phyre/`` and how they are made
(by the data stage):

* ``<slug>/labels.npz``: the simulated outcome of every candidate action on
  every task (planning reads them: :func:`load_task_labels`);
* ``<slug>_v<train>-<val>_p<ratio>[_l<layouts>]/2.0.0``: the training videos
  (TFDS, :func:`video_dataset_dir`).
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
import tensorflow_datasets as tfds

from slotformer_jax.data import sources
from slotformer_jax.datasets import base
from slotformer_jax.tasks.phyre_world import INVALID
from slotformer_jax.tasks.phyre_world import SOLVED
from slotformer_jax.tasks.phyre_world import PhyreLikeConfig
from slotformer_jax.tasks.phyre_world import Task
from slotformer_jax.tasks.phyre_world import all_tasks
from slotformer_jax.tasks.phyre_world import candidate_actions
from slotformer_jax.tasks.phyre_world import config_from_data_config
from slotformer_jax.tasks.phyre_world import label_candidates
from slotformer_jax.tasks.phyre_world import layout_tasks
from slotformer_jax.tasks.phyre_world import make_task
from slotformer_jax.tasks.phyre_world import render_video
from slotformer_jax.tasks.phyre_world import split_tasks

GENERATOR_VERSION = 1

NAME = 'synthetic_phyre'


def slug(config: PhyreLikeConfig) -> str:
  """A folder name unique to the generation parameters (+ code version)."""
  payload = json.dumps({**dataclasses.asdict(config),
                        'generator_version': GENERATOR_VERSION},
                       sort_keys=True)
  digest = hashlib.sha256(payload.encode()).hexdigest()[:8]
  h, w = config.resolution
  return (f'r{h}x{w}_f{config.fps}_t{config.sim_seconds:g}'
          f'_k{config.success_seconds:g}_{len(config.templates)}x'
          f'{config.tasks_per_template}_c{config.num_candidates}'
          f'_fold{config.fold}_s{config.seed}_{digest}')


def video_generation(data_config: Any) -> tuple[PhyreLikeConfig, int]:
  """(generation parameters, layouts per template) of the training videos
  a run's ``config.data`` names. With ``data.dynamics_layouts`` > 0 the
  videos show that many extra layouts per template instead of the fold's
  training tasks, which do not depend on the fold: one dataset (of fold 0)
  serves every fold."""
  config = config_from_data_config(data_config)
  layouts = int(data_config.dynamics_layouts)
  if layouts < 0:
    raise ValueError(f'data.dynamics_layouts must be >= 0, got {layouts}')
  if layouts:
    config = dataclasses.replace(config, fold=0)
  return config, layouts


def video_slug(config: PhyreLikeConfig, num_train: int, num_val: int,
               positive_ratio: float, layouts: int = 0) -> str:
  """The folder name of the training videos (see :func:`video_generation`)."""
  layout_part = f'_l{layouts}' if layouts else ''
  return (f'{slug(config)}_v{num_train}-{num_val}_p{positive_ratio:g}'
          f'{layout_part}')


def video_dataset_dir(data_config: Any, data_dir: str | os.PathLike[str]
                      ) -> Path:
  """The TFDS version folder of the training videos of ``config.data``."""
  return videos_dir(videos_of(data_config), data_dir)


def labels_path(config: PhyreLikeConfig, data_dir: str | os.PathLike[str]
                ) -> Path:
  """Where the outcomes of every candidate on every task are stored."""
  return Path(data_dir) / NAME / slug(config) / 'labels.npz'


def task_keys(config: PhyreLikeConfig) -> list[tuple[str, int]]:
  """(template, task index) of every task, templates in config order."""
  return [(template, i) for template in config.templates
          for i in range(config.tasks_per_template)]


def load_task_labels(config: PhyreLikeConfig,
                     data_dir: str | os.PathLike[str]
                     ) -> dict[tuple[str, int], np.ndarray]:
  """{(template, index): int8 [num_candidates]} (SOLVED / NOT_SOLVED /
  INVALID) of every task, as the data stage stored them.

  Raises:
    MissingInputError: they are not generated yet (names the command).
  """
  path = labels_path(config, data_dir)
  if not path.is_file():
    raise sources.not_generated('the PHYRE-like task labels', path)
  with np.load(path) as stored:
    return {key: stored[f'{key[0]}_{key[1]}'] for key in task_keys(config)}


# ----------------------------------------------------------------------------
# Generating
# ----------------------------------------------------------------------------


def build_task_labels(config: PhyreLikeConfig, out: base.Output
                      ) -> dict[tuple[str, int], np.ndarray]:
  """{(template, index): int8 [num_candidates]} for every task, simulated
  unless stored (~1 s per task) in :func:`labels_path`."""
  path = labels_path(config, out.data_dir)
  if path.is_file():
    return load_task_labels(config, out.data_dir)
  return _simulate_and_store(config, all_tasks(config), path, out)


def layout_labels(config: PhyreLikeConfig, count: int, out: base.Output
                  ) -> dict[tuple[str, int], np.ndarray]:
  """The simulated outcomes of every candidate on :func:`layout_tasks`
  (stored; ~1 s per layout), used only to mix solving actions into the
  dynamics videos as on labelled tasks."""
  unfolded = dataclasses.replace(config, fold=0)
  path = out.data_dir / NAME / slug(unfolded) / f'layouts_{count}.npz'
  tasks = layout_tasks(config, count)
  if path.is_file():
    with np.load(path) as stored:
      return {(t.template, t.index): stored[f'{t.template}_{t.index}']
              for t in tasks}
  return _simulate_and_store(config, tasks, path, out)


def _simulate_and_store(config: PhyreLikeConfig, tasks: list[Task],
                        path: Path, out: base.Output
                        ) -> dict[tuple[str, int], np.ndarray]:
  actions = candidate_actions(config)
  labels = {(t.template, t.index): label_candidates(t, actions, config)
            for t in tasks}
  out.save_arrays(path, {f'{k[0]}_{k[1]}': v for k, v in labels.items()})
  return labels


def training_video(config: PhyreLikeConfig,
                   labels: dict[tuple[str, int], np.ndarray],
                   positive_ratio: float, split: str, index: int,
                   layouts: int = 0) -> dict[str, np.ndarray]:
  """Video ``index``: a valid candidate on a training task, solving with
  probability ``positive_ratio`` when the task has a solution (the official
  SlotFormer PHYRE data mixes positives in the same way). With ``layouts``
  > 0 the task is one of :func:`layout_tasks` instead (``labels`` must
  hold theirs)."""
  if layouts:  # only this video's layout (each one is simulated to build)
    k = index % (len(config.templates) * layouts)
    task = make_task(config, config.templates[k // layouts],
                     config.tasks_per_template + k % layouts)
  else:
    train = split_tasks(config)['train']
    task = train[index % len(train)]
  rng = np.random.default_rng([config.seed, 17, ('train', 'val').index(split),
                               index])
  task_labels_ = labels[(task.template, task.index)]
  solved = np.flatnonzero(task_labels_ == SOLVED)
  valid = np.flatnonzero(task_labels_ != INVALID)
  pool = solved if solved.size and rng.random() < positive_ratio else valid
  candidate = int(rng.choice(pool))
  out = render_video(task, candidate_actions(config)[candidate], config)
  out.update(index=np.array(index, np.int32),
             task=np.array(config.templates.index(task.template) * 10_000
                           + task.index, np.int32),
             candidate=np.array(candidate, np.int32))
  return out


def features(config: PhyreLikeConfig) -> tfds.features.FeaturesDict:
  """The fields of :func:`training_video`."""
  h, w = config.resolution
  t = config.num_frames
  return tfds.features.FeaturesDict({
      'video': base.tensor((t, h, w, 3), np.uint8),
      'segmentations': base.tensor((t, h, w), np.uint8),
      'outcome': tfds.features.Scalar(np.int8),
      'index': tfds.features.Scalar(np.int32),
      'task': tfds.features.Scalar(np.int32),
      'candidate': tfds.features.Scalar(np.int32),
  })


@dataclasses.dataclass(frozen=True)
class Videos:
  """What names the training videos of a run's ``config.data``: on the
  fold's training tasks, or on ``layouts`` extra layouts per template
  (:func:`video_generation`)."""

  config: PhyreLikeConfig
  num_train: int
  num_val: int
  positive_ratio: float
  layouts: int = 0

  @property
  def num_frames(self) -> int:
    return self.config.num_frames

  @property
  def slug(self) -> str:
    return video_slug(self.config, self.num_train, self.num_val,
                      self.positive_ratio, self.layouts)


def videos_of(data_config: Any) -> Videos:
  """The training videos ``config.data`` names."""
  config, layouts = video_generation(data_config)
  return Videos(config, data_config.num_train, data_config.num_val,
                data_config.positive_ratio, layouts)


def videos_dir(videos: Videos, data_dir: str | os.PathLike[str]) -> Path:
  """The TFDS version folder of ``videos``."""
  return sources.generated_dir(data_dir, NAME, videos.slug)


def generate(videos: Videos, out: base.Output) -> Path:
  """The training videos, generated unless they are there (with the
  labels they need)."""
  config = videos.config
  if videos.layouts:
    labels = layout_labels(config, videos.layouts, out)
  else:
    labels = build_task_labels(config, out)
  return out.tfds_folder(
      videos_dir(videos, out.data_dir), name=NAME,
      features=features(config),
      description=json.dumps(dataclasses.asdict(config)),
      split_sizes={'train': videos.num_train, 'val': videos.num_val},
      make=functools.partial(training_video, config, labels,
                             videos.positive_ratio, layouts=videos.layouts))


DATASET = base.register(base.Generated(
    names=(NAME,), label='PHYRE-like', splits=('train', 'val'),
    features=functools.partial(features, PhyreLikeConfig()),
    what='the PHYRE-like training videos', parameters=videos_of,
    folder=videos_dir, generate=generate,
    # Planning scores every candidate of every task against these.
    task_data={'planning': lambda data_config, out: build_task_labels(
        config_from_data_config(data_config), out)}))
