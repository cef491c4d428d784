r"""The whole embedded VQA comparison as one command, one stage at a time.
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_run.py --workdir=runs/vqa [--seeds=0,1,2] \
      [--inputs=future,rollout,observed,blind] [--split=test] \
      [--config=configs/synthetic_vqa.py:long_savi] [-- <flags>]

Runs, one after the other (never in parallel: the 2-core CPU it is sized
for is shared), the video pipeline of `configs/synthetic_vqa.py` (dataset if
missing, SAVi, slot extraction, SlotFormer, the rollout after every video)
and then `train_vqa` + `evaluate_vqa` for every Aloe input and seed, all in
one workdir (vqa/<inputs>_s<seed>/); prints the table of
experiments/vqa_table.py and writes the wall time of every step to
<workdir>/vqa/run_times.json. Flags after `--` go to every stage (e.g.
`--config.vqa.num_train_steps=500`). The dataset goes to
$SLOTFORMER_DATA_DIR as usual (built by the first stage that needs it).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

CONFIG = 'configs/synthetic_vqa.py'
PIPELINE = ('train_savi', 'extract_slots', 'train_slotformer', 'vqa_slots')


def _run(config: str, args: list[str]) -> float:
  start = time.time()
  subprocess.run([sys.executable, '-m', 'slotformer_jax.main',
                  f'--config={config}'] + args, check=True)
  return time.time() - start


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument('--workdir', required=True)
  parser.add_argument('--config', default=CONFIG,
                      help='config file[:variant] of every stage')
  parser.add_argument('--seeds', default='0,1,2')
  parser.add_argument('--inputs', default='future,rollout,observed,blind')
  parser.add_argument('--split', default='test',
                      help='evaluation split (choose settings on val)')
  parser.add_argument('extra', nargs='*', help='flags for every stage')
  args = parser.parse_args()
  here = os.path.dirname(os.path.abspath(__file__))
  times: dict[str, float] = {}
  start = time.time()
  common = [f'--workdir={args.workdir}'] + args.extra
  for mode in PIPELINE:
    times[mode] = _run(args.config, common + [f'--mode={mode}'])
    print(f'[vqa_run] {mode}: {times[mode]:.0f} s', flush=True)
  for seed in args.seeds.split(','):
    for inputs in args.inputs.split(','):
      variant = [f'--config.vqa.inputs={inputs}', f'--config.vqa.seed={seed}',
                 f'--config.vqa.eval_split={args.split}']
      for mode in ('train_vqa', 'evaluate_vqa'):
        key = f'{mode}/{inputs}_s{seed}'
        times[key] = _run(args.config, common + variant + [f'--mode={mode}'])
        print(f'[vqa_run] {key}: {times[key]:.0f} s', flush=True)
  times['total'] = time.time() - start
  with open(os.path.join(args.workdir, 'vqa', 'run_times.json'), 'w') as f:
    json.dump(times, f, indent=1)
  print(f'[vqa_run] total {times["total"]:.0f} s', flush=True)
  subprocess.run([sys.executable, os.path.join(here, 'vqa_table.py'),
                  f'--workdir={args.workdir}', f'--split={args.split}'],
                 check=True)


if __name__ == '__main__':
  main()
