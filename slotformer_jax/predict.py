"""Predict from any clip with a trained world model.

Usage::

    python -m slotformer_jax.predict --workdir=runs/mine --video=clip.mp4 \
        --out=predictions/clip [--burn_in=6] [--rollout=10]

The clip's first ``--burn_in`` frames (default: the model's burn-in) are
observed; the model rolls its slots ``--rollout`` steps on (default: to the
end of the clip, at most 100). Writes into ``--out`` (nothing elsewhere):

* ``prediction.png``: rows 'real' (the clip), 'model' (SAVi's
  reconstruction of the observed frames | the predicted frames) and 'slots'
  (the model's frames tinted by each pixel's slot), a line between
  observed and predicted;
* ``prediction.gif``: the same rows frame by frame, each labelled
  'observed' or 'predicted';
* ``slots.npz``: the observed and predicted slots and the masks;
* ``explore/index.html`` (unless ``--no-explore``): the explorer page of the
  clip (docs/explore.md): the rollout slot by slot and its remove / freeze
  counterfactuals, from the model's own burn-in; written when the clip
  holds the real frames of the whole rollout.

The clip is read as the model's training videos were (resolution, crop or
pad, frame rate, frame stride: ``WorldModel.expected``); any file or folder
the folder dataset reads (``datasets/videos.py``; a folder of frames has no
rate: refused for a model trained at a set ``data.fps``). Problems are one
line and exit 1.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slotformer_jax.errors import UserError
from slotformer_jax.errors import printable

MAX_ROLLOUT = 100


def build_parser() -> argparse.ArgumentParser:
  parser = argparse.ArgumentParser(
      prog='python -m slotformer_jax.predict',
      description=__doc__.split('\n\n')[0])
  parser.add_argument('--workdir', required=True,
                      help='a trained run (or one made by official.convert)')
  parser.add_argument('--video', required=True, type=Path,
                      help='a video file, GIF or folder of numbered frames')
  parser.add_argument('--out', required=True, type=Path,
                      help='the folder to write the pictures into')
  parser.add_argument('--burn_in', type=int, default=None,
                      help='observed frames (default: the model\'s burn-in)')
  parser.add_argument('--rollout', type=int, default=None,
                      help='predicted steps (default: the rest of the clip)')
  parser.add_argument('--dynamics', default='slotformer',
                      choices=('slotformer', 'slot_lstm'))
  parser.add_argument('--on_mismatch', default='resize',
                      choices=('resize', 'refuse'),
                      help='frames of another size than the model\'s')
  parser.add_argument('--explore', action=argparse.BooleanOptionalAction,
                      default=True,
                      help='also write explore/index.html: the rollout slot '
                      'by slot and its remove / freeze counterfactuals '
                      '(needs the real frames of the rollout in the clip)')
  parser.add_argument('--scale', type=int, default=2,
                      help='pixels per frame pixel in the pictures')
  return parser


def predict(args: argparse.Namespace) -> dict[str, Path]:
  """Reads, predicts and writes (see the module docstring); returns
  {'png': ..., 'gif': ..., 'slots': ...}.

  Raises:
    UserError: the workdir, the clip or a length (one line).
  """
  # Imported here: --help answers before JAX starts.
  from slotformer_jax import api  # pylint: disable=g-import-not-at-top
  from slotformer_jax import frames as frames_lib  # pylint: disable=g-import-not-at-top
  from slotformer_jax.files import write_atomic  # pylint: disable=g-import-not-at-top

  model = api.WorldModel.load(args.workdir, args.dynamics,
                              on_mismatch=args.on_mismatch)
  stride = model.expected.rollout_stride
  needed = (model.expected.burn_in - 1) * stride + 1
  burn_in = needed if args.burn_in is None else args.burn_in
  if burn_in < needed:
    raise UserError(f'--burn_in={burn_in}: the model reads {needed} '
                    f'observed frames (burn-in {model.expected.burn_in}, '
                    f'stride {stride})')
  limit = burn_in + (args.rollout or MAX_ROLLOUT) * stride
  clip = model.read_video(args.video, max_frames=limit)
  if len(clip) < burn_in:
    raise UserError(f'{printable(args.video)}: {len(clip)} frames, shorter '
                    f'than the {burn_in} observed frames (--burn_in)')
  steps = args.rollout or max(1, (len(clip) - burn_in) // stride)
  if steps < 1:
    raise UserError(f'--rollout={steps} must be >= 1')
  observed = model.encode(clip[:burn_in])
  predicted = model.rollout(observed, steps)
  seen, future = model.decode(observed), model.decode(predicted)
  if seen.frames is None:
    raise UserError('this slot model decodes no pixels: nothing to draw')
  real_future = clip[burn_in + stride - 1::stride][:steps]
  blank = np.zeros((steps - len(real_future), *clip.shape[1:]), np.uint8)
  real = np.concatenate([clip[:burn_in], real_future, blank])
  model_frames = np.concatenate([seen.frames, future.frames])
  masks = np.concatenate([seen.masks, future.masks])
  tinted = frames_lib.to_uint8(frames_lib.mask_overlay(
      model_frames / 255.0, masks))
  rows = {'real': real, 'model': model_frames, 'slots': tinted}
  strip = frames_lib.labelled_grid(
      {name: _marked(row, burn_in) for name, row in rows.items()},
      args.scale)
  pictures = [frames_lib.labelled_grid(
      {f'{name} {"observed" if t < burn_in else "predicted"}':
       row[t:t + 1] for name, row in rows.items()}, args.scale)
              for t in range(len(real))]
  out = args.out
  out.mkdir(parents=True, exist_ok=True)
  paths = {'png': out / 'prediction.png', 'gif': out / 'prediction.gif',
           'slots': out / 'slots.npz'}
  write_atomic(paths['png'], _encoded(strip, 'PNG'))
  write_atomic(paths['gif'], _encoded_gif(pictures))
  with open(paths['slots'], 'wb') as f:
    np.savez(f, observed=observed, predicted=predicted, masks=masks)
  frames_needed = burn_in + steps * stride
  if not args.explore:
    return paths
  if len(clip) < frames_needed:
    print(f'explore: no page: the page compares the rollout with the real '
          f'frames, and the clip has {len(clip)} of the {frames_needed} '
          'needed (lower --rollout)', file=sys.stderr)
    return paths
  # The page starts where the model's own burn-in does.
  page = _explore(model, clip[burn_in - needed:frames_needed], steps, out,
                  f'{printable(args.video.name)}: '
                  f'{model.run.slot_model.label} + SlotFormer')
  if page is not None:
    paths['explore'] = Path(page)
  return paths


class _OneClip:
  """The clip and its slots as the explorer reads a split's slots: one
  video, a missing field a KeyError."""

  def __init__(self, item: dict[str, np.ndarray], fields: Sequence[str]):
    self.item, self.fields = item, ('slots', *fields)

  def __len__(self) -> int:
    return 1

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    del index
    return {field: self.item[field] for field in self.fields}


def _explore(model: Any, clip: np.ndarray, steps: int, out: Path,
             title: str) -> str | None:
  """The explorer page of the clip (evaluation/explore.py: rollouts slot
  by slot, remove / freeze counterfactuals) in ``out/explore/``."""
  from slotformer_jax.evaluation import evaluate  # pylint: disable=g-import-not-at-top
  from slotformer_jax.evaluation import explore  # pylint: disable=g-import-not-at-top
  run = model.run
  config = run.config
  eval_config = config.evaluation.copy_and_resolve_references()
  eval_config.rollout_steps = steps
  explore_config = config.explore.copy_and_resolve_references()
  explore_config.num_videos = 1
  dynamics_config = run.dynamics_section('slotformer')
  item = {'slots': model.encode(clip), 'video': clip}
  return explore.explore(
      explore_config, eval_config, dynamics_config,
      slot_model=run.slot_model, slot_params=run.stage1.params,
      dynamics={'slotformer': run.dynamics('slotformer')},
      identity={'workdir': str(run.paths.root), 'clip': title},
      open_slots=lambda fields: _OneClip(item, fields),
      num_true=evaluate.num_true_ids(config.data.max_instances),
      metrics_path=str(out / 'no_metrics.json'),
      output_dir=str(out / 'explore'), title=title)


def _marked(row: np.ndarray, burn_in: int) -> np.ndarray:
  """The row with a white bar on the left of the first predicted frame."""
  row = row.copy()
  if burn_in < len(row):
    row[burn_in, :, :1] = 255
  return row


def _encoded(picture: np.ndarray, kind: str) -> bytes:
  import io  # pylint: disable=g-import-not-at-top
  from PIL import Image  # pylint: disable=g-import-not-at-top
  buffer = io.BytesIO()
  Image.fromarray(picture).save(buffer, kind)
  return buffer.getvalue()


def _encoded_gif(pictures: Sequence[np.ndarray]) -> bytes:
  import io  # pylint: disable=g-import-not-at-top
  from PIL import Image  # pylint: disable=g-import-not-at-top
  images = [Image.fromarray(p) for p in pictures]
  buffer = io.BytesIO()
  images[0].save(buffer, 'GIF', save_all=True, append_images=images[1:],
                 duration=200, loop=0)
  return buffer.getvalue()


def main(argv: Sequence[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  try:
    paths = predict(args)
  except (UserError, FileNotFoundError, ValueError) as error:
    print(f'error: {printable(error)}', file=sys.stderr)
    return 1
  for name, path in paths.items():
    print(f'{name}: {os.fspath(path)}')
  return 0


if __name__ == '__main__':
  sys.exit(main())
