r"""Can extrapolating the observed end answer the predictive questions? (issue 12)
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_state_extrapolation.py [--config=configs/synthetic_vqa.py]
      [--variant=big] [--num_train=200 --num_val=100 --num_test=100]

Generates the videos of the config's data settings (physics only: no
rendering, the counterfactual worlds included so that the questions are
exactly those a built dataset gets; ``--num_*`` override the split sizes,
the videos are the dataset's first ones) and, for every option "the X
collides with the Y" of its predictive questions, compares the label with
rules on the simulator's states:

* ``extrapolation``: X and Y keep the ground velocity of their last two
  observed frames; "collides" iff their centre distance comes below the sum
  of their footprint radii + a margin at some frame within predicted_frames
  (``clevrer_like.extrapolated_clearance``). The margin is the one with the
  best per-option accuracy on train (a grid), then scored on val and test.
* ``real future``: the same rule on the simulated positions after the video
  (``clevrer_like.future_clearance``): a sanity check of the rule's
  geometry (the labels come from bullet's contacts, so ~100%).
* ``state probe``: a logistic regression (fitted on train options) on the
  features of experiments/vqa_state_probe.py (X's and Y's positions and
  velocities at the last two observed frames, distance, time and distance
  of closest approach): any learned reader of the observed end.

Prints per split: videos, predictive questions (per 100 videos), options,
the fraction correct, each rule's per-option accuracy, the confusion of the
extrapolation rule, and the generation time per video.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import time

import numpy as np
from sklearn.linear_model import LogisticRegression

from slotformer_jax.datasets import clevrer_like
from slotformer_jax.datasets import clevrer_like_questions as question_generator

MARGINS = np.round(np.arange(-1.0, 0.61, 0.05), 3)


def _module(path: str, name: str):
  spec = importlib.util.spec_from_file_location(name, path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def option_rows(config: clevrer_like.ClevrerLikeConfig, split: str,
                option_features=None) -> dict[str, np.ndarray]:
  """Per predictive option of ``split``: extrapolated and future clearance
  [m], label (1 = correct), state-probe features, the extrapolation's
  verdict (clevrer_like.extrapolation_verdict); and counts."""
  start = time.process_time()
  logs, positions = [], []
  for i in range(config.num_videos(split)):
    video = clevrer_like.generate_video(config, split, i, render=False)
    logs.append(video['events'])
    positions.append(video['positions'])
  seconds = time.process_time() - start
  scenes = question_generator.generate_split(
      logs, config.seed, split,
      video_filenames=[clevrer_like.video_filename(split, i)
                       for i in range(len(logs))],
      scene_offset=clevrer_like.SCENE_OFFSETS[split])
  horizon = config.predicted_frames
  extrapolated, future, label, features, verdicts = [], [], [], [], []
  num_questions = 0
  for log, pos, scene in zip(logs, positions, scenes):
    radii = np.array([clevrer_like.object_radius(o['shape'], o['size'],
                                                 config.object_scale)
                      for o in log.objects])
    names = {question_generator.name(log, i): i
             for i in range(log.num_objects)}
    for q in scene['questions']:
      if q['question_type'] != 'predictive':
        continue
      num_questions += 1
      for choice in q['choices']:
        words = choice['choice'].split()  # the A B collides with the C D
        a, b = names[' '.join(words[1:3])], names[' '.join(words[6:8])]
        approach = clevrer_like.extrapolated_approach(
            pos, radii, a, b, config.observed_frames, horizon)
        extrapolated.append(approach[0])
        verdicts.append(clevrer_like.extrapolation_verdict(*approach,
                                                           horizon))
        future.append(clevrer_like.future_clearance(
            pos, radii, a, b, config.observed_frames))
        label.append(int(choice['answer'] == 'correct'))
        if option_features is not None:
          features.append(option_features(pos[..., :2], a, b,
                                          config.observed_frames,
                                          horizon)[0])
  return {'extrapolated': np.array(extrapolated), 'future': np.array(future),
          'label': np.array(label), 'features': np.array(features),
          'verdict': np.array(verdicts),
          'videos': len(logs), 'questions': num_questions,
          'seconds': seconds}


def rule_accuracy(clearance: np.ndarray, label: np.ndarray,
                  margin: float) -> float:
  """Per-option accuracy of "collides iff clearance < margin"."""
  return float(np.mean((clearance < margin).astype(int) == label))


def best_margin(clearance: np.ndarray, label: np.ndarray) -> float:
  """The margin of MARGINS with the best accuracy (the smallest on ties)."""
  scores = [rule_accuracy(clearance, label, m) for m in MARGINS]
  return float(MARGINS[int(np.argmax(scores))])


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument('--config', default='configs/synthetic_vqa.py')
  parser.add_argument('--variant', default='')
  parser.add_argument('--num_train', type=int, default=200)
  parser.add_argument('--num_val', type=int, default=100)
  parser.add_argument('--num_test', type=int, default=100)
  parser.add_argument('--json', default='', help='also write the results')
  args = parser.parse_args()
  data = _module(args.config, 'vqa_config').get_config(args.variant).data
  config = dataclasses.replace(
      clevrer_like.config_from_data_config(data),
      num_train=args.num_train, num_val=args.num_val, num_test=args.num_test)
  probe = _module(os.path.join(os.path.dirname(os.path.abspath(__file__)),
                               'vqa_state_probe.py'), 'vqa_state_probe')
  print(f'data: {args.config}:{args.variant or "(default)"} -> '
        f'{config.slug}, videos {config.num_train}/{config.num_val}/'
        f'{config.num_test}')
  rows = {split: option_rows(config, split, probe.option_features)
          for split in clevrer_like.SPLITS}
  train = rows['train']
  margin = best_margin(train['extrapolated'], train['label'])
  future_margin = best_margin(train['future'], train['label'])
  logistic = LogisticRegression(max_iter=5000).fit(train['features'],
                                                   train['label'])
  results = {'config': f'{args.config}:{args.variant}', 'slug': config.slug,
             'margin': margin, 'future_margin': future_margin, 'splits': {}}
  print(f'margin chosen on train: extrapolation {margin:+.2f} m, real future '
        f'{future_margin:+.2f} m')
  for split, r in rows.items():
    said = r['extrapolated'] < margin
    yes = r['label'] == 1
    result = {
        'videos': r['videos'], 'predictive_questions': r['questions'],
        'questions_per_100_videos': 100.0 * r['questions'] / r['videos'],
        'options': int(len(r['label'])),
        'fraction_correct': float(r['label'].mean()),
        'extrapolation': rule_accuracy(r['extrapolated'], r['label'], margin),
        'real_future': rule_accuracy(r['future'], r['label'], future_margin),
        'state_probe': float(logistic.score(r['features'], r['label'])),
        # (label, rule) counts: collisions it finds / misses, wrong choices
        # it calls collisions / rightly rejects.
        'confusion': {'correct_said_yes': int((yes & said).sum()),
                      'correct_said_no': int((yes & ~said).sum()),
                      'wrong_said_yes': int((~yes & said).sum()),
                      'wrong_said_no': int((~yes & ~said).sum())},
        'cpu_seconds_per_video': r['seconds'] / max(r['videos'], 1),
    }
    results['splits'][split] = result
    print(f"{split}: {result['videos']} videos, "
          f"{result['predictive_questions']} predictive questions "
          f"({result['questions_per_100_videos']:.0f} per 100 videos), "
          f"{result['options']} options ({result['fraction_correct']:.3f} "
          f"correct) | per option: extrapolation "
          f"{100 * result['extrapolation']:.1f}, real future "
          f"{100 * result['real_future']:.1f}, state probe "
          f"{100 * result['state_probe']:.1f} | {result['confusion']} | "
          f"{result['cpu_seconds_per_video']:.3f} CPU s per video "
          '(physics + counterfactuals)')
  if args.json:
    with open(args.json, 'w') as f:
      json.dump(results, f, indent=1)


if __name__ == '__main__':
  main()
