"""The PHYRE-like embedded dataset ('synthetic_phyre') as its readers see it.

The generation parameters (:class:`PhyreLikeConfig`, named by a run's
``config.data``: the tasks, the candidate actions, the rendering) and the
files they name under ``<data_dir>/synthetic_phyre/``:

* ``<slug>/labels.npz``: the simulated outcome of every candidate action on
  every task (planning reads them: :func:`load_task_labels`);
* ``<slug>_v<train>-<val>_p<ratio>[_l<layouts>]/2.0.0``: the SAVi /
  SlotFormer training videos (TFDS, :func:`video_dataset_dir`).

The world itself (tasks, physics, rendering) is ``worlds/phyre_like.py``;
the generator that writes these files is ``data/convert/phyre_like.py``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from slotformer_jax.data.embedded import folders

GENERATOR_VERSION = 1

NAME = 'synthetic_phyre'
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


def config_from_data_config(data_config: Any) -> PhyreLikeConfig:
  fields = {f.name for f in dataclasses.fields(PhyreLikeConfig)}
  return PhyreLikeConfig(**{key: data_config[key] for key in fields
                            if key in data_config})


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
  config, layouts = video_generation(data_config)
  return folders.tfds_dir(data_dir, NAME, video_slug(
      config, data_config.num_train, data_config.num_val,
      data_config.positive_ratio, layouts))


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
    raise folders.not_generated('the PHYRE-like task labels', path)
  with np.load(path) as stored:
    return {key: stored[f'{key[0]}_{key[1]}'] for key in task_keys(config)}
