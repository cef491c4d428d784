"""How much of each SAVi target's signal lies in the objects (issue 51).
Answered (numbers, commands, machine) in docs/experiments/savi_targets.md.

Question: a SAVi reconstructing `depth` (or `flow`) segments nothing where
the same SAVi on RGB does; is that the target or the model? A slot model
is pushed to split the objects from the background only by the part of
its reconstruction error that a background alone cannot explain. This
measures that part per target on the held-out videos of a config (by
default `configs/synthetic.py:flow`, the embedded videos with their exact
flow and depth), in the model's own units (RGB in [-1, 1], flow as SAVi's
colour picture in [-1, 1], depth as log(1 + d)):

  background-only MSE  the squared error of the best object-free picture:
                       each pixel's median over every frame of every video
                       (the camera is fixed, objects cover a pixel in a
                       minority of frames), over all pixels, over object
                       pixels and over background pixels;
  per-frame variance   the target's variance within a frame (what a model
                       predicting one value per frame would miss);
  objects' part        background-only MSE / the target's variance over all
                       pixels of all frames: the part of what a decoder has
                       to explain that only objects explain (Adam's updates
                       do not depend on the loss's scale, so this ratio, not
                       the MSE itself, compares targets; above 100 % when
                       the median background lies off the mean);
  object share         the share of the background-only MSE in object
                       pixels.

  python experiments/target_signal.py --videos=40
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from slotformer_jax import datasets
from slotformer_jax import targets
from slotformer_jax.config.checks import load_config_file

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def signal(values: np.ndarray, objects: np.ndarray) -> dict[str, float]:
  """values [V, T, H, W, C] in the model's units, objects bool [V, T, H, W]
  -> the measures of the module docstring."""
  background = np.median(values.reshape(-1, *values.shape[2:]), axis=0)
  error = ((values - background) ** 2).mean(axis=-1)  # [V, T, H, W]
  flat = values.reshape(*values.shape[:2], -1, values.shape[-1])
  return {
      'background_only_mse': float(error.mean()),
      'background_only_mse_objects': float(error[objects].mean()),
      'background_only_mse_background': float(error[~objects].mean()),
      'per_frame_variance': float(flat.var(axis=2).mean()),
      'objects_part': float(error.mean()
                            / values.reshape(-1, values.shape[-1]).var(
                                axis=0).mean()),
      'object_share': float(error[objects].sum() / error.sum()),
  }


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--config', default=os.path.join(
      ROOT, 'configs', 'synthetic.py:flow'))
  parser.add_argument('--split', default='test')
  parser.add_argument('--videos', type=int, default=40)
  parser.add_argument('--json', default='')
  args = parser.parse_args()
  config = load_config_file(args.config)
  source = datasets.get_video_source(config.data, args.split)
  items = [source[i] for i in range(min(args.videos, len(source)))]
  objects = np.stack([item['segmentations'] for item in items]) > 0
  units = {'rgb': lambda x: x.astype(np.float32) / 127.5 - 1.0,
           'flow': lambda x: x, 'depth': lambda x: x}
  results = {'videos': len(items), 'object_pixels': float(objects.mean())}
  for target in targets.TARGETS.values():
    if target.field not in items[0]:
      continue
    values = units[target.name](np.stack([item[target.field]
                                          for item in items]))
    results[target.name] = signal(values, objects)
  print(f'{len(items)} {args.split} videos, {objects.mean():.1%} object '
        'pixels')
  print('| target | background-only MSE: all | objects | background | '
        "per-frame variance | objects' part | object share |")
  print('|---|---|---|---|---|---|---|')
  for name in targets.NAMES:
    if name in results:
      r = results[name]
      print(f"| {name} | {r['background_only_mse']:.4f} | "
            f"{r['background_only_mse_objects']:.4f} | "
            f"{r['background_only_mse_background']:.4f} | "
            f"{r['per_frame_variance']:.4f} | {r['objects_part']:.0%} | "
            f"{r['object_share']:.0%} |")
  if args.json:
    with open(args.json, 'w') as f:
      json.dump(results, f, indent=1)


if __name__ == '__main__':
  main()
