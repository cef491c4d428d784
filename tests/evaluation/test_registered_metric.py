"""A rollout metric from this one file, without editing the package.

`pixel_l1` is the mean absolute error of the decoded frames (lower is
better, needs frames). Registered below with its label, it is a value
`evaluation.metrics` takes, and `evaluate` scores every method with it:
metrics.json, per_step.csv and the table; the seeds' summary and its table,
render/per_step.png and the explorer's curves (the run's and each video's)
show it under its label.
"""

from __future__ import annotations

import csv
import json
import pathlib
import re

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline_helpers import check
from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from slotformer_jax import stages
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import rollout_metrics
from slotformer_jax.evaluation import seeds as seeds_lib
from slotformer_jax.evaluation import visualize

NAME = 'pixel_l1'
LABEL = 'L1 (pixels)'


@rollout_metrics.register_metric(NAME, LABEL, higher_is_better=False,
                                 needs=rollout_metrics.FRAMES)
def pixel_l1(step: rollout_metrics.Step):
  error = jnp.mean(jnp.abs(step.decoded.recon - step.frames), axis=(-3, -2, -1))
  return error, jnp.ones(error.shape, bool)


def test_the_package_does_not_know_it():
  package = pathlib.Path(stages.__file__).parent.parent
  for path in package.rglob('*.py'):
    text = path.read_text()
    assert NAME not in text and LABEL not in text, path
  metric = rollout_metrics.get(NAME)
  assert (metric.label, metric.higher_is_better, metric.needs) == (
      LABEL, False, rollout_metrics.FRAMES)


def test_it_is_a_value_of_evaluation_metrics(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  config.evaluation.metrics = ('psnr', NAME)
  check(config, ['evaluate'])
  config.evaluation.metrics = ('psnr', 'pixel_l2')
  with pytest.raises(UserError, match='pixel_l2'):
    check(config, ['evaluate'])


def test_the_seeds_summary_reads_it():
  def one_seed(value):
    return {'slot_model': 'savi', 'savi': {},
            'rollout': {'slotformer': {NAME: {'mean': value,
                                              'per_step': [value]}}},
            'protocol': {'rollout_steps': 1, 'burn_in': 2, 'num_videos': 4,
                         'split': 'test'},
            'checkpoints': {}, 'identity': {}}
  summary = seeds_lib.summarise({0: one_seed(0.1), 1: one_seed(0.3)}, {},
                                (0, 1))
  stats = summary['rollout']['slotformer'][NAME]
  assert stats['mean'] == pytest.approx(0.2) and stats['num_seeds'] == 2
  assert NAME in seeds_lib.format_table(summary, 'SAVi')


def test_evaluate_scores_it_and_every_page_shows_it(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  config.slot_lstm.train = False
  config.evaluation.metrics = ('psnr', NAME, 'fg_ari')
  workdir = tmp_path / 'run'
  results = run_stages(config, workdir, Mesh(np.asarray(jax.devices()[:1]),
                                             ('data',)),
                       ['train_savi', 'extract_slots', 'train_slotformer',
                        'evaluate', 'explore'])
  rollout = results['evaluate']['rollout']
  for method in ('slotformer', 'copy_last'):
    assert set(rollout[method]) == {'psnr', NAME, 'fg_ari'}
    values = rollout[method][NAME]['per_step']
    assert all(0 <= v <= 1 for v in values)
  with open(workdir / 'eval' / 'per_step.csv', newline='') as f:
    rows = [row for row in csv.DictReader(f) if row['metric'] == NAME]
  assert {row['method'] for row in rows} == set(rollout)  # every method
  assert len(rows) == len(rollout) * config.evaluation.rollout_steps
  header = evaluate.format_table(results['evaluate'], 'SAVi').splitlines()[1]
  assert header.split() == ['method', 'psnr', 'fg_ari', NAME]  # as registered
  figure = visualize.write_per_step_figure(
      str(workdir / 'eval' / 'metrics.json'), str(tmp_path / 'render'),
      {'slotformer': 'SlotFormer'}, 'savi_reconstruction')
  assert figure is not None and pathlib.Path(figure).stat().st_size > 0
  page = (workdir / 'explore' / 'index.html').read_text()
  data = json.loads(re.search(
      r'<script[^>]*id="explorer-data"[^>]*>(.*?)</script>', page,
      re.S).group(1))
  assert data['metric_labels'][NAME] == LABEL
  assert NAME in data['run_curves']
  # Each video's curve is the registered function too: over the same test
  # videos, their mean is the evaluation's per-step value.
  per_video = [video['curves'][NAME]['copy-last'] for video in data['videos']]
  assert len(per_video) == 4
  np.testing.assert_allclose(np.mean(per_video, axis=0),
                             rollout['copy_last'][NAME]['per_step'],
                             atol=6e-5)  # the page keeps 4 decimals
