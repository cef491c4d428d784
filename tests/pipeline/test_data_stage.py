"""The data stage: reading never writes, the stage makes the data, every
--mode runs it first."""

from __future__ import annotations

import os

import pytest

from pipeline_helpers import load_config
from pipeline_helpers import micro_config
from pipeline_helpers import prepare_data
from slotformer_jax import datasets
from slotformer_jax import stages
from slotformer_jax.data import vqa_questions
from slotformer_jax.data.sources import resolve_data_dir
from slotformer_jax.datasets import synthetic_phyre as phyre_like_data
from slotformer_jax.errors import MissingInputError
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.stages import data as data_stage

CONFIGS = ('synthetic:tiny', 'synthetic:steve_tiny', 'synthetic_contact:tiny',
           'synthetic_phyre:tiny', 'synthetic_vqa:tiny', 'clevrer_vqa:',
           'physion_contact:', 'phyre:', 'movi:')


def _snapshot(directory):
  """{relative path: (size, mtime_ns)} of every file below `directory`."""
  out = {}
  for root, _, names in os.walk(directory):
    for name in names:
      stat = os.stat(os.path.join(root, name))
      out[os.path.relpath(os.path.join(root, name), directory)] = (
          stat.st_size, stat.st_mtime_ns)
  return out


@pytest.mark.parametrize('spec', CONFIGS)
def test_every_mode_runs_the_data_stage_first(spec):
  run = Run.create(load_config(*spec.split(':')), '/nonexistent/run',
                   sharding.make_mesh())
  assert list(stages.DATA) == ['prepare_data']
  assert next(iter(stages.stage_table(run))) == 'prepare_data'
  for mode in ('all', *stages.stage_table(run)):
    selected = stages.selected_stages(run, mode)
    assert selected[0] == 'prepare_data', mode
    assert selected.count('prepare_data') == 1
    assert mode == 'all' or selected[-1] == mode


def test_the_splits_a_config_reads():
  reads = lambda spec: data_stage.splits_read(load_config(*spec.split(':')))
  assert reads('synthetic:tiny') == ('train', 'val', 'test')
  assert reads('synthetic_contact:tiny') == (
      'train', 'readout_train', 'readout_val', 'readout_test')
  assert reads('physion_contact:') == (
      'train', 'readout_train', 'readout_val', 'test')
  assert reads('synthetic_phyre:tiny') == ('train',)
  assert reads('phyre:') == ('train', 'val')
  assert reads('movi:') == ('train', 'val')
  assert reads('synthetic_vqa:tiny') == ('train', 'val', 'test')


@pytest.mark.parametrize('name', ['synthetic', 'synthetic_contact',
                                  'synthetic_phyre', 'synthetic_vqa'])
def test_opening_missing_embedded_data_names_the_stage_and_writes_nothing(
    tmp_path, name):
  """No generation on first use, no lock, no checksums: one line names the
  command that makes the data."""
  config = load_config(name, 'tiny')
  config.data.data_dir = str(tmp_path / 'data')
  (tmp_path / 'data').mkdir()
  readers = [lambda: datasets.get_video_source(config.data, 'train')]
  if name == 'synthetic_vqa':
    readers.append(lambda: vqa_questions.vocabulary(config))
  if name == 'synthetic_phyre':
    readers.append(lambda: phyre_like_data.load_task_labels(
        phyre_like_data.config_from_data_config(config.data),
        resolve_data_dir(config.data.data_dir)))
  for read in readers:
    with pytest.raises(MissingInputError,
                       match='--mode=prepare_data') as error:
      read()
    assert '\n' not in str(error.value)
  assert list((tmp_path / 'data').iterdir()) == []
  assert sorted(p.name for p in tmp_path.iterdir()) == ['data']


def test_the_data_stage_makes_the_data_once(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  prepare_data(config)
  made = _snapshot(tmp_path / 'data')
  assert any(name.endswith('checksums.json') for name in made)
  assert len(datasets.get_video_source(config.data, 'test')) == 4
  prepare_data(config)  # the data are there: a stat per file
  assert _snapshot(tmp_path / 'data') == made


def test_a_converted_dataset_that_is_not_there_is_left_to_its_reader(
    tmp_path):
  config = load_config('obj3d')
  config.data.data_dir = str(tmp_path / 'data')
  prepare_data(config)  # e.g. a run that reads only its extracted slots
  assert not (tmp_path / 'data').exists()
  with pytest.raises(MissingInputError,
                     match='slotformer_jax.data.prepare --dataset=obj3d'):
    datasets.get_video_source(config.data, 'train')
