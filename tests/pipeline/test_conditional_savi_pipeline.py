"""Conditional SAVi through the pipeline (tiny embedded data, 4 fake
devices): trained on the clips' first-frame boxes, extracted from each
video's first-frame boxes, evaluated with SAVi's first-frame-skipping
FG-ARI."""

import json
import os

import jax
import numpy as np
import pytest

from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from pipeline_helpers import slots_of
from slotformer_jax.run import Run
from slotformer_jax.datasets import get_video_source
from slotformer_jax.errors import ConfigError
from slotformer_jax.runtime import sharding
from slotformer_jax.workdir import identity as identity_lib

# 35 s: -m slow. The default suite checks conditional SAVi's modules
# (modules/test_conditional_savi.py) and the pipeline with plain SAVi.
pytestmark = pytest.mark.slow


@pytest.fixture(scope='module')
def trained(tmp_path_factory):
  root = tmp_path_factory.mktemp('conditional')
  config = micro_config('savi', root / 'data')
  config.savi.initial_slots = 'boxes'
  config.evaluation.skip_first_frame = True
  config.slot_lstm.train = False
  config.logging.tensorboard = False
  workdir = str(root / 'run')
  mesh = sharding.make_mesh()
  results = run_stages(config, workdir, mesh,
                       ['train_savi', 'extract_slots', 'train_slotformer',
                        'evaluate'])
  return config, workdir, mesh, results


def test_metrics_name_the_convention(trained):
  config, workdir, _, results = trained
  metrics = json.load(open(os.path.join(workdir, 'eval', 'metrics.json')))
  assert metrics['protocol']['skip_first_frame'] is True
  assert np.isfinite(metrics['savi']['fg_ari'])
  assert results['evaluate']['protocol']['skip_first_frame'] is True
  identity = identity_lib.read_identity(os.path.join(workdir, 'savi'))
  assert identity['fields']['savi']['initial_slots'] == 'boxes'


def test_extraction_conditions_on_each_videos_first_boxes(trained):
  """The extracted slots are SAVi encoding each video from its own
  first-frame boxes; permuting those boxes permutes the first frame's slots
  (slot 1 + i follows box i)."""
  config, workdir, mesh, _ = trained
  run = Run.create(config, workdir, mesh)
  slot_model, params = run.slot_model, run.stage1.params
  source = get_video_source(config.data, 'test')
  extracted = slots_of(config, workdir, 'test', ())
  video = source[1]
  chunk = config.extraction.chunk_length
  frames = video['video'][None, :chunk]
  boxes = video['boxes'][None, 0]
  rng = jax.random.key(0)
  slots, _ = slot_model.encode(params, frames, rng, {'boxes': boxes})
  np.testing.assert_allclose(extracted[1]['slots'][:chunk], slots[0],
                             atol=1e-4)
  rows = boxes.shape[1]
  permutation = np.roll(np.arange(rows), 1)
  permuted, _ = slot_model.encode(params, frames, rng,
                                  {'boxes': boxes[:, permutation]})
  np.testing.assert_allclose(
      permuted[0, 0], slots[0, 0][np.concatenate([[0], 1 + permutation])],
      atol=1e-4)


def test_too_few_slots_for_the_boxes_is_one_error_line(trained, tmp_path):
  config, _, mesh, _ = trained
  config = config.copy_and_resolve_references()
  config.savi.num_slots = 2
  with pytest.raises(ConfigError, match=r'savi.num_slots >= \d+'):
    run_stages(config, str(tmp_path / 'run'), mesh, ['train_savi'])
