r"""The markdown table of `benchmarks/tpu_compile.py`'s JSON rows.

  python benchmarks/tpu_compile_table.py rows_a.json rows_b.json ... \
      [--json=merged.json] [--seeds]

Rows are keyed by (topology, config, step, dtype, seeds, host_chips); a
later file's row replaces an earlier one's, except that a row without a largest-batch search
keeps the search of the row it replaces when both compiled the same program
(same FLOPs and HBM). Rows are sorted by config, step, slice and dtype.
`--seeds`: the table of the several-seed rows (`tpu_compile.py --seeds`),
each beside the one-seed row of the same step (from any of the files).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

sys.path.insert(0, os.path.join(os.path.dirname(__file__), '..'))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from tpu_chips import CHIPS  # noqa: E402  (the spec-sheet peaks)

from slotformer_jax import files  # noqa: E402

GiB = 2**30
CONFIG_ORDER = ('obj3d', 'clevrer', 'clevrer_vqa', 'phyre', 'phyre:planning',
                'physion', 'physion_contact')
STEP_ORDER = ('savi', 'dvae', 'steve', 'slotformer', 'eval_rollout', 'aloe',
              'readout')
TOPOLOGY_ORDER = ('v5e:2x4', 'v4:2x2x1', 'v5e:16x16')
SEARCH_FIELDS = ('largest_per_chip', 'smallest_not_fitting', 'tried',
                 'search_compiles')


def _key(row: dict[str, Any]) -> tuple:
  return (row['topology'], row['config'], row['step'], row['dtype'],
          row.get('seeds', 1), row.get('host_chips'))


def _rank(order: tuple[str, ...], value: str) -> tuple[int, str]:
  return (order.index(value) if value in order else len(order), value)


def merge(paths: list[str]) -> list[dict[str, Any]]:
  rows: dict[tuple, dict[str, Any]] = {}
  for path in paths:
    for row in files.read_json(path):
      old = rows.get(_key(row))
      if (old is not None and 'largest_per_chip' in old
          and 'largest_per_chip' not in row
          and old.get('flops') == row.get('flops')
          and old.get('hbm_bytes') == row.get('hbm_bytes')):
        row = dict(row, **{f: old[f] for f in SEARCH_FIELDS if f in old})
      rows[_key(row)] = row
  return sorted(rows.values(), key=lambda r: (
      _rank(CONFIG_ORDER, r['config']), _rank(STEP_ORDER, r['step']),
      _rank(TOPOLOGY_ORDER, r['topology']), r['dtype'], r.get('seeds', 1),
      r.get('host_chips') or 0))


def _largest(row: dict[str, Any]) -> str:
  if 'largest_per_chip' not in row:
    return 'not searched'
  above = row.get('smallest_not_fitting')
  return (f"{row['largest_per_chip']} (not {above})" if above is not None
          else f">= {row['largest_per_chip']} (search stopped)")


def table(rows: list[dict[str, Any]]) -> str:
  lines = ['| config | step | slice (chips) | dtype | batch (/chip) | fits '
           '| HBM GiB / chip | largest batch / chip (first that does not '
           'fit) | GFLOP / chip | GB / chip | floor ms | bound by | '
           'compile s |', '|' + '---|' * 13]
  for r in rows:
    head = (f"| {r['config']} | {r['step']} | {r['topology']} "
            f"({r['chips']}) | {r['dtype']} |")
    if r.get('status') != 'compiled':
      lines.append(f"{head} {r.get('batch', '')} | {r.get('status')}: "
                   f"{r.get('why', '')} |" + ' |' * 8)
      continue
    per_chip = r['batch'] // r['chips']
    star = ' *' if 'note' in r and 'does not split' in r['note'] else ''
    lines.append(
        f"{head} {r['batch']} ({per_chip}){star} | "
        f"{'yes' if r['fits'] else 'NO'} | "
        f"{r['hbm_bytes'] / GiB:.2f} of {r['chip_hbm'] / GiB:.0f} | "
        f"{_largest(r)} | {r['flops'] / 1e9:.1f} | "
        f"{r['bytes_accessed'] / 1e9:.2f} | {r['floor_seconds'] * 1e3:.2f} | "
        f"{_bound_by(r)} | "
        f"{r['compile_seconds']:.0f} |")
  return '\n'.join(lines)


def seeds_table(rows: list[dict[str, Any]]) -> str:
  """The K-seed rows (merged, sorted), each step's after its one-seed row:
  HBM per chip, the floor and the floor per seed, with the ratios of K
  seeds to one seed."""
  one = {_key(r)[:4]: r for r in rows
         if r.get('seeds', 1) == 1 and r.get('status') == 'compiled'}
  lines = ['| config | step | slice | dtype | seeds (mesh) | batch | fits | '
           'HBM GiB / chip (x one seed) | floor ms (x one seed) | '
           'floor ms / seed | bound by | compile s |', '|' + '---|' * 12]
  shown = set()
  for r in rows:
    if r.get('seeds', 1) == 1:
      continue
    head = (f"| {r['config']} | {r['step']} | {r['topology']} | "
            f"{r['dtype']} |")
    base = one.get(_key(r)[:4])
    if base is not None and _key(base) not in shown:
      shown.add(_key(base))
      lines.append(
          f"{head} 1 | {base['batch']} | {'yes' if base['fits'] else 'NO'} "
          f"| {base['hbm_bytes'] / GiB:.2f} | "
          f"{base['floor_seconds'] * 1e3:.2f} | "
          f"{base['floor_seconds'] * 1e3:.2f} | {_bound_by(base)} | "
          f"{base['compile_seconds']:.0f} |")
    if r.get('status') != 'compiled':
      lines.append(f"{head} {r['seeds']} | {r.get('batch', '')} | "
                   f"{r.get('status')}: {r.get('why', '')} |" + ' |' * 5)
      continue
    mesh = ' x '.join(f"{r['mesh'][axis]} {axis}" for axis in ('seed', 'data')
                      if axis in r['mesh'])
    hbm = f"{r['hbm_bytes'] / GiB:.2f}"
    floor = f"{r['floor_seconds'] * 1e3:.2f}"
    if base is not None:
      hbm += f" ({r['hbm_bytes'] / base['hbm_bytes']:.2f}x)"
      floor += f" ({r['floor_seconds'] / base['floor_seconds']:.2f}x)"
    if r.get('host_chips'):
      mesh += f", {r['host_chips']} chips / host"
    lines.append(
        f"{head} {r['seeds']} ({mesh}) | {r['batch']} | "
        f"{'yes' if r['fits'] else 'NO'} | {hbm} | {floor} | "
        f"{r['floor_per_seed_seconds'] * 1e3:.2f} | {_bound_by(r)} | "
        f"{r['compile_seconds']:.0f} |")
  return '\n'.join(lines)


def _bound_by(row: dict[str, Any]) -> str:
  """Which roofline term sets the floor, and by how much it exceeds the
  other (with tpu_chips.py's spec-sheet peaks)."""
  chip = CHIPS[row['device_kind']]
  t_flops = row['flops'] / chip['peak_flops']
  t_bytes = row['bytes_accessed'] / chip['hbm_bandwidth']
  if t_bytes >= t_flops:
    return f'bytes {t_bytes / max(t_flops, 1e-12):.1f}x'
  return f'FLOPs {t_flops / max(t_bytes, 1e-12):.1f}x'


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('inputs', nargs='+')
  parser.add_argument('--json', default='')
  parser.add_argument('--seeds', action='store_true',
                      help='the several-seed rows beside one-seed ones')
  args = parser.parse_args(argv)
  rows = merge(args.inputs)
  if args.json:
    files.write_json_atomic(args.json, rows)
  print(seeds_table(rows) if args.seeds else table(rows))
  return 0


if __name__ == '__main__':
  sys.exit(main())
