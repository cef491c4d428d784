"""TensorBoard summaries: a tiny run's event files, read by TensorBoard's own
reader (tensorboard's EventAccumulator; without the tensorboard package,
tensorboardX's Event protobuf over the TFRecord framing), have the expected
tags; `logging.tensorboard = False` writes none."""

import glob
import io
import os

import numpy as np
from PIL import Image
import pytest

from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from pipeline_helpers import accept
from slotformer_jax.runtime import sharding
from slotformer_jax import frames as frames_lib

SCALARS = ('train/loss', 'train/recon_loss', 'train/grad_norm',
           'train/param_norm', 'train/learning_rate',
           'train/steps_per_second', 'train/seconds_per_step')


def _read(directory):
  """({scalar tag: [(step, value)]}, {image tag: [(step, uint8 HWC)]})."""
  files = glob.glob(os.path.join(directory, 'events.out.tfevents.*'))
  assert files, f'no event file in {directory}'
  try:
    from tensorboard.backend.event_processing import event_accumulator
  except ImportError:
    event_accumulator = None
  scalars, images = {}, {}
  if event_accumulator is not None:
    accumulator = event_accumulator.EventAccumulator(
        directory, size_guidance={'scalars': 0, 'images': 0})
    accumulator.Reload()
    for tag in accumulator.Tags()['scalars']:
      scalars[tag] = [(e.step, e.value) for e in accumulator.Scalars(tag)]
    for tag in accumulator.Tags()['images']:
      images[tag] = [(e.step, np.asarray(Image.open(io.BytesIO(
          e.encoded_image_string)))) for e in accumulator.Images(tag)]
    return scalars, images
  from tensorboardX.proto import event_pb2
  from slotformer_jax.data import tfrecord
  for path in files:
    for record in tfrecord.iter_records(path):
      event = event_pb2.Event.FromString(bytes(record))
      for value in event.summary.value:
        if value.HasField('image'):
          images.setdefault(value.tag, []).append((event.step, np.asarray(
              Image.open(io.BytesIO(value.image.encoded_image_string)))))
        else:
          scalars.setdefault(value.tag, []).append(
              (event.step, value.simple_value))
  return scalars, images


@pytest.fixture(scope='module')
def tiny_run(tmp_path_factory):
  root = tmp_path_factory.mktemp('tensorboard')
  config = micro_config('savi', root / 'data')
  config.logging.image_every = 2
  workdir = str(root / 'run')
  run_stages(config, workdir, sharding.make_mesh(),
             ['train_savi', 'extract_slots', 'train_slotformer'])
  return config, workdir


def test_savi_stage_writes_scalars_and_labelled_images(tiny_run):
  config, workdir = tiny_run
  scalars, images = _read(os.path.join(workdir, 'savi', 'tensorboard'))
  assert set(SCALARS) <= set(scalars)
  steps = [step for step, _ in scalars['train/loss']]
  assert steps == [2, 4]  # log_every = 2, num_train_steps = 4
  # The same numbers as the JSONL log.
  lines = open(os.path.join(workdir, 'savi', 'train_log.jsonl')).readlines()
  import json
  logged = [json.loads(line) for line in lines]
  np.testing.assert_allclose([v for _, v in scalars['train/loss']],
                             [line['loss'] for line in logged], rtol=1e-6)
  assert [s for s, _ in images['images/reconstruction']] == [2, 4]
  picture = images['images/reconstruction'][0][1]
  # Three labelled rows (input, reconstruction, masks) of clip_length frames
  # at scale 2 after the label column.
  height, width = config.data.resolution
  assert picture.shape[0] == 3 * 2 * height
  assert picture.shape[1] == (frames_lib.GRID_LABEL_WIDTH
                              + config.savi.clip_length * 2 * width)
  # The label column has text drawn in it (not blank).
  assert (picture[:, :frames_lib.GRID_LABEL_WIDTH] < 128).any()


def test_dynamics_stage_writes_a_rollout_strip(tiny_run):
  config, workdir = tiny_run
  scalars, images = _read(os.path.join(workdir, 'slotformer', 'tensorboard'))
  assert {'train/loss', 'train/slot_loss', 'train/image_loss',
          'train/learning_rate'} <= set(scalars)
  strip = images['images/rollout'][-1][1]
  frames = config.slotformer.burn_in + config.slotformer.rollout
  height, width = config.data.resolution
  # Rows: real frames, extracted slots decoded, burn-in + rollout decoded.
  assert strip.shape[0] == 3 * 2 * height
  assert strip.shape[1] == frames_lib.GRID_LABEL_WIDTH + frames * 2 * width


def test_off_by_config_writes_no_event_file(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  config.logging.tensorboard = False
  config.savi.num_train_steps = 2
  workdir = str(tmp_path / 'run')
  run_stages(config, workdir, sharding.make_mesh(), ['train_savi'])
  assert os.path.exists(os.path.join(workdir, 'savi', 'train_log.jsonl'))
  assert not os.path.exists(os.path.join(workdir, 'savi', 'tensorboard'))
  assert not glob.glob(os.path.join(workdir, '**', 'events.out.tfevents.*'),
                       recursive=True)


def test_labelled_grid_rows():
  rows = {'a': np.zeros((3, 4, 5, 3), np.uint8),
          'b': np.full((3, 4, 5, 3), 255, np.uint8)}
  grid = frames_lib.labelled_grid(rows, scale=1)
  assert grid.shape == (8, frames_lib.GRID_LABEL_WIDTH + 15, 3)
  np.testing.assert_array_equal(grid[:4, frames_lib.GRID_LABEL_WIDTH:], 0)
  np.testing.assert_array_equal(grid[4:, frames_lib.GRID_LABEL_WIDTH:], 255)


def test_logging_settings_never_block_a_workdir(tmp_path):
  """A workdir from before the logging section, or with TensorBoard turned
  off or on later, is accepted without --allow_config_change."""
  from pipeline_helpers import load_config
  from slotformer_jax import files
  config = load_config('synthetic', 'tiny')
  workdir = str(tmp_path / 'run')
  accept(config, workdir)
  path = os.path.join(workdir, 'config.json')
  saved = files.read_json(path)
  del saved['logging']
  del saved['evaluation']['skip_first_frame']
  files.write_json_atomic(path, saved)
  assert accept(config, workdir) == []
  config.logging.tensorboard = False
  config.logging.image_every = 7
  assert accept(config, workdir) == []
  # skip_first_frame=True is a change like any other.
  config.evaluation.skip_first_frame = True
  with pytest.raises(Exception, match='evaluation.skip_first_frame'):
    accept(config, workdir)
