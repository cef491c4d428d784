"""Does the folder dataset (datasets/videos.py) give the native frames?
Answered in docs/experiments/own_videos.md.

Generates the quickstart's videos (configs/synthetic.py: 32x32, 24 frames;
by default fewer of them: `--num_test` test videos, `--num_train` and
`--num_val` 4 each), exports every video of each split twice, as a folder
of png frames and as an mp4 written by imageio (libx264, its default
quality, 10 fps), converts both folders through the data stage
(`config.data.source`), and compares the stored frames with the native
ones: png frames must be equal bit for bit; for the mp4s the PSNR of the
decoded frames against the originals is printed (mean, lowest video), with
the conversion times.

  python experiments/own_videos_equivalence.py --out=/tmp/equivalence
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import time
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
from PIL import Image

from slotformer_jax import datasets
from slotformer_jax.stages import data as data_stage

ROOT = Path(__file__).resolve().parent.parent
SPLITS = ('train', 'val', 'test')


def _config(name: str, variant: str = ''):
  spec = importlib.util.spec_from_file_location(
      name, ROOT / 'configs' / f'{name}.py')
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant) if variant else module.get_config()


def psnr(a: np.ndarray, b: np.ndarray) -> float:
  mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
  return float('inf') if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse))


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--out', required=True, type=Path)
  parser.add_argument('--num_test', type=int, default=100)
  # The quickstart's 1,000 / 50 give the folder that configs/videos.py
  # trains on (docs/experiments/own_videos.md, "Trained on the mp4s").
  parser.add_argument('--num_train', type=int, default=4)
  parser.add_argument('--num_val', type=int, default=4)
  args = parser.parse_args()
  data_dir = args.out / 'data'
  native = _config('synthetic').data
  native.num_train, native.num_val, native.num_test = (
      args.num_train, args.num_val, args.num_test)
  native.data_dir = str(data_dir)
  started = time.time()
  data_stage.prepare_dataset(native)
  print(f'generated {args.num_train + args.num_val + args.num_test} videos in '
        f'{time.time() - started:.1f} s')
  originals = {split: datasets.get_video_source(native, split)
               for split in SPLITS}
  for kind in ('png', 'mp4'):
    source = args.out / kind
    for split, videos in originals.items():
      for index in range(len(videos)):
        frames = videos[index]['video']
        if kind == 'png':
          folder = source / split / f'{index:04d}'
          os.makedirs(folder, exist_ok=True)
          for t, frame in enumerate(frames):
            Image.fromarray(frame).save(folder / f'{t}.png')
        else:
          os.makedirs(source / split, exist_ok=True)
          imageio.mimwrite(source / split / f'{index:04d}.mp4', frames,
                           fps=10, macro_block_size=1)
    config = _config('videos').data
    config.source, config.data_dir = str(source), str(data_dir)
    config.resolution = tuple(native.resolution)
    config.num_frames, config.frame_stride = native.num_frames, 1
    started = time.time()
    data_stage.prepare_dataset(config)
    took = time.time() - started
    stored = datasets.get_video_source(config, 'test')
    values = [psnr(stored[i]['video'], originals['test'][i]['video'])
              for i in range(len(stored))]
    equal = sum(np.array_equal(stored[i]['video'],
                               originals['test'][i]['video'])
                for i in range(len(stored)))
    finite = [v for v in values if np.isfinite(v)]
    print(f'{kind}: converted {sum(map(len, originals.values()))} videos in '
          f'{took:.1f} s; test videos equal bit for bit: {equal} of '
          f'{len(stored)}; PSNR vs the originals: mean '
          f'{np.mean(finite) if finite else float("inf"):.2f} dB, lowest '
          f'{min(values):.2f} dB')


if __name__ == '__main__':
  main()
