r"""Are the embedded predictive questions answerable from the simulator state?
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_state_probe.py [--config=configs/synthetic_vqa.py]

For every predictive option "the X collides with the Y" of the train and val
splits, re-simulates the video (physics only, no rendering) and fits, on
train, a logistic regression on X's and Y's ground positions and velocities
at the last two observed frames (and the distance and the time / distance
of closest approach if both kept their velocity); prints its per-option
accuracy on val, and that of the minimum centre distance of X and Y over the
frames after the video (what a perfect future shows). A reader of the slots
cannot do better than what the state tells; if this probe is well above 50%
the labels are learnable, and the gap between the two says how much the
future adds to extrapolating the observed end. The dataset must be built
(any `--mode` of the config builds it).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time

import numpy as np
from sklearn.linear_model import LogisticRegression

from slotformer_jax.datasets import clevrer_like
from slotformer_jax.data.sources import resolve_data_dir

_QUESTION_FILES = {'train': 'train', 'val': 'validation'}


def closest_approach(pa: np.ndarray, pb: np.ndarray, va: np.ndarray,
                     vb: np.ndarray, horizon: float) -> tuple[float, float]:
  """(time in [0, horizon], distance) of the closest approach of two points
  at pa, pb [2] moving with constant velocities va, vb [2] (per frame)."""
  d, rv = pa - pb, va - vb
  t = float(np.clip(-np.dot(d, rv) / max(float(np.dot(rv, rv)), 1e-9), 0.0,
                    horizon))
  return t, float(np.linalg.norm(d + t * rv))


def option_features(positions: np.ndarray, a: int, b: int, observed: int,
                    horizon: int) -> tuple[np.ndarray, float]:
  """(state features [15], future minimum distance) of the pair (a, b).

  positions: float [T, O, 2] ground positions of the simulation.
  """
  p = positions
  pa, pb = p[observed - 1, a], p[observed - 1, b]
  va, vb = pa - p[observed - 2, a], pb - p[observed - 2, b]
  t, dmin = closest_approach(pa, pb, va, vb, horizon)
  state = np.concatenate([pa, pb, va, vb, pa - pb, va - vb,
                          [np.linalg.norm(pa - pb), t, dmin]])
  future = np.linalg.norm(p[observed:, a] - p[observed:, b], axis=-1).min()
  return state, float(future)


def _rows(config: clevrer_like.ClevrerLikeConfig, root: str, split: str):
  with open(os.path.join(root, 'questions',
                         f'{_QUESTION_FILES[split]}.json')) as f:
    scenes = json.load(f)
  with open(os.path.join(root, split, 'events.jsonl')) as f:
    logs = [json.loads(line) for line in f]
  state, future, label = [], [], []
  for v, scene in enumerate(scenes):
    predictive = [q for q in scene['questions']
                  if q['question_type'] == 'predictive']
    if not predictive:
      continue
    sim = clevrer_like.simulate(clevrer_like.sample_video_scene(
        clevrer_like.video_rng(config.seed, split, v), config), config)
    recorded = [(c['objects'][0], c['objects'][1], c['frame'])
                for c in logs[v]['collisions']]
    if [(a, b, f) for a, b, f, _ in sim['collisions']] != recorded:
      raise RuntimeError(f'{split} video {v}: re-simulation differs from its '
                         'event log (dataset built by another generator?)')
    names = {f"{o['color']} {o['shape']}": i
             for i, o in enumerate(logs[v]['objects'])}
    for q in predictive:
      for choice in q['choices']:
        words = choice['choice'].split()  # the A B collides with the C D
        a, b = names[' '.join(words[1:3])], names[' '.join(words[6:8])]
        s, d = option_features(sim['positions'][..., :2], a, b,
                               config.observed_frames,
                               config.num_frames - config.observed_frames)
        state.append(s)
        future.append([d])
        label.append(int(choice['answer'] == 'correct'))
  return np.array(state), np.array(future), np.array(label)


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument('--config', default='configs/synthetic_vqa.py')
  args = parser.parse_args()
  spec = importlib.util.spec_from_file_location('vqa_config', args.config)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  data = module.get_config().data
  config = clevrer_like.config_from_data_config(data)
  root = str(clevrer_like.dataset_dir(
      config, resolve_data_dir(data.get('data_dir', None))))
  start = time.time()
  train, val = _rows(config, root, 'train'), _rows(config, root, 'val')
  print(f're-simulated in {time.time() - start:.0f} s; options: train '
        f'{len(train[2])} ({train[2].mean():.3f} correct), val '
        f'{len(val[2])} ({val[2].mean():.3f} correct)')
  for name, column in (('last observed state', 0),
                       ('future minimum distance', 1)):
    probe = LogisticRegression(max_iter=5000).fit(train[column], train[2])
    print(f'{name}: per option train {probe.score(train[column], train[2]):.3f}'
          f' val {probe.score(val[column], val[2]):.3f}')


if __name__ == '__main__':
  main()
