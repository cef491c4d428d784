"""Does a trained SAVi keep its segmentation and reconstruction frame after frame?
Answered for SAVi's targets (issue 51) in docs/experiments/savi_targets.md.

SAVi's whole-video FG-ARI (`--mode=evaluate`) is one clustering of all
frames of a video: a model that segments the frames it was trained on
(`savi.clip_length` frames per clip) but drifts afterwards scores near
chance, as does one that never segments. This tells them apart: for every
seed of a finished workdir (its extracted slots of `--split`, decoded by
its trained SAVi), per frame, the mean over the videos of

  FG-ARI      the frame's own FG-ARI (one clustering per frame, the
              evaluation's per-step convention), from the decoder's masks;
  <target>    the squared error of each reconstruction target (`rgb` in
              [0, 1], `flow` / `depth` in the data's units,
              slotformer_jax/targets.py);
  slot norm   the slots' mean L2 norm (drift shows as growth).

  python experiments/savi_frames.py --workdir=runs/targets_depth \\
      --frames=0,1,2,5,11,23
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax import targets as targets_lib
from slotformer_jax.evaluation import metrics
from slotformer_jax.run import Run


def per_frame(view: Run, split: str, num_videos: int) -> dict[str, Any]:
  """{measure: [T] mean over the split's first `num_videos` videos} of one
  seed's view of the run."""
  slot_model, params = view.slot_model, view.stage1.params
  videos, source = view.videos(split), view.slots(split)
  num_true = view.config.data.max_instances + 1
  names = [target.name for target in slot_model.targets]

  @jax.jit
  def measure(slots, segmentation):
    decoded = slot_model.decode(params, slots)
    alpha = decoded.alpha_masks[..., 0]  # [T, N, H, W]
    pred = metrics.segmentation_from_alpha_masks(alpha)
    score = metrics.adjusted_rand_index(
        segmentation[:, None].astype(jnp.int32), pred[:, None], num_true,
        alpha.shape[1], ignore_background=True)
    values = dict(decoded.targets or {})
    if decoded.recon is not None:
      values[targets_lib.RGB.name] = decoded.recon
    return jnp.where(score.valid, score.value, jnp.nan), values

  rows = {name: [] for name in ['fg_ari', 'slot_norm', *names]}
  for index in range(min(num_videos, len(source))):
    item, video = source[index], videos[index]
    fg_ari, values = jax.device_get(measure(item['slots'],
                                            video['segmentations']))
    rows['fg_ari'].append(fg_ari)
    rows['slot_norm'].append(np.linalg.norm(item['slots'], axis=-1).mean(-1))
    for name in names:
      truth = video[targets_lib.TARGETS[name].field]
      if name == targets_lib.RGB.name:
        truth = truth.astype(np.float32) / 255.0
      error = (np.asarray(values[name], np.float32) - truth) ** 2
      rows[name].append(error.reshape(len(error), -1).mean(-1))
  return {name: np.nanmean(np.stack(values), axis=0)
          for name, values in rows.items()}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--workdir', required=True)
  parser.add_argument('--split', default='test')
  parser.add_argument('--videos', type=int, default=100)
  parser.add_argument('--frames', default='0,1,2,5,11,23')
  parser.add_argument('--json', default='')
  args = parser.parse_args()
  run = Run.open(args.workdir)
  frames = [int(f) for f in args.frames.split(',')]
  views = run.seed_views() if run.seeds is not None else [run]
  results = {}
  for view in views:
    seed = view.config.seed if run.seeds is None else run.seeds[
        view.seed_index]
    rows = per_frame(view, args.split, args.videos)
    results[seed] = {name: values.tolist() for name, values in rows.items()}
    for name, values in rows.items():
      shown = ' '.join(f'{values[f]:.4g}' for f in frames if f < len(values))
      print(f'seed {seed} {name:>9} at frames {args.frames}: {shown}')
  if args.json:
    with open(args.json, 'w') as f:
      json.dump(results, f)


if __name__ == '__main__':
  main()
