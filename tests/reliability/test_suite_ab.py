"""benchmarks/suite_ab.py: its chunks and its arithmetic (no timings)."""

import importlib.util
import os

SCRIPT = os.path.join(os.path.dirname(__file__), '..', '..', 'benchmarks',
                      'suite_ab.py')


def _module():
  spec = importlib.util.spec_from_file_location('suite_ab', SCRIPT)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def test_every_test_file_is_in_exactly_one_chunk(tmp_path):
  files = ['test_top.py', 'a/test_1.py', 'a/test_2.py', 'a/test_3.py',
           'b/test_x.py', 'b/helpers.py', 'c/data.txt']
  for name in files:
    (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / name).write_text('')
  chunks = _module().default_chunks(str(tmp_path), files_per_chunk=2)
  assert all(chunks) and all(len(chunk) <= 2 for chunk in chunks)
  listed = sorted(os.path.relpath(p, tmp_path) for c in chunks for p in c)
  assert listed == sorted(f for f in files if '/test_' in f or
                          f.startswith('test_'))
  # a/ (3 files) splits into two chunks, each of one folder only.
  assert len(chunks) == 4
  assert all(len({os.path.dirname(p) for p in chunk}) == 1 for chunk in chunks)


def test_the_suite_difference_and_its_standard_error():
  rows = [dict(round=r, chunk=c, value=v, wall=w) for r, c, v, w in [
      (1, 0, 'A', 10.0), (1, 0, 'B', 11.0), (2, 0, 'A', 12.0),
      (2, 0, 'B', 12.0), (1, 1, 'A', 20.0), (1, 1, 'B', 19.0),
      (2, 1, 'A', 22.0), (2, 1, 'B', 23.0)]]
  text = _module().summarise(rows, 'A', 'B')
  # Chunk 0: differences 1, 0 (mean 0.5, variance 0.5); chunk 1: -1, 1
  # (mean 0, variance 2). Suite: +0.5 s on A's 11 + 21 = 32 s (+1.56 %),
  # standard error sqrt(0.5 / 2 + 2 / 2) = 1.118 s (3.49 %).
  assert 'round 1: A 30.0 s, B 30.0 s' in text
  assert 'suite: A 32.0 s; B - A = +0.5 s (+1.56 %)' in text
  assert 'standard error 3.49 %' in text
