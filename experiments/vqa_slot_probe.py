r"""Is the object a question names held by ONE slot? (issue 12, diagnosis)
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_slot_probe.py --workdir=runs/vqa [--frame=23]

Aloe answers "will the red cube collide with the blue sphere" only if it can
find the slots of those objects. This probe asks whether SAVi's slots are
object-centric on the embedded CLEVRER-like data, at one frame (default: the
last observed one), with SAVi's own decoder:

* decomposition: the share of each slot's alpha mass that falls on objects
  (a slot that holds an object is mostly on it; a slot that tiles the image
  has about the image's object-pixel fraction), and per object the largest
  mean alpha any one slot puts on its pixels;
* assignment: each slot goes to the ground-truth object that holds most of
  the pixels where it wins the alpha argmax (at least 2, and at least half
  of its pixels; else the slot is not an object slot);
* probes on the assigned slots, fitted on train videos, scored on val:
  logistic regression slot -> colour and -> shape (accuracy, and the
  majority class), ridge regression slot -> box centre (R^2 per axis).

Needs the workdir's SAVi and extracted slots (`--mode=extract_slots`) and the
dataset (`SLOTFORMER_DATA_DIR`). The probes are fitted with numpy.
"""

from __future__ import annotations

import argparse
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
from slotformer_jax.datasets.synthetic import COLORS, SHAPES
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.sources import resolve_data_dir
from slotformer_jax.runtime import sharding
from slotformer_jax.slot_models.savi import build_decoder


def assign_slots(winner: np.ndarray, segmentation: np.ndarray,
                 num_objects: int, min_pixels: int = 2) -> dict[int, int]:
  """slot -> object id (0-based) for the slots that hold an object.

  Args:
    winner: int [H, W] argmax slot of the decoder's alpha masks.
    segmentation: int [H, W] ground-truth object id + 1 (0: background).
  A slot holds object o if o covers most of the slot's winning pixels
  (at least ``min_pixels``, and at least half of them).
  """
  out = {}
  for k in np.unique(winner):
    ids = segmentation[winner == k]
    counts = np.bincount(ids, minlength=num_objects + 1)[1:num_objects + 1]
    if counts.size and counts.max() >= min_pixels and (
        counts.max() * 2 >= ids.size):
      out[int(k)] = int(counts.argmax())
  return out


def _standardise(train: np.ndarray, test: np.ndarray):
  mean, std = train.mean(0), train.std(0) + 1e-6
  add_bias = lambda x: np.c_[(x - mean) / std, np.ones(len(x))]
  return add_bias(train), add_bias(test)


def logistic_probe(x_train, y_train, x_test, y_test, num_classes: int,
                   l2: float = 1e-3, steps: int = 2000, lr: float = 0.5):
  """(train accuracy, test accuracy, test majority-class accuracy) of a
  softmax regression fitted by gradient descent."""
  a, b = _standardise(x_train, x_test)
  weights = np.zeros((a.shape[1], num_classes))
  onehot = np.eye(num_classes)[y_train]
  for _ in range(steps):
    z = a @ weights
    p = np.exp(z - z.max(1, keepdims=True))
    p /= p.sum(1, keepdims=True)
    weights -= lr * (a.T @ (p - onehot) / len(a) + l2 * weights)
  majority = np.bincount(y_train, minlength=num_classes).argmax()
  return (float(((a @ weights).argmax(1) == y_train).mean()),
          float(((b @ weights).argmax(1) == y_test).mean()),
          float((y_test == majority).mean()))


def ridge_r2(x_train, y_train, x_test, y_test, l2: float = 1.0):
  """Test R^2 per output column of a ridge regression."""
  a, b = _standardise(x_train, x_test)
  weights = np.linalg.solve(a.T @ a + l2 * np.eye(a.shape[1]), a.T @ y_train)
  residual = ((b @ weights - y_test) ** 2).sum(0)
  return 1.0 - residual / ((y_test - y_test.mean(0)) ** 2).sum(0)


def _split(config, workdir, root, split, frame, decode):
  source = SlotSource(Paths.of(workdir, config.stage1_workdir).slots(split))
  segmentation = np.load(os.path.join(root, split, 'segmentations.npy'),
                         mmap_mode='r')[:, frame]
  boxes = np.load(os.path.join(root, split, 'boxes.npy'), mmap_mode='r')
  with open(os.path.join(root, split, 'events.jsonl')) as f:
    objects = [json.loads(line)['objects'] for line in f]
  slots = np.stack([source[i]['slots'][frame] for i in range(len(source))])
  alpha, winner = decode(jnp.asarray(slots))
  alpha, winner = np.asarray(alpha)[..., 0], np.asarray(winner)  # [V,N,H,W]
  on_objects = segmentation[:, None] > 0
  purity = (alpha * on_objects).sum((2, 3)) / alpha.sum((2, 3))
  coverage, x, colour, shape, centre = [], [], [], [], []
  num_visible = 0
  for v in range(len(source)):
    for o in range(len(objects[v])):
      pixels = segmentation[v] == o + 1
      if pixels.sum() >= 2:
        num_visible += 1
        coverage.append(alpha[v][:, pixels].mean(1).max())
    for k, o in assign_slots(winner[v], segmentation[v],
                             len(objects[v])).items():
      x.append(slots[v, k])
      colour.append(COLORS.index(objects[v][o]['color']))
      shape.append(SHAPES.index(objects[v][o]['shape']))
      box = boxes[v, frame, o]
      centre.append([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
  return {'purity': purity.ravel(), 'object_fraction': on_objects.mean(),
          'coverage': np.array(coverage), 'visible': num_visible,
          'x': np.array(x), 'colour': np.array(colour),
          'shape': np.array(shape), 'centre': np.array(centre)}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--workdir', required=True)
  parser.add_argument('--frame', type=int, default=None,
                      help='frame to probe (default: the last observed)')
  args = parser.parse_args()
  with open(os.path.join(args.workdir, 'config.json')) as f:
    config = ml_collections.ConfigDict(json.load(f))
  frame = (config.data.observed_frames - 1 if args.frame is None
           else args.frame)
  root = str(clevrer_like_data.dataset_dir(
      clevrer_like_data.config_from_data_config(config.data),
      resolve_data_dir(config.data.get('data_dir', None))))
  loaded = Run.open(args.workdir).stage1
  params, step = loaded.params['savi'], loaded.step
  decoder_params = sharding.gather_to_host(params)['decoder']
  decoder = build_decoder(config.savi.decoder,
                                 tuple(config.data.resolution))

  @jax.jit
  def decode(slots):
    out = decoder.apply({'params': decoder_params}, slots)
    return out.alpha_masks, out.segmentation

  train, val = (_split(config, args.workdir, root, s, frame, decode)
                for s in ('train', 'val'))
  q = lambda a: ' / '.join(f'{v:.2f}' for v in np.quantile(a, [.25, .5, .75]))
  print(f'SAVi step {step}, frame {frame}; val videos:')
  print(f'  object pixels {val["object_fraction"]:.3f} of the image; alpha '
        f'mass on objects per slot (quartiles) {q(val["purity"])}')
  print(f'  per object, the best slot\'s mean alpha on its pixels '
        f'(quartiles) {q(val["coverage"])}')
  for name, s in (('train', train), ('val', val)):
    print(f'  {name}: {s["visible"]} visible objects, {len(s["x"])} slots '
          'assigned to one')
  if len(train['x']) < 10 or len(val['x']) < 5:
    print('too few object slots to fit probes')
    return
  for name, labels, classes in (('colour', 'colour', len(COLORS)),
                                ('shape', 'shape', len(SHAPES))):
    fit_train, fit_val, majority = logistic_probe(
        train['x'], train[labels], val['x'], val[labels], classes)
    print(f'slot -> {name}: train {fit_train:.3f}, val {fit_val:.3f} '
          f'(val majority {majority:.3f})')
  r2 = ridge_r2(train['x'], train['centre'], val['x'], val['centre'])
  print(f'slot -> box centre: val R^2 y {r2[0]:.3f}, x {r2[1]:.3f}')


if __name__ == '__main__':
  main()
