r"""Rollout vs first-frame planning classifier, task by task (issue 11).
Answered (numbers, commands, machine) in docs/experiments/planning.md.

  python experiments/planning_per_task.py --split=test \
      --workdir=runs/ramp_f0 --workdir=runs/ramp_f1 --workdir=runs/ramp_f2

AUCCESS over 16-20 tasks per fold moves by several points between seeds, so
"the rollout classifier is above the first-frame one" needs a paired test:
for every task of ``--split`` ('test', or 'dev' = the training tasks that
choose the epoch), the AUCCESS of each trained classifier (mean over its
seeds), then the difference rollout - first frame, pooled over the given
workdirs (one per fold), with its standard error over tasks.

Reads each workdir's config.json, its SAVi / SlotFormer and the classifiers
that `--mode=train_readout` wrote (planning/<condition>/seed_<k>/).
"""

from __future__ import annotations

import argparse

import numpy as np

from slotformer_jax.run import Run
from slotformer_jax.stages.planning import embedded as planning_stage
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.tasks import planning


def per_task_auccess(run: Run, split: str) -> dict[str, np.ndarray]:
  """{condition: float [tasks]}: each task's AUCCESS, mean over seeds."""
  by_split, outcomes, generation = planning_stage.task_candidates(
      run, (split,))
  out = {}
  for condition in run.config.readout.conditions:
    per_seed = []
    for seed in run.config.readout.seeds:
      model, params = planning_stage.load_classifier(run, condition, seed)
      scores = phyre_planning.candidate_scores(model, params, by_split[split],
                                               generation.num_candidates)
      per_seed.append([planning.plan_auccess([s], [o])
                       for s, o in zip(scores, outcomes[split])])
    out[condition] = np.mean(per_seed, axis=0)
  return out


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--workdir', action='append', required=True)
  parser.add_argument('--split', default='test', choices=('test', 'dev'))
  args = parser.parse_args()
  differences = []
  for workdir in args.workdir:
    run = Run.open(workdir)
    config = run.config
    auccess = per_task_auccess(run, args.split)
    difference = auccess[phyre_planning.ROLLOUT] - auccess[
        phyre_planning.FIRST_FRAME]
    differences.append(difference)
    print(f'{workdir} (fold {config.data.fold}, {len(difference)} '
          f'{args.split} tasks): first frame '
          f'{100 * auccess[phyre_planning.FIRST_FRAME].mean():.1f}, rollout '
          f'{100 * auccess[phyre_planning.ROLLOUT].mean():.1f}, difference '
          f'{100 * difference.mean():+.1f}')
  pooled = np.concatenate(differences)
  error = pooled.std(ddof=1) / np.sqrt(len(pooled)) if len(pooled) > 1 else 0
  print(f'all {len(pooled)} tasks: rollout - first frame '
        f'{100 * pooled.mean():+.2f} +- {100 * error:.2f} (standard error '
        f'over tasks); rollout better on {int((pooled > 0.005).sum())}, '
        f'worse on {int((pooled < -0.005).sum())}')


if __name__ == '__main__':
  main()
