"""A fourth generated dataset from this one file, without editing the package.

'test_squares': coloured squares gliding over a gray floor and bouncing off
the walls, drawn with numpy (no simulator), with their segmentation ids and
boxes. Its module is this file: the spec (what a video holds), the folder its
parameters name, the generator (writing through the data stage's `Output`)
and `datasets.register`. Registered at import, it runs the data stage
(`prepare_data`: generated once, its checksums recorded and verified) and
the tiny pipeline (SAVi, slot extraction, SlotFormer, evaluation); the config
check names it among the known datasets.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
from pathlib import Path

import ml_collections
import numpy as np
import pytest
import tensorflow_datasets as tfds

from pipeline_helpers import check
from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from slotformer_jax import datasets
from slotformer_jax.data import sources
from slotformer_jax.datasets import base
from slotformer_jax.errors import ConfigError
from slotformer_jax.runtime import sharding

NAME = 'test_squares'
SPLITS = ('train', 'val', 'test')
COLORS = np.array([(220, 40, 40), (40, 180, 60), (50, 80, 220),
                   (230, 200, 40)], np.uint8)
FLOOR = 128


@dataclasses.dataclass(frozen=True)
class Squares:
  """Generation parameters: they name the folder."""

  resolution: tuple[int, int] = (16, 16)
  num_frames: int = 8
  num_objects: int = 2
  side: int = 5
  seed: int = 0
  num_train: int = 8
  num_val: int = 4
  num_test: int = 4

  @property
  def slug(self) -> str:
    h, w = self.resolution
    return base.digest_name(f'r{h}x{w}_t{self.num_frames}_k{self.num_objects}',
                            dataclasses.asdict(self))

  def sizes(self) -> dict[str, int]:
    return {'train': self.num_train, 'val': self.num_val,
            'test': self.num_test}


def parameters(data_config: ml_collections.ConfigDict) -> Squares:
  fields = {f.name for f in dataclasses.fields(Squares)}
  values = {k: data_config[k] for k in fields if k in data_config}
  values['resolution'] = tuple(values.get('resolution', (16, 16)))
  return Squares(**values)


def features(squares: Squares) -> tfds.features.FeaturesDict:
  (h, w), t, o = squares.resolution, squares.num_frames, squares.num_objects
  return tfds.features.FeaturesDict({
      'video': base.tensor((t, h, w, 3), np.uint8),
      'segmentations': base.tensor((t, h, w), np.uint8),
      'boxes': base.tensor((t, o, 4), np.float32),
      'index': tfds.features.Scalar(np.int32),
  })


def video(squares: Squares, split: str, index: int) -> dict[str, np.ndarray]:
  """Video `index` of `split`: a pure function of them and the seed."""
  rng = np.random.default_rng([squares.seed, SPLITS.index(split), index])
  (h, w), t, side = squares.resolution, squares.num_frames, squares.side
  room = np.array([h - side, w - side], np.float64)
  position = rng.uniform(0, 1, (squares.num_objects, 2)) * room
  velocity = rng.uniform(-1.5, 1.5, (squares.num_objects, 2))
  frames = np.full((t, h, w, 3), FLOOR, np.uint8)
  ids = np.zeros((t, h, w), np.uint8)
  boxes = np.zeros((t, squares.num_objects, 4), np.float32)
  for step in range(t):
    for k, (y, x) in enumerate(np.round(position).astype(int)):
      frames[step, y:y + side, x:x + side] = COLORS[k % len(COLORS)]
      ids[step, y:y + side, x:x + side] = k + 1
      boxes[step, k] = (y / h, x / w, (y + side) / h, (x + side) / w)
    position += velocity
    bounced = (position < 0) | (position > room)
    velocity[bounced] *= -1
    position = np.clip(position, 0, room)
  return {'video': frames, 'segmentations': ids, 'boxes': boxes,
          'index': np.array(index, np.int32)}


def folder(squares: Squares, data_dir: str | Path) -> Path:
  return sources.generated_dir(data_dir, NAME, squares.slug)


def generate(squares: Squares, out: base.Output) -> Path:
  return out.tfds_folder(
      folder(squares, out.data_dir), name=NAME, features=features(squares),
      description='coloured squares bouncing off the walls',
      split_sizes=squares.sizes(), make=functools.partial(video, squares))


DATASET = datasets.register(base.Generated(
    names=(NAME,), label='squares', features=functools.partial(
        features, Squares()),
    what='the squares dataset', parameters=parameters, folder=folder,
    generate=generate, split_sizes=Squares.sizes))


def squares_config(data_dir: Path) -> ml_collections.ConfigDict:
  """The micro SAVi pipeline (tests/pipeline_helpers.py) on the squares."""
  config = micro_config('savi', data_dir)
  config.data.name = NAME
  config.data.num_objects = 2
  config.data.max_instances = 2
  # The fewest compiled programs: two steps each, no Slot-LSTM, the rollout
  # metrics that need no LPIPS network, no SAVi whole-video scores.
  config.savi.num_train_steps = config.slotformer.num_train_steps = 2
  config.slot_lstm.train = False
  config.extraction.splits = ('train', 'test')
  config.evaluation.metrics = ('psnr', 'fg_ari')
  config.evaluation.savi_metrics = False
  return config


def test_the_package_does_not_know_it():
  package = pathlib.Path(datasets.__file__).parent.parent
  assert not any(NAME in path.read_text() for path in package.rglob('*.py'))
  assert datasets.get(NAME) is DATASET
  assert DATASET.frames == 8 and DATASET.resolution == (16, 16)
  # Registering it again (a re-import) is a no-op; another dataset under
  # its name is refused.
  assert datasets.register(DATASET) is DATASET
  with pytest.raises(ValueError, match='taken'):
    datasets.register(dataclasses.replace(DATASET, label='other squares'))


def test_a_typo_in_its_name_is_one_line_before_any_work(tmp_path):
  config = squares_config(tmp_path / 'data')
  config.data.name = 'test_square'
  with pytest.raises(ConfigError, match=f"'test_square'.*{NAME}"):
    check(config, ['train_savi'])
  assert not (tmp_path / 'data').exists()


def test_a_dataset_from_one_test_file_runs_the_pipeline(tmp_path):
  config = squares_config(tmp_path / 'data')
  check(config, ['prepare_data', 'train_savi', 'evaluate'])
  workdir = tmp_path / 'run'
  results = run_stages(config, workdir, sharding.make_mesh(),
                       ['train_savi', 'extract_slots', 'train_slotformer',
                        'evaluate'])
  # The data stage made it where its parameters say, checksums recorded.
  path = folder(parameters(config.data), tmp_path / 'data')
  assert (path / 'checksums.json').is_file()
  videos = datasets.get_video_source(config.data, 'test')
  assert len(videos) == 4
  expected = video(parameters(config.data), 'test', 3)
  for key, value in expected.items():
    np.testing.assert_array_equal(videos[3][key], value, err_msg=key)
  evaluated = results['evaluate']
  assert evaluated['protocol']['clips'] == 'first'
  assert evaluated['protocol']['num_videos'] == 4
  rollout = evaluated['rollout']['slotformer']
  assert len(rollout['fg_ari']['per_step']) == (
      config.evaluation.rollout_steps)
  assert np.isfinite(rollout['psnr']['mean'])
  assert 0 <= rollout['fg_ari']['mean'] <= 1
  # A clip rule the dataset does not offer is one line before any work.
  config.evaluation.clips = 'clevrer'
  with pytest.raises(ConfigError, match="evaluation.clips must be one of "
                     f"'first' for data.name='{NAME}'"):
    check(config, ['evaluate'])
