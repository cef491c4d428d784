"""Physion: fixtures in the published layout -> convert -> read back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import dataset_fixtures as fx
from slotformer_jax import datasets
from slotformer_jax.datasets import physion
from slotformer_jax.data import pipeline
from slotformer_jax.data import prepare
from slotformer_jax.data import sources
from dataset_fixtures import data_section

# ffmpeg runs as a subprocess (fork + exec at once), which JAX's fork warning
# does not tell apart from a bare fork when JAX was imported by another test.
pytestmark = pytest.mark.filterwarnings(
    r'ignore:os\.fork\(\) was called:RuntimeWarning')

LONG, SHORT = 20, 8     # frames of the two template videos
KEEP = 12               # --num_frames (the paper: 150)
RES = 16
STEP = 10               # grey-level step between frames of the templates


def _copy(template: Path, target: Path) -> None:
  target.parent.mkdir(parents=True, exist_ok=True)
  target.write_bytes(template.read_bytes())


def make_source(base: Path) -> Path:
  """All 8 scenarios: 2 Training, 2 Readout and 1 Testing video each."""
  root = base / 'Physion'
  long_video = fx.write_mp4(base / 'long.mp4', fx.marker_video(LONG, 32, 32,
                                                                 STEP))
  short_video = fx.write_mp4(base / 'short.mp4', fx.marker_video(SHORT, 32,
                                                                   32, STEP))
  readout_rows, test_rows = [], []
  for s, scenario in enumerate(physion.SCENARIOS):
    for k in range(2):
      _copy(long_video if k == 0 else short_video,
            root / physion.TRAIN_DIR / f'{scenario}_training_MP4s' /
            f'pilot_{scenario.lower()}_train_{k:04d}_img.mp4')
      _copy(long_video, root / physion.TRAIN_DIR / f'{scenario}_readout_MP4s' /
            f'pilot_{scenario.lower()}_readout_{k:04d}_img.mp4')
      readout_rows.append((f'pilot_{scenario.lower()}_readout_{k:04d}',
                           (s + k) % 2 == 0))
    name = (f'pilot_{scenario.lower()}' if scenario != 'Contain'
            else 'pilot-containment-box')  # '..._0004' is a bad stimulus
    _copy(long_video, root / physion.TEST_DIR / scenario / 'mp4s-redyellow' /
          f'{name}-redyellow_0004_img.mp4')
    test_rows.append((f'{name}_0004_img', s % 2 == 1))
  for path, rows in ((root / physion.READOUT_LABELS, readout_rows),
                     (root / physion.TEST_LABELS, test_rows)):
    path.write_text(',ground truth outcome\n' + ''.join(
        f'{name},{label}\n' for name, label in rows))
  return root


def convert(root: Path, data_dir: Path, *extra: str) -> int:
  return prepare.main([
      '--dataset=physion', f'--source={root}', f'--data_dir={data_dir}',
      f'--resolution={RES}', f'--num_frames={KEEP}', '--num_workers=1',
      '--no_progress', *extra])


def source_for(data_dir: Path, split: str) -> sources.VideoSource:
  return datasets.get_video_source(data_section(
      name='physion', data_dir=str(data_dir), resolution=(RES, RES)), split)


@pytest.fixture(scope='module')
def converted(tmp_path_factory):
  base = tmp_path_factory.mktemp('physion')
  root = make_source(base)
  assert convert(root, base / 'data', '--val_fraction=0.5') == 0
  return root, base / 'data'


def levels(video: np.ndarray) -> np.ndarray:
  return video[:, RES // 2, RES // 2].astype(float).mean(-1)


def test_frames_truncated_and_resized(converted):
  _, data_dir = converted
  items = [source_for(data_dir, split)[i]
           for split in ('train', 'val') for i in range(len(source_for(
               data_dir, split)))]
  lengths = sorted({item['video'].shape[0] for item in items})
  # Long videos are cut to the first KEEP frames, short ones kept whole.
  assert lengths == [SHORT, KEEP]
  for item in items:
    video = item['video']
    assert video.shape[1:] == (RES, RES, 3) and video.dtype == np.uint8
    np.testing.assert_allclose(levels(video),
                               20 + STEP * np.arange(len(video)), atol=2)
    assert int(item['label']) == -1          # Training subset: no labels


def test_splits_labels_and_flags(converted):
  root, data_dir = converted
  train, val = source_for(data_dir, 'train'), source_for(data_dir, 'val')
  names = lambda src: {str(src[i]['video_name'].item(), 'utf-8')
                       for i in range(len(src))}
  # The Training videos are split by name hash, disjointly and completely.
  assert len(train) + len(val) == 16
  assert not names(train) & names(val)
  for name in names(val):
    assert physion._is_val(f'{name}_img.mp4', 0.5)
  readout = source_for(data_dir, 'readout_train')
  readout_val = source_for(data_dir, 'readout_val')
  labels = dict(
      line.split(',') for line in
      (root / physion.READOUT_LABELS).read_text().splitlines()[1:])
  for src in (readout, readout_val):
    for i in range(len(src)):
      item = src[i]
      name = str(item['video_name'].item(), 'utf-8')
      assert int(item['label']) == (labels[name] == 'True')
      assert physion.SCENARIOS[int(item['scenario'])].lower() in name
  test = source_for(data_dir, 'test')
  assert len(test) == 8
  for i in range(8):
    item = test[i]
    scenario = physion.SCENARIOS[int(item['scenario'])]
    assert int(item['label']) == physion.SCENARIOS.index(scenario) % 2
    assert bool(item['bad_stimulus']) == (scenario == 'Contain')
    assert item['video'].shape == (KEEP, RES, RES, 3)


def test_stride_three_at_read_time(converted):
  _, data_dir = converted
  batch = pipeline.make_train_batch(
      source_for(data_dir, 'readout_train'), 0, batch_size=3, clip_length=4,
      seed=1, frame_stride=3)
  assert batch['video'].shape == (3, 4, RES, RES, 3)
  steps = np.diff(batch['video'][:, :, RES // 2, RES // 2].astype(float)
                  .mean(-1), axis=1)
  np.testing.assert_allclose(steps, 3 * STEP, atol=2)


def test_official_split_files(tmp_path):
  root = make_source(tmp_path)
  lists = tmp_path / 'splits'
  lists.mkdir()
  train_dir = f'{physion.TRAIN_DIR}/Collide_training_MP4s'
  readout_dir = f'{physion.TRAIN_DIR}/Drop_readout_MP4s'
  content = {
      'training_train.json': {'Collide': [
          f'{train_dir}/pilot_collide_train_0001_img.mp4']},
      'training_val.json': {'Collide': [
          f'{train_dir}/pilot_collide_train_0000_img.mp4']},
      'readout_train.json': {'Drop': [
          f'{readout_dir}/pilot_drop_readout_0000_img.mp4',
          f'{readout_dir}/pilot_drop_readout_0001_img.mp4']},
      'readout_val.json': {'Drop': [
          f'{readout_dir}/pilot_drop_readout_0001_img.mp4']},
      'test_test.json': {'Roll': [
          f'{physion.TEST_DIR}/Roll/mp4s-redyellow/'
          'pilot_roll-redyellow_0004_img.mp4']},
  }
  for name, payload in content.items():
    fx.write_json(lists / name, payload)
  assert convert(root, tmp_path / 'data', f'--split_files={lists}') == 0
  data_dir = tmp_path / 'data'
  assert [len(source_for(data_dir, s)) for s in physion.SPLITS] == [
      1, 1, 2, 1, 1]
  assert source_for(data_dir, 'train')[0]['video'].shape[0] == SHORT


def test_bad_inputs(tmp_path, capsys):
  root = make_source(tmp_path)
  # Truncated and unreadable videos, and a readout video without a label.
  truncated = fx.write_mp4(
      root / physion.TRAIN_DIR / 'Link_training_MP4s' / 'trunc_img.mp4',
      fx.noise_video(LONG, 32, 32))
  fx.truncate(truncated, 0.5)
  (root / physion.TRAIN_DIR / 'Link_training_MP4s' / 'junk_img.mp4'
   ).write_bytes(b'junk' * 50)
  _copy(root.parent / 'long.mp4', root / physion.TRAIN_DIR /
        'Link_readout_MP4s' / 'unlabelled_img.mp4')
  result = prepare.run(prepare.build_parser().parse_args([
      '--dataset=physion', f'--source={root}',
      f'--data_dir={tmp_path / "data"}', f'--resolution={RES}',
      f'--num_frames={KEEP}', '--num_workers=1', '--no_progress',
      '--val_fraction=0', '--splits=train,readout_train',
      '--max_skip_fraction=0.5']))
  assert result.num_examples == {'train': 16, 'readout_train': 16}
  assert result.skip_counts() == {
      'train': {'truncated_video': 1, 'unreadable_video': 1},
      'readout_train': {'missing_label': 1}}
  # Missing label file / scenario folder: clear errors naming the layout.
  (root / physion.TEST_LABELS).unlink()
  assert convert(root, tmp_path / 'data2', '--splits=test') == 1
  err = capsys.readouterr().err
  assert 'PhysionTestMP4s/labels.csv' in err and 'mp4s-redyellow' in err
  (root / physion.TRAIN_DIR / 'Roll_training_MP4s').rename(tmp_path / 'x')
  with pytest.raises(FileNotFoundError, match='Roll_training_MP4s'):
    physion.discover(root, 'train', physion.Options())


def test_label_file_parsing(tmp_path):
  path = tmp_path / 'labels.csv'
  path.write_text(',ground truth outcome\nfoo_0001_img,True\nbar-redyellow_'
                  '0002,False\n')
  assert physion.read_labels(path) == {'foo_0001': 1, 'bar_0002': 0}
  path.write_text(',outcome\nfoo,True\n')
  with pytest.raises(ValueError, match='ground truth outcome'):
    physion.read_labels(path)
  assert physion.stimulus_name(
      'pilot_towers_nb2_fr015_SJ010_mono0_dis0_occ0_tdwroom-redyellow_0001_'
      'img.mp4') == 'pilot_towers_nb2_fr015_SJ010_mono0_dis0_occ0_tdwroom_0001'
  assert json.dumps(physion.Options().params)  # serialisable


def test_label_file_not_utf8_is_one_line_naming_the_file(tmp_path, capsys):
  root = make_source(tmp_path)
  labels = root / physion.READOUT_LABELS
  # A spreadsheet that saved the labels as Windows-1252 ('é' is 0xe9).
  labels.write_bytes(labels.read_bytes() + 'caf\u00e9_0001,True\n'.encode(
      'cp1252'))
  assert convert(root, tmp_path / 'data', '--splits=readout_train') == 1
  err = capsys.readouterr().err.strip()
  assert len(err.splitlines()) == 1 and err.startswith('error: '), err
  assert f'{labels}:18: not UTF-8 text (byte 0xe9)' in err, err
  # A byte-order mark (also a spreadsheet export) is not an error.
  labels.write_bytes(b'\xef\xbb\xbf' + f',{physion.LABEL_COLUMN}\n'
                     'foo_img,True\n'.encode())
  assert physion.read_labels(labels) == {'foo': 1}


def test_empty_hashed_split_says_so(tmp_path, capsys):
  root = make_source(tmp_path)
  # 16 Training videos, none of whose names hashes below 0.02: 'val' is
  # empty although every folder is there.
  assert convert(root, tmp_path / 'data', '--splits=val',
                 '--val_fraction=0.02') == 1
  err = capsys.readouterr().err.strip()
  assert len(err.splitlines()) == 1, err
  assert 'not found' not in err, err
  assert ("none of the 16 training videos falls in split 'val'" in err
          and '--val_fraction=0.02' in err), err
  # Empty folders are named as such.
  for scenario in physion.SCENARIOS:
    for video in (root / physion.TRAIN_DIR /
                  f'{scenario}_readout_MP4s').glob('*.mp4'):
      video.unlink()
  with pytest.raises(FileNotFoundError, match='hold no .mp4'):
    physion.discover(root, 'readout_val', physion.Options())
