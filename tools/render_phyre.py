"""Renders PHYRE rollouts into the layout ``slotformer_jax.data.phyre`` reads.

The ``phyre`` simulator has no wheel for the Python this project uses, so run
this script once in an environment where ``pip install phyre`` works (phyre
0.2.2 has Linux wheels for CPython 3.6-3.9; this script needs 3.7+ and only
numpy, Pillow and phyre), then convert its output anywhere::

    python tools/render_phyre.py --out=/data/phyre_rollouts --fold=0
    python -m slotformer_jax.data.prepare --dataset=phyre \\
        --source=/data/phyre_rollouts --data_dir=/data/slotformer

What it renders (the SlotFormer / RPIN recipe, see the SlotFormer appendix):

* BALL tier, ``ball_within_template`` evaluation setup, fold ``--fold``:
  split ``train`` = the fold's train + dev tasks, ``val`` = its test tasks;
* per task, from PHYRE's default 100k-action cache: ``int(int(2000 *
  pos_ratio) * data_ratio)`` solving and ``int(int(2000 * (1 - pos_ratio)) *
  data_ratio)`` failing actions for train (500 instead of 2000 for val),
  shuffled with ``numpy.random.RandomState(seed)`` task by task (positives
  then negatives), which reproduces the official selection for
  ``--seed=<fold>``; ``--actions_file`` takes an explicit list instead;
* each action simulated at ``--fps`` frames per simulated second (PHYRE
  runs 60 steps per second, so every ``60 // fps``-th step is kept), at most
  ``--max_frames`` frames, rendered with PHYRE's palette on a black
  background (PHYRE's white background and black colour swapped; the paper
  found light objects hard to segment on white).

Output layout (also documented in docs/datasets.md)::

    <out>/meta.json
    <out>/<split>/rollouts.jsonl      # {"id", "task", "action", "success",
                                      #  "num_frames"}, one line per rollout
    <out>/<split>/frames/<id>.png     # frames stacked vertically, RGB

Re-running resumes: rollouts already listed in ``rollouts.jsonl`` are kept.
This file is not part of the package and imports nothing from it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import multiprocessing
import os
import sys
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

# Must match slotformer_jax/datasets/phyre.py (FORMAT, FORMAT_VERSION).
FORMAT = 'slotformer-phyre-rollouts'
FORMAT_VERSION = 1
STEPS_PER_SECOND = 60  # PHYRE's simulation rate
# PHYRE colour indices: 0 is the white background, 6 is black.
WHITE_INDEX, BLACK_INDEX = 0, 6
TEMPLATES = tuple(f'{i:05d}' for i in range(25))  # the BALL-tier templates
SPLIT_BASE_ACTIONS = {'train': 2000, 'val': 500}

# One rollout to render: (id, task id, task index in the simulator, action,
# label from the cache).
Rollout = Tuple[str, str, int, Tuple[float, float, float], int]


def black_background(observation: np.ndarray) -> np.ndarray:
  """Swaps PHYRE's white (background) and black colour indices."""
  out = observation.copy()
  out[observation == WHITE_INDEX] = BLACK_INDEX
  out[observation == BLACK_INDEX] = WHITE_INDEX
  return out


def render_frames(phyre: Any, images: np.ndarray,
                  max_frames: int) -> np.ndarray:
  """uint8 [T, H, W, 3]: the first ``max_frames`` observations as RGB.

  ``phyre.observations_to_uint8_rgb`` maps colour indices to PHYRE's palette
  and flips the image so that up is up.
  """
  return np.stack([phyre.observations_to_uint8_rgb(black_background(image))
                   for image in images[:max_frames]])


def filmstrip(frames: np.ndarray) -> np.ndarray:
  """[T, H, W, 3] -> [T * H, W, 3], frames top to bottom."""
  return frames.reshape(-1, *frames.shape[2:])


def select_actions(statuses: np.ndarray, actions: np.ndarray, num_pos: int,
                   num_neg: int, seed: int) -> List[Tuple[int, np.ndarray,
                                                          int]]:
  """(task index, action, label) per rollout, the official sampling.

  Args:
    statuses: int [num_tasks, A] cached outcomes (1 solved, -1 not solved,
      0 invalid).
    actions: float [A, 3] the cached actions.
    num_pos, num_neg: solving / failing actions kept per task.
    seed: RandomState seed; task by task, positives then negatives are
      shuffled with it (as the official code does with np.random.seed).
  """
  rng = np.random.RandomState(seed)
  out = []
  for task_index, status in enumerate(statuses):
    positives = actions[status == 1].copy()
    negatives = actions[status == -1].copy()
    rng.shuffle(positives)
    rng.shuffle(negatives)
    out += [(task_index, a, 1) for a in positives[:num_pos]]
    out += [(task_index, a, 0) for a in negatives[:num_neg]]
  return out


def split_tasks(phyre: Any, eval_setup: str, fold: int,
                split: str) -> List[str]:
  """Task ids of a split: train = train + dev tasks, val = test tasks."""
  train, dev, test = phyre.get_fold(eval_setup, fold)
  tasks = list(train) + list(dev) if split == 'train' else list(test)
  return [t for t in tasks if t.split(':')[0] in TEMPLATES]


def plan_rollouts(phyre: Any, args: argparse.Namespace, split: str,
                  tasks: Sequence[str]) -> List[Rollout]:
  """The rollouts of a split, ids '000000', '000001', ... in task order."""
  if args.actions_file:
    # Official format: float [N, 4] (task index, x, y, r) + labels [N].
    info = np.load(args.actions_file.format(split=split))
    labels = np.load(args.actions_file.format(split=split).replace(
        '.npy', '-label.npy'))
    chosen = [(int(row[0]), row[1:], int(label))
              for row, label in zip(info, labels)]
  else:
    cache = phyre.get_default_100k_cache(args.tier)
    sample = cache.get_sample(list(tasks), None)
    base = SPLIT_BASE_ACTIONS[split]
    num_pos = int(args.data_ratio * int(base * args.pos_ratio))
    num_neg = int(args.data_ratio * int(base * (1 - args.pos_ratio)))
    chosen = select_actions(np.asarray(sample['simulation_statuses']),
                            np.asarray(sample['actions']), num_pos, num_neg,
                            args.seed)
  return [(f'{i:06d}', tasks[task_index], task_index,
           tuple(float(v) for v in action), label)
          for i, (task_index, action, label) in enumerate(chosen)]


# Per-worker state: the simulator of the split's tasks (built once per
# process by the pool initializer; PHYRE simulators are not picklable).
_WORKER: Dict[str, Any] = {}


def _init_worker(phyre_module_name: str, tasks: Sequence[str], tier: str,
                 frames_dir: str, fps: int, max_frames: int) -> None:
  phyre = importlib.import_module(phyre_module_name)
  _WORKER.update(
      phyre=phyre, simulator=phyre.initialize_simulator(list(tasks), tier),
      frames_dir=frames_dir, stride=STEPS_PER_SECOND // fps,
      max_frames=max_frames)


def _render_one(rollout: Rollout) -> Optional[Dict[str, Any]]:
  """Simulates and writes one rollout; returns its index line (or None)."""
  rollout_id, task, task_index, action, cached_label = rollout
  phyre, simulator = _WORKER['phyre'], _WORKER['simulator']
  simulation = simulator.simulate_action(
      task_index, np.asarray(action), stride=_WORKER['stride'],
      need_images=True, need_featurized_objects=False)
  if simulation.images is None:  # invalid action: nothing to render
    return None
  frames = render_frames(phyre, np.asarray(simulation.images),
                         _WORKER['max_frames'])
  path = os.path.join(_WORKER['frames_dir'], f'{rollout_id}.png')
  tmp = path + '.tmp.png'
  Image.fromarray(filmstrip(frames)).save(tmp)
  os.replace(tmp, path)
  success = int(simulation.status) == 1
  return {'id': rollout_id, 'task': task, 'action': list(action),
          'success': success, 'num_frames': int(len(frames)),
          'cached_success': bool(cached_label)}


def _done_ids(index_path: str) -> set:
  if not os.path.isfile(index_path):
    return set()
  with open(index_path) as f:
    return {json.loads(line)['id'] for line in f if line.strip()}


def render_split(phyre: Any, args: argparse.Namespace, split: str) -> None:
  tasks = split_tasks(phyre, args.eval_setup, args.fold, split)
  rollouts = plan_rollouts(phyre, args, split, tasks)
  split_dir = os.path.join(args.out, split)
  frames_dir = os.path.join(split_dir, 'frames')
  os.makedirs(frames_dir, exist_ok=True)
  index_path = os.path.join(split_dir, 'rollouts.jsonl')
  done = _done_ids(index_path)
  todo = [r for r in rollouts if r[0] not in done]
  print(f'{split}: {len(tasks)} tasks, {len(rollouts)} rollouts, '
        f'{len(todo)} to render', flush=True)
  init = (phyre.__name__, tasks, args.tier, frames_dir, args.fps,
          args.max_frames)
  mismatched = invalid = 0
  with open(index_path, 'a') as index:
    if args.num_workers <= 1:
      _init_worker(*init)
      results: Iterator[Optional[Dict[str, Any]]] = map(_render_one, todo)
      pool = None
    else:
      pool = multiprocessing.Pool(args.num_workers, _init_worker, init)
      results = pool.imap(_render_one, todo, chunksize=16)
    try:
      for count, line in enumerate(results, start=1):
        if line is None:
          invalid += 1
          continue
        mismatched += line.pop('cached_success') != line['success']
        index.write(json.dumps(line) + '\n')
        if count % 1000 == 0:
          index.flush()
          print(f'  {split}: {count} / {len(todo)}', flush=True)
    finally:
      if pool is not None:
        pool.terminate()
  if invalid or mismatched:
    print(f'{split}: {invalid} invalid actions left out; {mismatched} '
          'simulated outcomes differ from the cache (the simulated one is '
          'stored)', flush=True)


def write_meta(phyre: Any, args: argparse.Namespace) -> None:
  """Writes meta.json (or checks that an earlier run used the same settings)."""
  meta = {
      'format': FORMAT, 'format_version': FORMAT_VERSION, 'tier': args.tier,
      'eval_setup': args.eval_setup, 'fold': args.fold, 'fps': args.fps,
      'max_frames': args.max_frames, 'background': 'black',
      # PHYRE observations are SCENE_HEIGHT x SCENE_WIDTH (256 x 256).
      'frame_size': [int(phyre.SCENE_HEIGHT), int(phyre.SCENE_WIDTH)],
      'splits': list(args.splits),
      'data_ratio': args.data_ratio, 'pos_ratio': args.pos_ratio,
      'seed': args.seed, 'actions_file': args.actions_file,
  }
  path = os.path.join(args.out, 'meta.json')
  if os.path.isfile(path):
    with open(path) as f:
      previous = json.load(f)
    if {k: v for k, v in previous.items() if k != 'splits'} != \
        {k: v for k, v in meta.items() if k != 'splits'}:
      raise SystemExit(f'{path} was written with other settings; use a new '
                       '--out folder')
    meta['splits'] = sorted(set(previous['splits']) | set(meta['splits']))
  os.makedirs(args.out, exist_ok=True)
  with open(path, 'w') as f:
    json.dump(meta, f, indent=1, sort_keys=True)


def build_parser() -> argparse.ArgumentParser:
  parser = argparse.ArgumentParser(
      description='Render PHYRE rollouts for slotformer_jax (needs phyre).')
  parser.add_argument('--out', required=True, help='output folder')
  parser.add_argument('--fold', type=int, default=0, help='0..9')
  parser.add_argument('--eval_setup', default='ball_within_template')
  parser.add_argument('--tier', default='ball')
  parser.add_argument('--splits', default='train,val')
  parser.add_argument('--fps', type=int, default=1)
  parser.add_argument('--max_frames', type=int, default=15)
  parser.add_argument('--data_ratio', type=float, default=0.1)
  parser.add_argument('--pos_ratio', type=float, default=0.2)
  parser.add_argument('--seed', type=int, default=None,
                      help='action shuffling seed (default: the fold)')
  parser.add_argument('--actions_file', default=None,
                      help='official action list, with {split} in the name, '
                      'e.g. within-fold_0-{split}-data_0.1-pos_0.2.npy '
                      '(labels read from the matching -label.npy)')
  parser.add_argument('--num_workers', type=int,
                      default=len(os.sched_getaffinity(0))
                      if hasattr(os, 'sched_getaffinity') else 1)
  parser.add_argument('--phyre_module', default='phyre',
                      help=argparse.SUPPRESS)  # tests pass a stand-in
  return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
  args = build_parser().parse_args(argv)
  args.splits = tuple(s for s in args.splits.split(',') if s)
  unknown = [s for s in args.splits if s not in SPLIT_BASE_ACTIONS]
  if unknown:
    raise SystemExit(f'unknown splits {unknown}; use train and/or val')
  if args.seed is None:
    args.seed = args.fold
  if STEPS_PER_SECOND % args.fps:
    raise SystemExit(f'--fps must divide {STEPS_PER_SECOND}')
  try:
    phyre = importlib.import_module(args.phyre_module)
  except ImportError:
    raise SystemExit('This script needs the PHYRE simulator: pip install '
                     'phyre (in an environment whose Python it supports).')
  write_meta(phyre, args)
  for split in args.splits:
    render_split(phyre, args, split)
  return 0


if __name__ == '__main__':
  sys.exit(main())
