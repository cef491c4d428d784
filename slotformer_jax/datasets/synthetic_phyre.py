"""Writes the PHYRE-like embedded dataset: the simulated labels of every
candidate action and the SAVi / SlotFormer training videos.

The tasks, physics and rendering are the world's (worlds/phyre_like.py);
the parameters and the files they name are data/embedded/phyre_like.py's.
Run by the data stage (stages/data.py).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data.convert import embedded
from slotformer_jax.data.embedded.phyre_like import NAME
from slotformer_jax.data.embedded.phyre_like import PhyreLikeConfig
from slotformer_jax.data.embedded.phyre_like import labels_path
from slotformer_jax.data.embedded.phyre_like import load_task_labels
from slotformer_jax.data.embedded.phyre_like import slug
from slotformer_jax.data.embedded.phyre_like import video_generation
from slotformer_jax.data.embedded.phyre_like import video_slug
from slotformer_jax.worlds.phyre_like import INVALID
from slotformer_jax.worlds.phyre_like import SOLVED
from slotformer_jax.worlds.phyre_like import Task
from slotformer_jax.worlds.phyre_like import all_tasks
from slotformer_jax.worlds.phyre_like import candidate_actions
from slotformer_jax.worlds.phyre_like import label_candidates
from slotformer_jax.worlds.phyre_like import layout_tasks
from slotformer_jax.worlds.phyre_like import make_task
from slotformer_jax.worlds.phyre_like import render_video
from slotformer_jax.worlds.phyre_like import split_tasks


def build_task_labels(config: PhyreLikeConfig,
                      data_dir: str | os.PathLike[str]
                      ) -> dict[tuple[str, int], np.ndarray]:
  """{(template, index): int8 [num_candidates]} for every task, simulated
  unless stored.

  Simulating every candidate of every task takes ~1 s per task; the result
  is stored in ``<data_dir>/synthetic_phyre/<slug>/labels.npz``
  (:func:`slotformer_jax.data.embedded.phyre_like.labels_path`).
  """
  path = labels_path(config, data_dir)
  if path.is_file():
    return load_task_labels(config, data_dir)
  return _simulate_and_store(config, all_tasks(config), path)


def layout_labels(config: PhyreLikeConfig, count: int,
                  data_dir: str | os.PathLike[str]
                  ) -> dict[tuple[str, int], np.ndarray]:
  """The simulated outcomes of every candidate on :func:`layout_tasks`
  (stored; ~1 s per layout), used only to mix solving actions into the
  dynamics videos as on labelled tasks."""
  unfolded = dataclasses.replace(config, fold=0)
  path = Path(data_dir) / NAME / slug(unfolded) / f'layouts_{count}.npz'
  tasks = layout_tasks(config, count)
  if path.is_file():
    with np.load(path) as stored:
      return {(t.template, t.index): stored[f'{t.template}_{t.index}']
              for t in tasks}
  return _simulate_and_store(config, tasks, path)


def _simulate_and_store(config: PhyreLikeConfig, tasks: list[Task],
                        path: Path) -> dict[tuple[str, int], np.ndarray]:
  actions = candidate_actions(config)
  labels = {(t.template, t.index): label_candidates(t, actions, config)
            for t in tasks}
  path.parent.mkdir(parents=True, exist_ok=True)
  partial = path.with_suffix('.tmp.npz')
  np.savez(partial, **{f'{k[0]}_{k[1]}': v for k, v in labels.items()})
  os.replace(partial, path)
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


def video_family(config: PhyreLikeConfig, num_train: int, num_val: int,
                 positive_ratio: float,
                 labels: dict[tuple[str, int], np.ndarray],
                 layouts: int = 0) -> embedded.Family:
  """Training videos for SAVi / SlotFormer ('train', 'val' splits): on the
  fold's training tasks, or on ``layouts`` extra layouts per template."""
  h, w = config.resolution
  t = config.num_frames
  return embedded.Family(
      name=NAME,
      slug=video_slug(config, num_train, num_val, positive_ratio, layouts),
      description=json.dumps(dataclasses.asdict(config)),
      features={
          'video': embedded.tensor((t, h, w, 3), np.uint8),
          'segmentations': embedded.tensor((t, h, w), np.uint8),
          'outcome': tfds.features.Scalar(np.int8),
          'index': tfds.features.Scalar(np.int32),
          'task': tfds.features.Scalar(np.int32),
          'candidate': tfds.features.Scalar(np.int32),
      },
      split_sizes={'train': num_train, 'val': num_val},
      make=functools.partial(training_video, config, labels, positive_ratio,
                             layouts=layouts))


def build_video_dataset(data_config: Any, data_dir: str | os.PathLike[str]
                        ) -> Path:
  """The SAVi / SlotFormer training videos named by a run's config.data,
  generated unless they are there (with the labels they need)."""
  config, layouts = video_generation(data_config)
  if layouts:
    labels = layout_labels(config, layouts, data_dir)
  else:
    labels = build_task_labels(config, data_dir)
  return embedded.build(
      video_family(config, data_config.num_train, data_config.num_val,
                   data_config.positive_ratio, labels, layouts), data_dir,
      num_workers=data_config.num_workers)
