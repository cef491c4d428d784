"""Every reader of files from elsewhere, on seeded structure-aware mutations
of a valid input (tests/reader_fuzz.py; the .pth reader has its own:
tests/official/test_pth_reader_hostile.py): each case must be read into a
well-formed result, or refused with the one-line error its command prints,
holding no raw control character; within 5 s, writing nothing. One child
process per reader, so a crash or a hang fails the test, not pytest.

    python -m pytest -q tests/reliability/test_reader_fuzz.py          # a few s each
    python -m pytest -q -m slow tests/reliability/test_reader_fuzz.py  # 3 x 2,000 each
"""

import collections
import json
import os
import subprocess
import sys

import pytest

TESTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROOT = os.path.dirname(TESTS)

# Cases per reader in the default suite (about 2 s of fuzzing each on the
# 2-core machine, besides the child's imports).
CASES = {'movi_metadata': 150, 'movi_records': 150, 'questions': 300,
         'vocabulary': 300, 'phyre': 150, 'physion_lists': 300,
         'metrics': 300, 'digests': 300}
SECONDS_PER_CASE = 5


def fuzz(reader, seed, cases, folder):
  """The verdicts of `cases` mutations, read in one child process."""
  env = {**os.environ, 'PYTHONPATH': os.pathsep.join(
      [ROOT, os.environ.get('PYTHONPATH', '')]).rstrip(os.pathsep),
         'JAX_PLATFORMS': 'cpu'}
  done = subprocess.run(
      [sys.executable, os.path.join(TESTS, 'reader_fuzz.py'), reader,
       str(seed), str(cases), str(folder), str(SECONDS_PER_CASE)],
      capture_output=True, text=True, env=env, check=False,
      timeout=120 + cases * SECONDS_PER_CASE)
  verdicts = [json.loads(line) for line in done.stdout.splitlines()]
  assert done.returncode == 0 and len(verdicts) == cases, (
      f'the fuzz process died with status {done.returncode} after '
      f'{len(verdicts)} cases (the next: case {len(verdicts)}): '
      f'{done.stderr[-3000:]}')
  return verdicts


def check(verdicts):
  problems = [v for v in verdicts if 'problem' in v]
  assert not problems, problems[:3]
  outcomes = collections.Counter(v['outcome'] for v in verdicts)
  # Not vacuous: some cases read, some refused, many kinds of mutation.
  assert outcomes['read'] and outcomes['refused'], outcomes
  kinds = {v['what'].split(': ')[-1].split()[0] for v in verdicts}
  assert len(kinds) >= 8, kinds
  return outcomes


@pytest.mark.parametrize('reader', sorted(CASES))
def test_fuzzed_inputs_are_read_or_refused_in_one_line(reader, tmp_path):
  verdicts = fuzz(reader, 0, CASES[reader], tmp_path)
  outcomes = check(verdicts)
  slowest = max(v['seconds'] for v in verdicts)
  print(f'{reader}: {dict(outcomes)}, slowest case {slowest:.3f} s')


@pytest.mark.slow
@pytest.mark.parametrize('seed', [1, 2, 3])
@pytest.mark.parametrize('reader', sorted(CASES))
def test_longer_fuzz(reader, seed, tmp_path):
  check(fuzz(reader, seed, 2000, tmp_path))
