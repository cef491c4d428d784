"""Files a team can read: every atomic write gets 0666 & ~umask, not 0600."""

import contextlib
import os
import stat

import pytest

from slotformer_jax import files
from slotformer_jax.workdir import lock as lock_lib
from slotformer_jax.runtime import xla_flags


@contextlib.contextmanager
def umask(value):
  old = os.umask(value)
  try:
    yield
  finally:
    os.umask(old)


def mode(path):
  return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize('mask, expected', [(0o022, 0o644), (0o002, 0o664),
                                            (0o077, 0o600)])
def test_atomic_writes_follow_the_umask(tmp_path, mask, expected):
  with umask(mask):
    files.write_json_atomic(tmp_path / 'run' / 'config.json', {'a': 1})
    files.write_atomic(tmp_path / 'run' / 'wall_times.json', b'{}\n')
    files.append_line_atomic(tmp_path / 'run' / 'log.jsonl', '{"step": 1}')
    files.append_line_atomic(tmp_path / 'run' / 'log.jsonl', '{"step": 2}')
    with files.atomic_text(tmp_path / 'run' / 'per_step.csv') as f:
      f.write('step,psnr\n')
  for name in ('config.json', 'wall_times.json', 'log.jsonl', 'per_step.csv'):
    assert mode(tmp_path / 'run' / name) == expected, name
  # The folder files.py made: as os.makedirs makes it.
  assert mode(tmp_path / 'run') == 0o777 & ~mask
  # Still atomic: no temporary file is left behind, the content is whole.
  assert sorted(os.listdir(tmp_path / 'run')) == [
      'config.json', 'log.jsonl', 'per_step.csv', 'wall_times.json']
  assert (tmp_path / 'run' / 'log.jsonl').read_text() == (
      '{"step": 1}\n{"step": 2}\n')


def test_a_failed_write_leaves_no_temporary_file(tmp_path, monkeypatch):
  def fail(*args):
    raise OSError('disk full')
  monkeypatch.setattr(os, 'replace', fail)
  with pytest.raises(OSError, match='disk full'):
    files.write_atomic(tmp_path / 'a.json', b'{}')
  assert os.listdir(tmp_path) == []


def test_temporary_names_do_not_collide(tmp_path, monkeypatch):
  # An existing file with the drawn name is skipped, never overwritten.
  names = iter(['aaaaaaaaaaaa', 'aaaaaaaaaaaa', 'bbbbbbbbbbbb'])
  monkeypatch.setattr(files.secrets, 'token_hex', lambda n: next(names))
  fd, first = files._create_temporary(str(tmp_path), '.x.tmp.')
  os.close(fd)
  fd, second = files._create_temporary(str(tmp_path), '.x.tmp.')
  os.close(fd)
  assert first != second and os.path.basename(second).endswith('bbbbbbbbbbbb')


def test_lock_and_probe_cache_follow_the_umask(tmp_path):
  with umask(0o002):
    held = lock_lib.FileLock(str(tmp_path / 'run' / 'lock'), what='the run')
    held.acquire()
    try:
      assert mode(tmp_path / 'run' / 'lock') == 0o664
    finally:
      held.release()
    xla_flags._write_cache(tmp_path / 'cache' / 'xla_flag_probes.json',
                           {'--flag': True})
  assert mode(tmp_path / 'cache' / 'xla_flag_probes.json') == 0o664
  assert xla_flags._read_cache(
      tmp_path / 'cache' / 'xla_flag_probes.json') == {'--flag': True}
