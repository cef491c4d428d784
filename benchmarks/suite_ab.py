r"""Is the default test suite slower with one value of an environment variable
than with another? Runs the suite chunk by chunk, each chunk under both
values back to back, and compares the pairs.

  python benchmarks/suite_ab.py --out=/tmp/suite_ab.tsv \
      [--env=SLOTFORMER_MALLOC_TUNING] [--a=0] [--b=no-arena-limit] [--rounds=4]

Whole-suite runs one after the other cannot answer it on a shared or
throttled machine: the same setting's suite varied by 1-2 minutes in an
hour on the 2-core box, more than the 1-3 % in question. Here the drift
cancels: every chunk (a test folder, large folders split into groups of at
most `--files_per_chunk` files) runs under A and under B within a few
minutes, the order alternating chunk by chunk and mirrored in the next
round. `--b=unset` removes the variable (the tests' own default then
applies).

Writes one TSV row per run (wall / user / system seconds and minor faults
of the pytest process and its children, from `os.wait4`; pytest's last
line) and prints, per round, the sums; per chunk, the sums over rounds;
and for the whole suite the mean B - A difference with its standard error
(each chunk's spread of paired differences over the rounds). What was
measured: docs/performance.md, "Host memory churn".
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import time

_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _split(files: list[str], files_per_chunk: int) -> list[list[str]]:
  parts = math.ceil(len(files) / files_per_chunk)
  size = math.ceil(len(files) / parts) if parts else 1
  return [files[i:i + size] for i in range(0, len(files), size)]


def default_chunks(tests_dir: str, files_per_chunk: int) -> list[list[str]]:
  """The top-level test files, then each folder's; large groups split."""
  def test_files(path):
    return sorted(os.path.join(path, f) for f in os.listdir(path)
                  if f.startswith('test_') and f.endswith('.py'))
  chunks = _split(test_files(tests_dir), files_per_chunk)
  for folder in sorted(os.listdir(tests_dir)):
    path = os.path.join(tests_dir, folder)
    if os.path.isdir(path):
      chunks.extend(_split(test_files(path), files_per_chunk))
  return chunks


def run_chunk(paths: list[str], env_name: str, value: str) -> dict:
  env = dict(os.environ)
  if value == 'unset':
    env.pop(env_name, None)
  else:
    env[env_name] = value
  start = time.perf_counter()
  proc = subprocess.Popen(
      [sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', *paths],
      cwd=_REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
      text=True)
  output = proc.stdout.read()
  _, status, usage = os.wait4(proc.pid, 0)
  wall = time.perf_counter() - start
  lines = [line for line in output.splitlines() if line.strip()]
  return {'wall': wall, 'user': usage.ru_utime, 'system': usage.ru_stime,
          'faults': usage.ru_minflt, 'rc': os.waitstatus_to_exitcode(status),
          'summary': lines[-1] if lines else ''}


def summarise(rows: list[dict], a: str, b: str) -> str:
  out = []
  for rnd in sorted({r['round'] for r in rows}):
    sums = {v: sum(r['wall'] for r in rows if r['round'] == rnd
                   and r['value'] == v) for v in (a, b)}
    out.append(f'round {rnd}: {a} {sums[a]:.1f} s, {b} {sums[b]:.1f} s')
  total_diff, variance, base = 0.0, 0.0, 0.0
  for chunk in sorted({r['chunk'] for r in rows}):
    pairs = {}
    for r in rows:
      if r['chunk'] == chunk:
        pairs.setdefault(r['round'], {})[r['value']] = r['wall']
    pairs = [p for p in pairs.values() if a in p and b in p]
    if not pairs:
      continue
    diffs = [p[b] - p[a] for p in pairs]
    base += statistics.mean(p[a] for p in pairs)
    total_diff += statistics.mean(diffs)
    if len(diffs) > 1:
      variance += statistics.variance(diffs) / len(diffs)
    out.append(f'chunk {chunk}: {a} {sum(p[a] for p in pairs):.1f} s, '
               f'{b} {sum(p[b] for p in pairs):.1f} s over {len(pairs)} rounds')
  if base:
    se = math.sqrt(variance)
    out.append(f'suite: {a} {base:.1f} s; {b} - {a} = {total_diff:+.1f} s '
               f'({100 * total_diff / base:+.2f} %), standard error '
               f'{100 * se / base:.2f} %')
  return '\n'.join(out)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--out', required=True, help='TSV file to write')
  parser.add_argument('--env', default='SLOTFORMER_MALLOC_TUNING')
  parser.add_argument('--a', default='0')
  parser.add_argument('--b', default='no-arena-limit')
  parser.add_argument('--rounds', type=int, default=4)
  parser.add_argument('--files_per_chunk', type=int, default=7)
  parser.add_argument('--tests_dir', default=os.path.join(_REPO, 'tests'))
  args = parser.parse_args()
  chunks = default_chunks(os.path.abspath(args.tests_dir),
                          args.files_per_chunk)
  rows = []
  with open(args.out, 'w') as out:
    out.write('round\tchunk\tvalue\tload\twall_s\tuser_s\tsystem_s\tfaults'
              '\trc\tsummary\n')
    for rnd in range(1, args.rounds + 1):
      for i, paths in enumerate(chunks):
        order = (args.a, args.b) if (i + rnd) % 2 else (args.b, args.a)
        for value in order:
          load = os.getloadavg()[0]
          result = run_chunk(paths, args.env, value)
          rows.append(dict(result, round=rnd, chunk=i, value=value))
          out.write(f"{rnd}\t{i}\t{value}\t{load:.2f}\t{result['wall']:.2f}\t"
                    f"{result['user']:.2f}\t{result['system']:.2f}\t"
                    f"{result['faults']}\t{result['rc']}\t"
                    f"{result['summary']}\n")
          out.flush()
          print(f'round {rnd} chunk {i} {args.env}={value}: '
                f"{result['wall']:.1f} s, {result['summary']}", flush=True)
  print(summarise(rows, args.a, args.b))


if __name__ == '__main__':
  main()
