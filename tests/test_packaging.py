"""Installable like a library: the shipped configs by name from any folder,
no import-time banner, the license and the GPU extras declared."""

import configparser
import os
import pathlib
import subprocess
import sys

from slotformer_jax.config import checks

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_a_shipped_config_is_found_by_name_from_any_folder(
    tmp_path, monkeypatch):
  # What `pip install .` makes of configs/ (setup.py): a package of them.
  package = tmp_path / 'site' / 'shipped_for_test'
  package.mkdir(parents=True)
  (package / 'mine.py').write_text('def get_config(v=""):\n  return 1\n')
  monkeypatch.syspath_prepend(str(tmp_path / 'site'))
  monkeypatch.setattr(checks, 'SHIPPED_CONFIGS', 'shipped_for_test')
  elsewhere = tmp_path / 'elsewhere'
  elsewhere.mkdir()
  monkeypatch.chdir(elsewhere)
  assert checks.shipped_config('configs/mine.py:tiny') == (
      f'{package / "mine.py"}:tiny')
  # A file that is there wins; other names and folders are left alone.
  (elsewhere / 'configs').mkdir()
  (elsewhere / 'configs' / 'mine.py').write_text('')
  assert checks.shipped_config('configs/mine.py') == 'configs/mine.py'
  assert checks.shipped_config('configs/absent.py') == 'configs/absent.py'
  assert checks.shipped_config('other/mine.py') == 'other/mine.py'


def test_setup_ships_the_configs_the_license_and_the_gpu_extras():
  setup = (ROOT / 'setup.py').read_text()
  assert "'slotformer_jax.configs': 'configs'" in setup
  config = configparser.ConfigParser()
  config.read(ROOT / 'setup.cfg')
  extras = config['options.extras_require']
  assert 'jax[cuda12]' in extras['cuda12'] and 'jax[cuda13]' in extras[
      'cuda13']
  assert config['metadata']['license_files'] == 'LICENSE'
  assert 'Apache License' in (ROOT / 'LICENSE').read_text()[:200]


def test_importing_the_datasets_prints_nothing(tmp_path):
  env = dict(os.environ, PYTHONPATH=str(ROOT))
  result = subprocess.run(
      [sys.executable, '-c', 'import slotformer_jax.datasets'], cwd=tmp_path,
      env=env, capture_output=True, text=True, timeout=120)
  assert result.returncode == 0, result.stderr
  assert result.stdout == '' and result.stderr == '', result.stderr
