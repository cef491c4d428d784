"""Does the future tell more than the first frame, in simulator states? (issue 11)
Answered (numbers, commands, machine) in docs/experiments/planning.md.

The planning classifier on SAVi slots of the first frame (85.9 mean AUCCESS
over 3 folds) is not beaten by the one on first frame + SlotFormer rollout
(84.1). Before blaming SlotFormer, check the task itself: train a success
classifier on SIMULATOR STATES of the embedded PHYRE-like tasks
(tasks/phyre_world.py, configs/synthetic_phyre.py), once on the first
frame (+ the action) and once on later frames of the TRUE simulation. If the
true future is not far above the first frame, no dynamics model can help.

Per frame the "slots" are five role rows (green, goal, gray dynamic body,
black static body, red ball; absent -> zeros), each
[present, x, y, cos angle, sin angle, radius, width, height, is_ball] (lengths
/ WORLD); the action (x, y, r) is appended. Inputs: 'first_frame' (frame 0),
'frames_0_3' (the official classifier's frames), 'frames_0_2_4_10' (the
rollout classifier's readout.selected_steps), 'all_frames' (0..10).
Heads: a 2-hidden-layer MLP (64 wide) and logistic regression, trained as the
task does (every solving + readout.negatives_per_task failing valid
candidates per training task, tasks/phyre_planning.task_splits), epoch chosen
by AUCCESS on the dev tasks, then AUCCESS (tasks/planning.plan_auccess) and
accuracy at p = 0.5 over every valid candidate of the test tasks. States come
from phyre_like.simulate(record=True) (physics only, no rendering), whose
outcome is the candidate's label.

  nice -n 19 python experiments/planning_state_ceiling.py --folds 0 1 2
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import tempfile
import time

import flax.linen as nn
import numpy as np

from slotformer_jax.datasets import synthetic_phyre as phyre_like_data
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.tasks import planning
from slotformer_jax.stages import readout_fit
from slotformer_jax.tasks import readout as readout_lib
from slotformer_jax.tasks import phyre_world as phyre_like

ROLES = (phyre_like.GREEN, phyre_like.GOAL, phyre_like.DYNAMIC,
         phyre_like.STATIC, phyre_like.ACTION)
INPUTS = {'first_frame': (0,), 'frames_0_3': (0, 3),
          'frames_0_2_4_10': (0, 2, 4, 10), 'all_frames': tuple(range(11))}


class MLP(nn.Module):
  width: int = 64

  @nn.compact
  def __call__(self, x):
    x = nn.relu(nn.Dense(self.width)(x))
    x = nn.relu(nn.Dense(self.width)(x))
    return nn.Dense(1)(x)[..., 0]


class Logistic(nn.Module):

  @nn.compact
  def __call__(self, x):
    return nn.Dense(1)(x)[..., 0]


def fit_head(model, train, select, fit_config, seed):
  """(params, log) of a head fitted as the pipeline fits its readouts
  (`readout_fit.fit_readout`), in a folder thrown away after."""
  with tempfile.TemporaryDirectory() as directory:
    return readout_fit.fit_readout(directory, 'head', model, train, select,
                                   fit_config, seed)


def role_rows(tasks) -> tuple[str, ...]:
  """One row per body a kind can have: ROLES, with a kind repeated as often
  as the most bodies of that kind in one task (the first templates have at
  most one of each, so their rows are ROLES exactly)."""
  most = {kind: max([1] + [sum(b.kind == kind for b in t.bodies)
                           for t in tasks]) for kind in ROLES}
  return tuple(kind for kind in ROLES for _ in range(most[kind]))


def frame_rows(bodies, poses, roles=ROLES) -> np.ndarray:
  """float32 [len(roles), 9] for one frame; the k-th body of a kind goes to
  that kind's k-th row."""
  rows = np.zeros((len(roles), 9), np.float32)
  seen = {kind: 0 for kind in ROLES}
  for body, ((x, y), angle) in zip(bodies, poses):
    w = phyre_like.WORLD
    row = [i for i, kind in enumerate(roles) if kind == body.kind][
        seen[body.kind]]
    seen[body.kind] += 1
    rows[row] = [
        1.0, x / w, y / w, np.cos(angle), np.sin(angle), body.radius / w,
        body.size[0] / w, body.size[1] / w, float(body.shape == 'ball')]
  return rows


def simulate_task(task, actions, config, roles=ROLES):
  """(outcomes int8 [A], states float32 [A, T, R, 9]; invalid rows zero)."""
  outcomes = np.full(len(actions), planning.INVALID, np.int8)
  states = np.zeros((len(actions), config.num_frames, len(roles), 9),
                    np.float32)
  for i, action in enumerate(actions):
    result = phyre_like.simulate(task, action, config, record=True)
    outcomes[i] = result['outcome']
    if result['outcome'] != planning.INVALID:
      states[i] = [frame_rows(result['bodies'], poses, roles)
                   for poses in result['states']]
  return outcomes, states


def features(states, actions, frames) -> np.ndarray:
  x = states[:, list(frames)].reshape(len(states), -1)
  return np.concatenate([x, actions.astype(np.float32)], -1)


def main():
  parser = argparse.ArgumentParser()
  parser.add_argument('--config', default='configs/synthetic_phyre.py')
  parser.add_argument('--folds', type=int, nargs='+', default=[0])
  parser.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
  parser.add_argument('--epochs', type=int, default=40)
  parser.add_argument('--inputs', nargs='+', default=list(INPUTS))
  parser.add_argument('--heads', nargs='+', default=['mlp', 'logistic'])
  parser.add_argument('--templates', nargs='+', default=None,
                      help='override config.data.templates (names of '
                      'tasks/phyre_world.ALL_TEMPLATES)')
  parser.add_argument('--tasks_per_template', type=int, default=None)
  args = parser.parse_args()
  path, _, variant = args.config.partition(':')
  spec = importlib.util.spec_from_file_location('cfg', path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  run_config = module.get_config(variant)
  if args.templates:
    run_config.data.templates = tuple(args.templates)
  if args.tasks_per_template:
    run_config.data.tasks_per_template = args.tasks_per_template
  generation = phyre_like_data.config_from_data_config(run_config.data)
  actions = phyre_like.candidate_actions(generation)
  start = time.time()
  tasks = phyre_like.all_tasks(generation)
  roles = role_rows(tasks)
  sims = {(t.template, t.index): simulate_task(t, actions, generation, roles)
          for t in tasks}  # fold-independent
  sim_s = time.time() - start
  print(f'simulated {len(sims)} tasks x {len(actions)} candidates in '
        f'{sim_s:.0f} s', flush=True)
  results = {'config': args.config, 'templates': list(generation.templates),
             'tasks_per_template': generation.tasks_per_template,
             'simulation_s': round(sim_s, 1),
             'epochs': args.epochs, 'seeds': args.seeds}
  heads = {'mlp': MLP, 'logistic': Logistic}
  for fold in args.folds:
    run_config.data.fold = fold
    splits = phyre_planning.task_splits(run_config)
    keys = {s: [(t.template, t.index) for t in v] for s, v in splits.items()}
    outcomes = {s: [sims[k][0] for k in v] for s, v in keys.items()}
    results[f'fold{fold}/random'] = float(np.mean([
        100 * planning.plan_auccess(planning.random_scores(
            outcomes['test'], seed), outcomes['test'])
        for seed in args.seeds]))
    results[f'fold{fold}/oracle'] = 100 * planning.plan_auccess(
        planning.oracle_scores(outcomes['test']), outcomes['test'])
    for name in args.inputs:
      frames = INPUTS[name]
      feats = {s: [features(sims[k][1], actions, frames) for k in v]
               for s, v in keys.items()}
      rng = np.random.default_rng(run_config.seed)  # as train_readout
      rows, labels = [], []
      for f, o in zip(feats['train'], outcomes['train']):
        valid = np.flatnonzero(o != planning.INVALID)
        solved = o[valid] == planning.SOLVED
        keep = valid[np.concatenate([
            np.flatnonzero(solved),
            rng.permutation(np.flatnonzero(~solved))[
                :run_config.readout.negatives_per_task]])]
        rows.append(f[keep])
        labels.append((o[keep] == planning.SOLVED).astype(np.float32))
      train_x, train_y = np.concatenate(rows), np.concatenate(labels)
      mean, std = train_x.mean(0), train_x.std(0) + 1e-6

      def scores_of(model, params, split, mean=mean, std=std, feats=feats):
        out = []
        for f, o in zip(feats[split], outcomes[split]):
          s = np.full(len(o), -np.inf)
          valid = o != planning.INVALID
          s[valid] = readout_lib.predict(model, params,
                                         (f[valid] - mean) / std)
          out.append(s)
        return out

      for head in args.heads:
        model = heads[head]()
        aucs, accs, devs = [], [], []
        for seed in args.seeds:
          params, log = fit_head(
              model, ((train_x - mean) / std, train_y),
              lambda p, model=model: planning.plan_auccess(
                  scores_of(model, p, 'dev'), outcomes['dev']),
              readout_lib.FitConfig(epochs=args.epochs, batch_size=128,
                                    learning_rate=1e-3), seed)
          test = scores_of(model, params, 'test')
          aucs.append(100 * planning.plan_auccess(test, outcomes['test']))
          devs.append(100 * log['best_score'])
          hits = [((s[o != planning.INVALID] > 0.5)
                   == (o[o != planning.INVALID] == planning.SOLVED))
                  for s, o in zip(test, outcomes['test'])]
          accs.append(100 * np.concatenate(hits).mean())
        key = f'fold{fold}/{name}/{head}'
        results[key] = {'auccess': round(float(np.mean(aucs)), 1),
                        'auccess_std': round(float(np.std(aucs)), 1),
                        'per_seed': [round(a, 1) for a in aucs],
                        'dev_auccess': round(float(np.mean(devs)), 1),
                        'accuracy': round(float(np.mean(accs)), 1),
                        'train_pairs': len(train_y),
                        'train_solving': round(float(train_y.mean()), 3)}
        print(f'fold {fold} {name:16s} {head:8s} AUCCESS '
              f'{np.mean(aucs):5.1f} +- {np.std(aucs):4.1f} '
              f'{[round(a, 1) for a in aucs]} dev {np.mean(devs):5.1f} '
              f'acc {np.mean(accs):5.1f}', flush=True)
    print(f'fold {fold} random {results[f"fold{fold}/random"]:.1f} oracle '
          f'{results[f"fold{fold}/oracle"]:.1f}', flush=True)
  for name in args.inputs:
    for head in args.heads:
      values = [results[f'fold{f}/{name}/{head}']['auccess']
                for f in args.folds]
      results[f'mean/{name}/{head}'] = round(float(np.mean(values)), 1)
  results['total_s'] = round(time.time() - start, 1)
  print(json.dumps(results))


if __name__ == '__main__':
  main()
