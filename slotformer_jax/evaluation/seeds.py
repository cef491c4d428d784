"""The evaluation of several seeds (config.seeds) in one summary.

Each seed's evaluation is the one-seed evaluation (`evaluate.evaluate`,
written to `seed_<s>/eval/metrics.json`); this folds them into the run's
`eval/metrics.json`: per metric the mean over the seeds, their standard
deviation and each seed's value. The deviation is the population one
(numpy's `std`, ddof=0), as the contact and planning readouts report their
seeds (`mean +- std`). A seed that diverged in training (its checkpoint
records the update) is not evaluated: it is named with the reason and left
out of every mean, as is a seed whose value of a metric is missing or not
finite (its value is shown as null and the metric's `num_seeds` counts the
seeds in its mean), so no NaN ever reaches a mean unseen.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from slotformer_jax.evaluation import rollout_metrics
from slotformer_jax.files import write_json_atomic

STD = ('population standard deviation over the seeds in the mean (numpy '
       'std, ddof=0), as the readouts report their seeds')
# Counts every seed shares (the protocol's), not metrics to average.
_COUNTS = ('num_videos', 'num_frames')


def _finite(value: Any) -> float | None:
  """A metric value as a float, or None when missing or not finite."""
  if value is None or isinstance(value, bool):
    return None
  value = float(value)
  return value if math.isfinite(value) else None


def statistics(values: dict[int, Any]) -> dict[str, Any]:
  """{seed: value} -> {'mean', 'std', 'num_seeds', 'per_seed'}: the mean
  and population std of the finite values (None when there is none),
  how many there are, and every seed's value (None: missing)."""
  per_seed = {str(seed): _finite(value) for seed, value in values.items()}
  finite = [v for v in per_seed.values() if v is not None]
  return {'mean': float(np.mean(finite)) if finite else None,
          'std': float(np.std(finite)) if finite else None,
          'num_seeds': len(finite), 'per_seed': per_seed}


def _per_step_mean(curves: list[list[Any]]) -> list[float | None]:
  """The per-step mean over the seeds' curves (None where none is
  finite)."""
  out = []
  for step_values in zip(*curves):
    finite = [v for v in map(_finite, step_values) if v is not None]
    out.append(float(np.mean(finite)) if finite else None)
  return out


def fold(per_seed: dict[int, Any]) -> Any:
  """{seed: results} of one shape -> the same nesting with `statistics`
  in place of every number (a seed lacking a key counts as missing
  there); lists and strings are left out (None). E.g. Aloe's metrics per
  question type."""
  present = [v for v in per_seed.values() if v is not None]
  if present and all(isinstance(v, dict) for v in present):
    keys = dict.fromkeys(k for v in present for k in v)
    out = {}
    for key in keys:
      folded = fold({seed: (v or {}).get(key)
                     for seed, v in per_seed.items()})
      if folded is not None:
        out[key] = folded
    return out
  if any(isinstance(v, (list, str, dict)) for v in present):
    return None
  return statistics(per_seed)


def summarise(per_seed: dict[int, dict[str, Any]], excluded: dict[int, str],
              seeds: tuple[int, ...]) -> dict[str, Any]:
  """The run's summary of the seeds' evaluations.

  Args:
    per_seed: {seed: its `evaluate.evaluate` results} of the evaluated
      seeds.
    excluded: {seed: why it was not evaluated} (e.g. 'slotformer diverged
      in update 117').
    seeds: every seed of the run (config.seeds), in order.

  Returns:
    'seeds', 'evaluated', 'excluded', 'std' (which deviation), the slot
    model's metrics and 'rollout' {method: {metric: `statistics` + the
    per-step mean 'per_step'}}, the shared 'protocol' and 'checkpoints',
    each seed's 'identity' and its 'files'.
  """
  evaluated = [seed for seed in seeds if seed in per_seed]
  summary: dict[str, Any] = {
      'seeds': list(seeds), 'evaluated': evaluated,
      'excluded': {str(seed): why for seed, why in excluded.items()},
      'std': STD}
  if not evaluated:
    return summary
  first = per_seed[evaluated[0]]
  name = first['slot_model']
  quality = {}
  for key, value in first[name].items():
    quality[key] = value if key in _COUNTS else statistics(
        {seed: per_seed[seed][name].get(key) for seed in evaluated})
  rollout = {}
  for method, per_metric in first['rollout'].items():
    rollout[method] = {}
    for metric in per_metric:
      entries = {seed: per_seed[seed]['rollout'][method][metric]
                 for seed in evaluated}
      rollout[method][metric] = dict(
          statistics({seed: entry['mean'] for seed, entry in entries.items()}),
          per_step=_per_step_mean([entry['per_step']
                                   for entry in entries.values()]))
  summary.update({
      'slot_model': name, name: quality, 'rollout': rollout,
      'protocol': first['protocol'], 'checkpoints': first['checkpoints'],
      'identity': {str(seed): per_seed[seed]['identity']
                   for seed in evaluated},
      'files': {str(seed): os.path.join(f'seed_{seed}', 'eval',
                                        'metrics.json')
                for seed in evaluated}})
  return summary


def write(directory: str, summary: dict[str, Any]) -> None:
  """`directory`/metrics.json (atomic: never a torn file)."""
  write_json_atomic(os.path.join(directory, 'metrics.json'), summary,
                    sort_keys=False)


def _cell(stats: dict[str, Any] | None, digits: int = 4) -> str:
  """'mean +- std' of `statistics`, '-' without a value."""
  if not stats or stats['mean'] is None:
    return '-'
  return f'{stats["mean"]:.{digits}f} +- {stats["std"]:.{digits}f}'


def format_table(summary: dict[str, Any], label: str) -> str:
  """The method x metric table of `summary`, each cell mean +- std over
  the seeds; `label` names the slot model ('SAVi')."""
  excluded = '; '.join(f'seed {seed}: {why}'
                       for seed, why in summary['excluded'].items())
  if not summary['evaluated']:
    return f'No seed evaluated ({excluded}).'
  rollout = summary['rollout']
  names = rollout_metrics.ordered(n for m in rollout.values() for n in m)
  protocol = summary['protocol']
  lines = [f'Rollout of {protocol["rollout_steps"]} steps after '
           f'{protocol["burn_in"]} burn-in frames, {protocol["num_videos"]} '
           f'{protocol["split"]} videos (mean over steps), mean +- std over '
           f'seeds {summary["evaluated"]}:']
  header = f'{"method":<22}' + ''.join(f'{n:>20}' for n in names)
  lines += [header, '-' * len(header)]
  for method, per_metric in rollout.items():
    lines.append(f'{method:<22}' + ''.join(
        f'{_cell(per_metric.get(name)):>20}' for name in names))
  quality = summary[summary['slot_model']]
  parts = [f'{title} {_cell(quality.get(key), digits)}'
           for key, title, digits in (
               ('fg_ari', 'FG-ARI', 4), ('fg_miou_per_frame',
                                         'FG-mIoU per frame', 4),
               ('ari', 'ARI', 4), ('psnr', 'PSNR (dB)', 2))
           if quality.get(key) and quality[key]['mean'] is not None]
  if parts:
    lines.append(f'{label} on the whole videos: ' + ', '.join(parts))
  if excluded:
    lines.append(f'Not in the means: {excluded}')
  return '\n'.join(lines)
