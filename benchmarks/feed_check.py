"""Is a train step input-bound? Times the step fed by the real reader
(`pipeline.train_batches` with reader worker processes, then
`sharding.prefetch_to_device`, as `trainer.fit` does) against the same step
on one batch already on the device. Used by benchmarks/gpu_check.py
(``--fed``); runs on CPU too.

The data: OBJ3D-like PNG videos (benchmarks/reader_speed.py's, moving
squares) at the step's resolution, converted by
``python -m slotformer_jax.data.prepare`` (so 'video' is decoded from
array_record as in training); any other field of the batch (slots, tokens,
...) is random, memory-mapped from a .npy file next to it (read as the
extracted slots are). A step that reads slots (SlotFormer) is fed as in
training, by a `SlotSource` over a slot extraction written here (random
slots), with the fixture's videos when the step reads frames; their
clips then start where the step's shorter video begins (L_I reads the
rollout's frames only: `video_from`).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

import reader_speed  # benchmarks/reader_speed.py
from slotformer_jax import datasets
from slotformer_jax.config import defaults
from slotformer_jax.data import pipeline
from slotformer_jax.data import slots
from slotformer_jax.data import prepare
from slotformer_jax.runtime import sharding
from slotformer_jax.train import trainer

# Fed over resident per-step time above which the step waits for its input.
INPUT_BOUND_RATIO = 1.10


class FixtureSource:
  """Items {'video': decoded from the converted fixture (if any), other
  fields: rows of memory-mapped random arrays}, all with `frames` frames.
  Picklable (the reader workers get a copy)."""

  def __init__(self, videos: Any, arrays: dict[str, np.ndarray],
               num_videos: int):
    self.videos = videos
    self.arrays = arrays
    self.num_videos = num_videos

  def __len__(self) -> int:
    return self.num_videos

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    item = {key: np.asarray(value[index])
            for key, value in self.arrays.items()}
    if self.videos is not None:
      item['video'] = self.videos[index]['video']
    return item


def fixture_source(spec: dict[str, Any], frames: int, workdir: Path,
                   num_videos: int = 64) -> FixtureSource:
  """A source of `num_videos` videos of `frames` frames with the fields of
  `spec` ({field: shape [B, L, ...] or [B], dtype})."""
  workdir.mkdir(parents=True, exist_ok=True)
  videos = None
  if 'video' in spec:
    height, width = spec['video'].shape[2:4]
    data_dir = workdir / f'data_{height}x{width}_{frames}'
    if not data_dir.is_dir():
      raw = workdir / f'OBJ3D_{max(height, width)}_{frames}'
      if not (raw / 'train').is_dir():
        reader_speed.write_obj3d_like(raw, num_videos,
                                      resolution=max(height, width),
                                      frames=frames)
      prepare.main(['--dataset=obj3d', f'--source={raw}',
                    f'--data_dir={data_dir}', '--splits=train',
                    f'--resolution={height}x{width}', '--no_progress',
                    f'--num_workers={min(4, os.cpu_count() or 1)}'])
    data = defaults.base_config().data
    data.name, data.data_dir = 'obj3d', str(data_dir)
    data.resolution = (height, width)
    videos = datasets.get_video_source(data, 'train')
    num_videos = len(videos)
  if 'slots' in spec:
    return _slot_source(spec, frames, workdir, videos, num_videos)
  rng = np.random.default_rng(0)
  arrays = {}
  for key, value in spec.items():
    if key == 'video':
      continue
    dtype = np.dtype(value.dtype)
    shape = ((num_videos,) if len(value.shape) == 1
             else (num_videos, frames, *value.shape[2:]))
    path = workdir / f'{key}_{"x".join(map(str, shape))}_{dtype.str[1:]}.npy'
    if not path.exists():
      if np.issubdtype(dtype, np.floating):
        data = rng.normal(size=shape).astype(dtype)
      else:
        data = rng.integers(0, 2, size=shape).astype(dtype)
      np.save(path, data)
    arrays[key] = np.load(path, mmap_mode='r')
  return FixtureSource(videos, arrays, num_videos)


def _slot_source(spec: dict[str, Any], frames: int, workdir: Path,
                 videos: Any, num_videos: int) -> slots.SlotSource:
  """Random slots of `num_videos` videos of `frames` frames, read as
  training reads extracted slots, with `videos` behind them (or none)."""
  if set(spec) - {'slots', 'video'}:
    raise ValueError(f'a slot step reads slots and video, not {sorted(spec)}')
  _, length, num_slots, slot_size = spec['slots'].shape
  directory = str(workdir / f'slots_{num_videos}x{frames}x{num_slots}'
                            f'x{slot_size}')
  if not (slots.read_meta(directory) or {}).get('complete'):
    writer = slots.SlotWriter(directory, num_videos, num_slots, slot_size,
                              savi_step=0)
    rng = np.random.default_rng(0)
    for index in range(num_videos):
      writer.add(index, rng.normal(size=(frames, num_slots, slot_size))
                 .astype(np.float32))
    writer.close()
  video_from = length - spec['video'].shape[1] if 'video' in spec else 0
  return slots.SlotSource(directory, videos, video_from=video_from)


def time_fed_vs_resident(compiled, state, frozen, spec: dict[str, Any],
                         mesh, *, frame_stride: int, reader_workers: int,
                         repeats: int, workdir: Path,
                         num_videos: int = 64) -> dict[str, Any]:
  """Per-step seconds of `compiled` (state, batch, frozen) -> (state,
  metrics) fed by the reader vs on one resident batch; neither blocks on
  the device per step (as the trainer), each run blocks once at its end."""
  batch_size = next(iter(spec.values())).shape[0]
  # The longest time axis (a slot step's video may start later in the clip).
  clip_length = max(value.shape[1] for value in spec.values()
                    if len(value.shape) > 1)
  frames = max(50, (clip_length - 1) * frame_stride + 1)
  source = fixture_source(spec, frames, workdir, num_videos)
  stream = pipeline.train_batches(
      source, batch_size=batch_size, clip_length=clip_length, seed=0,
      fields=tuple(spec), frame_stride=frame_stride,
      num_workers=reader_workers)
  feed = sharding.prefetch_to_device(stream, mesh,
                                     size=trainer.DEVICE_PREFETCH)
  try:
    # Warm-up: start the workers, fill the buffers, run the step twice.
    started = time.perf_counter()
    _, batch = next(feed)
    startup = time.perf_counter() - started
    for _ in range(2):
      state, metrics = compiled(state, batch, frozen)
      _, batch = next(feed)
    jax.block_until_ready(metrics['loss'])
    resident = batch
    begin = time.perf_counter()
    for _ in range(repeats):
      state, metrics = compiled(state, resident, frozen)
    jax.block_until_ready(metrics['loss'])
    resident_s = (time.perf_counter() - begin) / repeats
    begin = time.perf_counter()
    for _ in range(repeats):
      _, batch = next(feed)
      state, metrics = compiled(state, batch, frozen)
    jax.block_until_ready(metrics['loss'])
    fed_s = (time.perf_counter() - begin) / repeats
  finally:
    feed.close()
  ratio = fed_s / resident_s
  bound = 'input-bound' if ratio > INPUT_BOUND_RATIO else 'compute-bound'
  return dict(reader_workers=reader_workers, fed_ms=1e3 * fed_s,
              resident_ms=1e3 * resident_s, fed_over_resident=ratio,
              verdict=bound, reader_startup_s=startup,
              batch_mib=sum(int(np.prod(v.shape)) * np.dtype(v.dtype).itemsize
                            for v in spec.values()) / 2**20,
              fed_steps_timed=repeats)
