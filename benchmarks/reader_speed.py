r"""Frames per second of the training reader over a converted dataset.

  python benchmarks/reader_speed.py [--videos=64] [--seconds=10]
  python benchmarks/reader_speed.py --workers=1,2 --rounds=6 --seconds=5


Writes OBJ3D-layout PNG videos (64x64, 50 frames of smooth backgrounds with
moving squares, like rendered scenes: they compress as real frames do),
converts them with ``python -m slotformer_jax.data.prepare``, then times:

* random access: whole videos read from array_record and decoded to numpy
  (``source[i]``), in frames/s;
* ``pipeline.train_batches`` (the training reader, background prefetch as in
  training) for the clip shapes the stages use, in delivered clip frames/s
  (batch x clip length x batches / s). Since the chunked layout (2.0.0)
  each clip reads only the chunks that hold it (``clip_reader.py``
  compares the layouts).

``--workers=A,B,...`` times ``train_batches(num_workers=A)`` (0: the
background thread; N: N worker processes, ``data.reader_workers``) against
the others, alternating within each of ``--rounds`` rounds (order reversed
every other round), and prints the median frames/s of each and the median
per-round ratio to the first.

Run it on an otherwise idle machine for numbers you compare.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from slotformer_jax import datasets

from slotformer_jax.config import defaults
from slotformer_jax.data import pipeline
from slotformer_jax.data import prepare

RES = 64
FRAMES = 50


def write_obj3d_like(root: Path, num_videos: int, seed: int = 0, *,
                     resolution: int = RES, frames: int = FRAMES) -> None:
  """``<root>/train/<n>/test_<t>.png``: `frames` frames (default 50) of
  moving squares at `resolution` x `resolution` (default 64; squares and
  speeds scale with it)."""
  rng = np.random.default_rng(seed)
  res = resolution
  side = 12 * res // RES
  speed = 2 * res // RES
  ys, xs = np.mgrid[:res, :res]
  for video in range(num_videos):
    folder = root / 'train' / str(video)
    folder.mkdir(parents=True, exist_ok=True)
    background = (60 + 40 * ys / res + 20 * xs / res)[..., None] * np.ones(3)
    squares = [(rng.integers(0, res - side, 2),
                rng.integers(-speed, speed + 1, 2),
                rng.integers(40, 255, 3)) for _ in range(4)]
    for t in range(frames):
      frame = background.copy()
      for position, velocity, color in squares:
        y, x = np.clip(position + t * velocity, 0, res - side)
        frame[y:y + side, x:x + side] = color
      frame += rng.normal(0, 1.5, frame.shape)   # renderer noise
      Image.fromarray(np.clip(frame, 0, 255).astype(np.uint8)).save(
          folder / f'test_{t + 1}.png')


def time_random_access(source, seconds: float) -> float:
  """Decoded frames/s of whole-video reads in a random order."""
  rng = np.random.default_rng(0)
  frames, started = 0, time.perf_counter()
  while time.perf_counter() - started < seconds:
    frames += len(source[int(rng.integers(len(source)))]['video'])
  return frames / (time.perf_counter() - started)


def time_train_batches(source, batch_size: int, clip_length: int,
                       frame_stride: int, seconds: float,
                       num_workers: int = 0) -> float:
  """Delivered clip frames/s of pipeline.train_batches."""
  batches = pipeline.train_batches(
      source, batch_size=batch_size, clip_length=clip_length, seed=0,
      frame_stride=frame_stride, num_workers=num_workers)
  # Start the prefetch thread or the workers (process start-up is once per
  # stage, not what is compared) and let them fill their buffers.
  for _ in range(1 + 2 * max(1, num_workers)):
    next(batches)
  count, started = 0, time.perf_counter()
  while time.perf_counter() - started < seconds:
    batch = next(batches)
    count += batch['video'].shape[0] * batch['video'].shape[1]
  elapsed = time.perf_counter() - started
  batches.close()
  return count / elapsed


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--videos', type=int, default=64)
  parser.add_argument('--seconds', type=float, default=10.0)
  parser.add_argument('--workdir', default=None,
                      help='keep the fixture and conversion here')
  parser.add_argument('--workers', default='0',
                      help='comma-separated reader worker counts to compare '
                      '(0: the thread)')
  parser.add_argument('--rounds', type=int, default=1)
  args = parser.parse_args()
  workers = [int(w) for w in args.workers.split(',')]
  with tempfile.TemporaryDirectory() as tmp:
    work = Path(args.workdir or tmp)
    if not (work / 'OBJ3D' / 'train').is_dir():
      write_obj3d_like(work / 'OBJ3D', args.videos)
    prepare.main(['--dataset=obj3d', f'--source={work / "OBJ3D"}',
                  f'--data_dir={work / "data"}', '--splits=train',
                  '--no_progress', '--num_workers=2'])
    data = defaults.base_config().data
    data.name, data.data_dir = 'obj3d', str(work / 'data')
    data.resolution = (RES, RES)
    source = datasets.get_video_source(data, 'train')
    shards = sorted(source.dataset_dir.glob('*.array_record-*'))
    size = sum(p.stat().st_size for p in shards)
    print(f'{len(source)} videos of {FRAMES}x{RES}x{RES}: {size / 2**20:.1f} '
          f'MiB on disk ({size / (len(source) * FRAMES * RES * RES * 3):.0%}'
          ' of raw); cores available: '
          f'{len(os.sched_getaffinity(0))}')
    print(f'load average before: {_load()}')
    if workers == [0]:
      print(f'random access (whole videos): '
            f'{time_random_access(source, args.seconds):8.0f} frames/s '
            'decoded')
    shapes = ((64, 6, 1, 'SAVi clips (OBJ3D: batch 64 x 6 frames)'),
              (64, 16, 1, 'SlotFormer clips with L_I (batch 64 x 16 frames)'),
              (64, 16, 2, 'CLEVRER-style stride 2 (batch 64 x 16 frames)'))
    for batch_size, clip, stride, what in shapes:
      rates = {w: [] for w in workers}
      for round_index in range(args.rounds):
        order = workers if round_index % 2 == 0 else workers[::-1]
        for w in order:
          rates[w].append(time_train_batches(source, batch_size, clip, stride,
                                             args.seconds, num_workers=w))
      for w in workers:
        label = 'thread' if w == 0 else f'{w} worker process' + (
            'es' if w > 1 else '')
        line = (f'train_batches {what}, {label}: '
                f'{np.median(rates[w]):8.0f} frames/s delivered')
        if w != workers[0]:
          ratio = np.median(np.asarray(rates[w]) / np.asarray(rates[workers[0]]))
          line += f' ({ratio:.2f}x {workers[0]}, median of {args.rounds} rounds)'
        print(line, flush=True)
    print(f'load average after: {_load()}')


def _load() -> str:
  return ', '.join(f'{x:.2f}' for x in os.getloadavg())


if __name__ == '__main__':
  main()
