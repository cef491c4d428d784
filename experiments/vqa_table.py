r"""Mean +- std over seeds of the VQA variants of one workdir, as a table.
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_table.py --workdir=runs/vqa [--workdir=...] [--split=test]

Reads vqa/<inputs>_s<seed>/metrics_<split>.json (written by
`--mode=evaluate_vqa`) and vqa/answer_prior_<split>.json of every workdir
given (variants trained in parallel live in separate workdirs: one run
holds a workdir's lock).
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re

import numpy as np

COLUMNS = (('descriptive', 'accuracy'),
           ('explanatory', 'per_option'), ('explanatory', 'per_question'),
           ('predictive', 'per_option'), ('predictive', 'per_question'),
           ('counterfactual', 'per_option'),
           ('counterfactual', 'per_question'))
ROWS = ('future', 'rollout', 'observed', 'blind')


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument('--workdir', required=True, action='append')
  parser.add_argument('--split', default='test')
  args = parser.parse_args()
  runs = collections.defaultdict(list)
  paths = sorted(set(path for workdir in args.workdir for path in glob.glob(
      os.path.join(workdir, 'vqa', '*_s*', f'metrics_{args.split}.json'))))
  for path in paths:
    inputs = re.match(r'(.*)_s\d+$', os.path.basename(os.path.dirname(path)))
    with open(path) as f:
      metrics = json.load(f)
    if 'seeds' in metrics:  # a config.seeds run's summary: its own table
      raise SystemExit(f'{path} is the summary of a run with several seeds '
                       '(mean, std, per seed inside); this table reads '
                       'one-seed workdirs')
    runs[inputs.group(1)].append(metrics)
  header = ' | '.join(f'{t[:5]}. {m.replace("per_", "per ")}'
                      for t, m in COLUMNS)
  print(f'| Aloe input | seeds | {header} |')
  print('|' + '---|' * (len(COLUMNS) + 2))
  for name in ROWS:
    if name not in runs:
      continue
    cells = []
    for t, m in COLUMNS:
      values = [100 * r[t][m] for r in runs[name] if t in r]
      cells.append(f'{np.mean(values):.1f} +- {np.std(values):.1f}'
                   if values else '-')
    print(f'| {name} | {len(runs[name])} | ' + ' | '.join(cells) + ' |')
  priors = [p for workdir in args.workdir for p in glob.glob(os.path.join(
      workdir, 'vqa', f'answer_prior_{args.split}.json'))]
  if priors:
    with open(priors[0]) as f:
      prior = json.load(f)
    cells = [f'{100 * prior[t][m]:.1f}' if t in prior else '-'
             for t, m in COLUMNS]
    print('| answer prior | - | ' + ' | '.join(cells) + ' |')
  templates = sorted({t for rs in runs.values() for r in rs
                      for t in r.get('descriptive_per_template', {})})
  if templates:
    print('\n| descriptive accuracy per template | ' + ' | '.join(
        name for name in ROWS if name in runs) + ' |')
    print('|---|' + '---|' * sum(name in runs for name in ROWS))
    for t in templates:
      cells = []
      for name in ROWS:
        if name not in runs:
          continue
        values = [100 * r['descriptive_per_template'][t]['accuracy']
                  for r in runs[name]
                  if t in r.get('descriptive_per_template', {})]
        cells.append(f'{np.mean(values):.1f} +- {np.std(values):.1f}'
                     if values else '-')
      n = next(r['descriptive_per_template'][t]['questions']
               for rs in runs.values() for r in rs
               if t in r.get('descriptive_per_template', {}))
      print(f'| {t} ({n}) | ' + ' | '.join(cells) + ' |')
  counts = runs[next(iter(runs))][0] if runs else {}
  types = dict.fromkeys(t for t, _ in COLUMNS)
  print('\nquestions: ' + ', '.join(
      f'{t} {counts[t]["questions"]}' for t in types if t in counts))


if __name__ == '__main__':
  main()
