"""Conditional vs unconditional SAVi on the embedded data (issue 25).
Answered (numbers, commands, machine) in docs/experiments/conditional_savi.md.

Trains SAVi on configs/synthetic.py (32x32, 2-3 static objects + a launched
sphere) with `savi.initial_slots` 'learned' (unconditional, SlotFormer's
SAVi) and 'boxes' (slots started from the first frame's boxes, SAVi's
conditional model) at the same budget (`--steps` updates, same batch, clip
and learning rate). The seeds of one variant train in ONE program
(`config.seeds`, docs/seeds.md; `seed_data_order='per_seed'`, so seed s is
the one-seed run `--config.seed=s`: its initialisation, step RNG and data
order). Each seed's slots of the test videos are extracted by the
pipeline's own stage (into seed_<s>/slots/test) and scored by the
pipeline's own whole-video evaluation (`evaluation.evaluate_slot_model`),
once over every frame and once skipping the first (SAVi paper). Prints a
markdown table and writes every number to --out/results.json.

  nice -n 10 python experiments/conditional_savi.py --steps=1200 \\
      --seeds=0,1,2 --out=/work/scratch-cond/conditional_savi_seeds
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time

import numpy as np

from slotformer_jax import stages
from slotformer_jax.evaluation import evaluate
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.workdir.settings import accept_config

KINDS = ('learned', 'boxes')
METRICS = ('fg_ari', 'fg_ari_per_frame', 'fg_miou_per_frame', 'ari', 'psnr')


def _config(kind: str, seeds: tuple[int, ...], steps: int):
  spec = importlib.util.spec_from_file_location(
      'synthetic', os.path.join(os.path.dirname(__file__), '..', 'configs',
                                'synthetic.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  config = module.get_config()
  config.seed = seeds[0]
  if len(seeds) > 1:  # one program; seed s as the one-seed run of s
    config.seeds = seeds
    config.seed_data_order = 'per_seed'
  config.savi.initial_slots = kind
  config.savi.num_train_steps = steps
  config.savi.checkpoint_every = steps
  config.extraction.splits = ('test',)
  return config


def run(kind: str, seeds: tuple[int, ...], steps: int, out: str
        ) -> list[dict]:
  """Trains SAVi variant `kind` for every seed of `seeds` (one program when
  several), extracts and scores each seed's test slots; one result per
  seed."""
  config = _config(kind, seeds, steps)
  workdir = os.path.join(out, kind + ''.join(f'_seed{s}' for s in seeds))
  run = Run.create(config, workdir)
  mesh, slot_model = run.mesh, run.slot_model
  accept_config(config.to_dict(), run.paths)
  table = stages.stage_table(run)
  table['prepare_data'](run)  # readers only open data
  started = time.time()
  table['train_savi'](run)
  train_seconds = time.time() - started
  table['extract_slots'](run)
  views = run.seed_views() if run.seeds is not None else [run]
  split = config.evaluation.split
  num_frames = config.data.num_frames
  results = []
  for view in views:
    source = view.slots(split, ('video', 'segmentations'))
    result = {'kind': kind, 'seed': view.seed, 'steps': steps,
              'seeds_in_program': list(seeds),
              'train_seconds_all_seeds': train_seconds,
              'num_videos': len(source)}
    for skip in (False, True):
      config.evaluation.skip_first_frame = skip
      scores = evaluate.evaluate_slot_model(
          config.evaluation, evaluate.num_true_ids(config.data.max_instances),
          mesh, slot_model, view.stage1.params, source, num_frames,
          batch_size=sharding.per_host_batch_size(
              config.evaluation.batch_size, mesh),
          fields=('slots', 'video', 'segmentations'))
      result['skip_first' if skip else 'all_frames'] = {
          name: scores[name] for name in METRICS}
    print(json.dumps(result), flush=True)
    results.append(result)
  return results


def _table(results: list[dict]) -> str:
  lines = ['| initial slots | seed | FG-ARI (all frames) | FG-ARI (skip '
           'first) | FG-ARI per frame | FG-mIoU per frame | ARI | PSNR |',
           '|---|---|---|---|---|---|---|---|']
  for r in results:
    a, s = r['all_frames'], r['skip_first']
    lines.append(f'| {r["kind"]} | {r["seed"]} | {a["fg_ari"]:.3f} | '
                 f'{s["fg_ari"]:.3f} | {a["fg_ari_per_frame"]:.3f} | '
                 f'{a["fg_miou_per_frame"]:.3f} | {a["ari"]:.3f} | '
                 f'{a["psnr"]:.2f} |')
  for kind in KINDS:
    rows = [r for r in results if r['kind'] == kind]
    if not rows:
      continue
    cells = []
    for convention, name in (('all_frames', 'fg_ari'),
                             ('skip_first', 'fg_ari'),
                             ('all_frames', 'fg_ari_per_frame'),
                             ('all_frames', 'fg_miou_per_frame'),
                             ('all_frames', 'ari')):
      values = [r[convention][name] for r in rows]
      cells.append(f'{np.mean(values):.3f} +- {np.std(values):.3f}')
    psnr = [r['all_frames']['psnr'] for r in rows]
    lines.append(f'| **{kind}, mean +- std** | {len(rows)} seeds | '
                 + ' | '.join(cells) + f' | {np.mean(psnr):.2f} |')
  return '\n'.join(lines)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--steps', type=int, default=500)
  parser.add_argument('--seeds', default='0,1,2',
                      help='trained together in one program per variant')
  parser.add_argument('--kinds', default=','.join(KINDS))
  parser.add_argument('--out', required=True)
  args = parser.parse_args()
  seeds = tuple(int(s) for s in args.seeds.split(','))
  results = []
  path = os.path.join(args.out, 'results.json')
  for kind in args.kinds.split(','):
    results.extend(run(kind, seeds, args.steps, args.out))
    os.makedirs(args.out, exist_ok=True)
    with open(path, 'w') as f:
      json.dump(results, f, indent=1)
  print(_table(results))


if __name__ == '__main__':
  main()
