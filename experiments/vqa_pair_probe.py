r"""Do the slots after the video tell whether X and Y will collide? (issue 12)
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_pair_probe.py --workdir=runs/vqa [--split=val]

Aloe must both find the slots of the objects a predictive choice names and
read the future from them. This probe takes the first part away and asks
only the second: is the answer in SlotFormer's rollout, and is it there more
than in the observed end of the video?

For every predictive option "the X collides with the Y":

1. X and Y get their slots at the last observed frame: each object the slot
   with the largest mean decoded alpha on its ground-truth pixels (options
   with an object out of view there are left out and counted);
   SAVi and SlotFormer keep a slot's index over time, so the same two slot
   indices follow X and Y in every later frame.
2. A ridge regression, fitted on the training videos' assigned slots at that
   frame, reads a slot's box centre (the slot probe reports its R^2).
3. One small feature set per input, a logistic regression fitted on the
   training options, scored on ``--split``:

   * ``observed``: X's and Y's decoded centres and velocities at the last two
     observed frames, their distance, and the time and distance of closest
     approach if both kept their velocity (the extrapolation the state probe
     does on simulator states);
   * ``copy-last``: the same distance at the last observed frame only;
   * ``rollout``: the minimum decoded centre distance of X and Y over
     SlotFormer's rolled-out frames (``vqa/slots``, written by `vqa_slots`);
   * ``future``: the same over SAVi's slots of the real frames after the video
     (the ceiling of any reader of the rollout).

Needs the workdir's SAVi, its extracted slots over the whole simulated clip,
the `vqa_slots` stage, and the dataset (`SLOTFORMER_DATA_DIR`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os

from slotformer_jax.runtime import xla_flags

xla_flags.apply_fast_cpu_flags()

# pylint: disable=g-import-not-at-top,wrong-import-position
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax.run import Run
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.datasets import clevrer_like as clevrer_like_data
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.sources import resolve_data_dir
from slotformer_jax.runtime import sharding
from slotformer_jax.slot_models.savi import build_decoder

_QUESTION_FILES = {'train': 'train', 'val': 'validation', 'test': 'test'}
INPUTS = ('observed', 'copy-last', 'rollout', 'future')


def _benchmark(name: str):
  """Another script of this folder, loaded as a module."""
  spec = importlib.util.spec_from_file_location(
      name, os.path.join(os.path.dirname(__file__), f'{name}.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def pair_features(centres: np.ndarray, a: int, b: int, observed: int
                  ) -> dict[str, np.ndarray]:
  """Features of each input for the slot pair (a, b).

  Args:
    centres: float [2, T, N, 2] decoded box centres of every slot of one
      video, frames < ``observed`` from the video itself: [0] followed by
      SlotFormer's rollout, [1] by SAVi's slots of the real frames after it.
    a, b: slot indices of X and Y.
    observed: number of observed frames.
  """
  rollout, future = centres[0], centres[1]
  horizon = rollout.shape[0] - observed
  pa, pb = rollout[observed - 1, a], rollout[observed - 1, b]
  va, vb = pa - rollout[observed - 2, a], pb - rollout[observed - 2, b]
  t, dmin = _benchmark('vqa_state_probe').closest_approach(
      pa, pb, va, vb, horizon)
  last = np.linalg.norm(pa - pb)
  distance = lambda c: np.linalg.norm(c[observed:, a] - c[observed:, b],
                                      axis=-1).min()
  return {
      'observed': np.concatenate([pa, pb, va, vb, pa - pb, va - vb,
                                  [last, t, dmin]]),
      'copy-last': np.array([last]),
      'rollout': np.array([distance(rollout)]),
      'future': np.array([distance(future)]),
  }


def object_slots(alpha: np.ndarray, segmentation: np.ndarray,
                 num_objects: int) -> dict[int, int]:
  """object id (0-based) -> the slot with the largest mean alpha on its
  pixels, for every object with at least one pixel.

  Args:
    alpha: float [N, H, W] SAVi's decoded alpha masks.
    segmentation: int [H, W] ground-truth object id + 1 (0: background).
  """
  out = {}
  for o in range(num_objects):
    pixels = segmentation == o + 1
    if pixels.any():
      out[o] = int(alpha[:, pixels].mean(1).argmax())
  return out


def _options(root: str, split: str):
  """(video, object a, object b, label) of every predictive option."""
  with open(os.path.join(root, 'questions',
                         f'{_QUESTION_FILES[split]}.json')) as f:
    scenes = json.load(f)
  with open(os.path.join(root, split, 'events.jsonl')) as f:
    objects = [json.loads(line)['objects'] for line in f]
  offset = clevrer_like_data.SCENE_OFFSETS[split]
  out = []
  for scene in scenes:
    v = int(scene['scene_index']) - offset
    names = {f"{o['color']} {o['shape']}": i for i, o in enumerate(objects[v])}
    for q in scene['questions']:
      if q['question_type'] != 'predictive':
        continue
      for choice in q['choices']:
        words = choice['choice'].split()  # the A B collides with the C D
        out.append((v, names[' '.join(words[1:3])],
                    names[' '.join(words[6:8])],
                    int(choice['answer'] == 'correct')))
  return out


def _split_rows(config, workdir, root, split, decode, probe):
  """Per option: features of every input; and the train slots -> centres."""
  observed = config.vqa.video_length
  frame = observed - 1
  source = SlotSource(Paths.of(workdir, config.stage1_workdir).slots(split))
  with_rollout = np.load(os.path.join(workdir, 'vqa', 'slots', f'{split}.npy'),
                         mmap_mode='r')
  length = with_rollout.shape[1]
  segmentation = np.load(os.path.join(root, split, 'segmentations.npy'),
                         mmap_mode='r')[:, frame]
  boxes = np.load(os.path.join(root, split, 'boxes.npy'), mmap_mode='r')
  num_objects = np.load(os.path.join(root, split, 'num_objects.npy'))
  real = np.stack([source[i]['slots'][:length] for i in range(len(source))])
  if real.shape[1] < length:
    raise ValueError(f'the extracted slots have {real.shape[1]} frames, the '
                     f'rollout reaches frame {length}: extract the whole clip')
  alpha, _ = decode(jnp.asarray(real[:, frame]))
  alpha = np.asarray(alpha)[..., 0]  # [V, N, H, W]
  slot_of, x, centre = [], [], []
  for v in range(len(real)):
    slot_of.append(object_slots(alpha[v], segmentation[v],
                                int(num_objects[v])))
    for o, k in slot_of[-1].items():
      x.append(real[v, frame, k])
      box = boxes[v, frame, o]
      centre.append([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
  return {'real': real, 'rollout': with_rollout, 'slot_of': slot_of,
          'options': _options(root, split), 'x': np.array(x),
          'centre': np.array(centre)}


def _features(rows, read_centre, observed: int):
  features = {name: [] for name in INPUTS}
  labels, skipped = [], 0
  for v, a, b, label in rows['options']:
    slots = rows['slot_of'][v]
    if a not in slots or b not in slots:
      skipped += 1
      continue
    centres = np.stack([read_centre(np.asarray(rows['rollout'][v])),
                        read_centre(rows['real'][v])])
    for name, f in pair_features(centres, slots[a], slots[b],
                                 observed).items():
      features[name].append(f)
    labels.append(label)
  return ({k: np.array(v) for k, v in features.items()}, np.array(labels),
          skipped)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--workdir', required=True)
  parser.add_argument('--split', default='val', choices=('val', 'test'))
  args = parser.parse_args()
  with open(os.path.join(args.workdir, 'config.json')) as f:
    config = ml_collections.ConfigDict(json.load(f))
  root = str(clevrer_like_data.dataset_dir(
      clevrer_like_data.config_from_data_config(config.data),
      resolve_data_dir(config.data.get('data_dir', None))))
  probe = _benchmark('vqa_slot_probe')
  loaded = Run.open(args.workdir).stage1
  params, step = loaded.params['savi'], loaded.step
  decoder_params = sharding.gather_to_host(params)['decoder']
  decoder = build_decoder(config.savi.decoder,
                                 tuple(config.data.resolution))

  @jax.jit
  def decode(slots):
    out = decoder.apply({'params': decoder_params}, slots)
    return out.alpha_masks, out.segmentation

  train = _split_rows(config, args.workdir, root, 'train', decode, probe)
  test = _split_rows(config, args.workdir, root, args.split, decode, probe)
  # Ridge slot -> centre on the training videos' assigned slots.
  mean, std = train['x'].mean(0), train['x'].std(0) + 1e-6
  design = np.c_[(train['x'] - mean) / std, np.ones(len(train['x']))]
  weights = np.linalg.solve(design.T @ design + np.eye(design.shape[1]),
                            design.T @ train['centre'])

  def read_centre(slots: np.ndarray) -> np.ndarray:  # [T, N, D] -> [T, N, 2]
    flat = slots.reshape(-1, slots.shape[-1])
    return (np.c_[(flat - mean) / std, np.ones(len(flat))] @ weights
            ).reshape(slots.shape[:-1] + (2,))

  observed = config.vqa.video_length
  f_train, y_train, skip_train = _features(train, read_centre, observed)
  f_test, y_test, skip_test = _features(test, read_centre, observed)
  r2 = probe.ridge_r2(train['x'], train['centre'], test['x'], test['centre'])
  print(f'SAVi step {step}; slot -> centre R^2 on {args.split} '
        f'{r2[0]:.3f} / {r2[1]:.3f}')
  print(f'predictive options with both objects in a slot: train '
        f'{len(y_train)} (skipped {skip_train}), {args.split} {len(y_test)} '
        f'(skipped {skip_test}, {y_test.mean():.3f} correct)')
  for name in INPUTS:
    fit, score, majority = probe.logistic_probe(
        f_train[name], y_train, f_test[name], y_test, 2)
    print(f'{name:10s} per option: train {fit:.3f}, {args.split} '
          f'{score:.3f} (majority {majority:.3f})')


if __name__ == '__main__':
  main()
