"""Kubric MOVi: a fixture in the published TFDS layout -> convert -> read
back, damaged downloads, and the whole pipeline on it (configs/movi.py)."""

import json
import re
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tensorflow_datasets as tfds

import dataset_fixtures as fx
from slotformer_jax import datasets
from slotformer_jax import targets
from slotformer_jax.data import media
from slotformer_jax.datasets import movi
from slotformer_jax.data import prepare
from slotformer_jax.errors import MissingInputError
from dataset_fixtures import data_section

ROOT = Path(__file__).resolve().parents[2]
T, SIZE = 8, 32  # fixture frames and size (MOVi: 24 x 128 or 256)
SHARDS = {'train': [3, 2], 'validation': [2]}


def _convert(source, data_dir, *extra):
  return prepare.main(['--dataset=movi', f'--source={source}',
                       f'--data_dir={data_dir}', '--num_workers=1',
                       '--no_progress', *extra])


@pytest.fixture(scope='module')
def movi_download(tmp_path_factory):
  folder = tmp_path_factory.mktemp('download') / 'movi_a' / '32x32' / '1.0.0'
  examples = fx.write_movi(folder, shard_lengths=SHARDS, num_frames=T,
                           size=SIZE, seed=3)
  return folder, examples


@pytest.fixture(scope='module')
def converted(movi_download, tmp_path_factory):
  folder, examples = movi_download
  data_dir = tmp_path_factory.mktemp('data')
  # Native size (exact comparisons) and 16x16 (the pipeline's fixture run).
  assert _convert(folder, data_dir, '--resolution=32') == 0
  assert _convert(folder.parent, data_dir, '--resolution=16') == 0
  return data_dir, examples


def _source(data_dir, split, resolution=(32, 32)):
  return datasets.get_video_source(data_section(
      name='movi_a', data_dir=str(data_dir), resolution=resolution), split)


def test_fields_round_trip(converted):
  data_dir, examples = converted
  rows = movi.MAX_INSTANCES['movi_a']
  for split, movi_split in (('train', 'train'), ('val', 'validation')):
    source = _source(data_dir, split)
    assert len(source) == len(examples[movi_split])
    for item, example in zip(source, examples[movi_split]):
      n = len(example['instances'])
      assert item['video'].shape == (T, SIZE, SIZE, 3)
      np.testing.assert_array_equal(item['video'], example['video'])
      np.testing.assert_array_equal(item['segmentations'],
                                    example['segmentations'][..., 0])
      assert int(item['num_instances']) == n
      assert (str(item['video_name'].item(), 'utf-8')
              == example['metadata']['video_name'])
      assert item['boxes'].shape == (T, rows, 4)
      for k, instance in enumerate(example['instances']):
        frames = instance['bbox_frames']
        visible = np.zeros(T, bool)
        visible[frames] = True
        np.testing.assert_array_equal(item['visible'][:, k], visible)
        np.testing.assert_allclose(item['boxes'][frames, k],
                                   np.stack(instance['bboxes']))
        assert not item['boxes'][~visible, k].any()  # SAVi's padding box
        for field in ('positions', 'velocities', 'image_positions'):
          np.testing.assert_array_equal(item[field][:, k], instance[field])
      assert not item['visible'][:, n:].any()
      assert not item['positions'][:, n:].any()
      # Ids as in MOVi: 0 background, k = instance k - 1; row k - 1 of the
      # boxes is the box of id k (Kubric's boxes from the masks).
      for k in range(1, n + 1):
        boxes, frames = fx.boxes_from_ids(item['segmentations'], k)
        np.testing.assert_allclose(item['boxes'][frames, k - 1], boxes,
                                   atol=1e-6)


def _kubric_decoded(stored, value_range):
  """Kubric's decoding (challenges/movi/movi_a.py's docstring)."""
  low, high = value_range
  return stored / 65535 * (high - low) + low


def test_flow_and_depth_are_kept_and_served_decoded(converted):
  """Stored in MOVi's encoding at the source size (the uint16 values and
  ranges as they came), served decoded: backward / forward flow in pixels,
  `flow` = flow_to_rgb(backward flow), `depth` = log(1 + distance), as
  targets.py's contract says; the fixture's flows are those of its moving
  squares."""
  data_dir, examples = converted
  source = _source(data_dir, 'train')
  for item, example in zip(source, examples['train']):
    meta = example['metadata']
    for name in ('backward_flow', 'forward_flow'):
      want = _kubric_decoded(example[name], meta[f'{name}_range'])
      assert item[name].dtype == np.float32
      np.testing.assert_allclose(item[name], want, atol=1e-4)
    np.testing.assert_allclose(item['flow'], targets.flow_to_rgb(
        item['backward_flow']), atol=1e-6)
    distance = _kubric_decoded(example['depth'], meta['depth_range'])
    np.testing.assert_allclose(item['depth'], np.log1p(distance), atol=1e-5)
    assert item['flow'].shape == (T, SIZE, SIZE, 3)
    assert item['depth'].shape == (T, SIZE, SIZE, 1)
    assert not any(k.endswith('_range') for k in item)
    # A square moving by (dy, dx): backward flow (-dy, -dx) on its pixels
    # from frame 1 on (quantised to 1 / 65535 of the range).
    ids = item['segmentations']
    for k in range(1, len(example['instances']) + 1):
      pixels = ids[1:] == k
      if pixels.any():
        flow = item['backward_flow'][1:][pixels]
        np.testing.assert_allclose(flow, flow[:1].repeat(len(flow), 0),
                                   atol=1e-3)
    assert np.abs(item['backward_flow'][0]).max() < 1e-3  # frame 0: none


def test_clips_of_flow_and_depth_are_cut_as_the_frames(converted):
  data_dir, _ = converted
  source = _source(data_dir, 'train')
  item = source[1]
  fields = ('video', 'flow', 'depth', 'backward_flow', 'boxes')
  clip = source.clip(1, 2, 3, 2, fields)
  assert tuple(clip) == fields
  for field in fields:
    np.testing.assert_array_equal(clip[field], item[field][2:7:2])


def test_resized_flow_is_rescaled_and_depth_kept(converted):
  """--resolution=16 of 32x32 MOVi: flow and depth take the pixels the
  segmentations take; flow vectors are halved (row by 16 / 32, column by
  16 / 32), depth values kept."""
  data_dir, _ = converted
  small, full = _source(data_dir, 'train', (16, 16)), _source(data_dir,
                                                              'train')
  item, reference = small[1], full[1]

  def picked(values):
    return np.moveaxis(media.resize_labels(np.moveaxis(values, -1, 1),
                                           (16, 16)), 1, -1)

  for name in ('backward_flow', 'forward_flow'):
    np.testing.assert_allclose(item[name], picked(reference[name]) * 0.5,
                               atol=2e-4)
  np.testing.assert_allclose(item['depth'], picked(reference['depth']),
                             atol=1e-6)
  np.testing.assert_allclose(item['flow'], targets.flow_to_rgb(
      item['backward_flow']), atol=1e-6)


def test_a_folder_without_flow_reads_and_a_flow_run_is_told_to_convert(
    tmp_path):
  """A folder converted without flow and depth (before converter version
  2, or from a download without them) reads as before; a run whose SAVi
  reconstructs flow is one line naming the conversion command."""
  from slotformer_jax.errors import ConfigError  # pylint: disable=g-import-not-at-top
  from slotformer_jax.slot_models.savi import Savi  # pylint: disable=g-import-not-at-top
  from pipeline_helpers import load_config  # pylint: disable=g-import-not-at-top
  folder = tmp_path / 'movi_a' / '1.0.0'
  fx.write_movi(folder, shard_lengths={'train': [1]}, num_frames=T,
                size=16, seed=1, flow_depth=False)
  assert _convert(folder, tmp_path / 'data', '--resolution=16') == 0
  source = _source(tmp_path / 'data', 'train', (16, 16))
  item = source[0]
  assert 'flow' not in item and 'depth' not in item
  assert item['video'].shape == (T, 16, 16, 3)
  config = load_config('movi', 'fixture')
  config.data.data_dir = str(tmp_path / 'data')
  config.savi.targets = ('flow', 'depth')
  with pytest.raises(ConfigError) as raised:
    Savi(config).check_data(source, 'train')
  message = str(raised.value)
  assert '\n' not in message
  assert 'convert the download again' in message, message
  assert '--dataset=movi' in message and 'prepared_config' in message


def test_the_fixture_is_movi_shaped(movi_download):
  """The fixture exercises what the converter must handle: an instance that
  leaves the view (ragged boxes shorter than the video), and every MOVi-A
  feature of Kubric's builder."""
  _, examples = movi_download
  lengths = [len(i['bbox_frames']) for e in examples['train']
             for i in e['instances']]
  assert min(lengths) < T and max(lengths) == T
  folder, _ = movi_download
  leaves = movi.feature_leaves(json.loads((folder / 'features.json')
                                          .read_text()))
  assert {'depth', 'forward_flow', 'normal', 'events/collisions/force',
          'camera/positions', 'instances/shape_label'} <= set(leaves)


def test_feature_specs_match_tfds(movi_download):
  """The specs read from features.json are TFDS's own serialized specs of
  the same connectors (a Video is serialized as its Sequence of Images)."""
  folder, _ = movi_download
  leaves = movi.feature_leaves(json.loads((folder / 'features.json')
                                          .read_text()))
  expected = tfds.core.utils.flatten_nest_dict(
      fx.movi_a_features(T, SIZE, SIZE).get_serialized_info())
  assert set(leaves) == set(expected)
  for key, info in expected.items():
    leaf = leaves[key]
    assert leaf.shape == info.shape, key
    assert leaf.sequence_rank == info.sequence_rank, key
    want = ('bytes' if info.np_dtype == np.object_
            else np.dtype(info.np_dtype).name)
    assert leaf.dtype == want, key
  assert leaves['video'].image_shape == (SIZE, SIZE, 3)
  assert leaves['depth'].image_dtype == 'uint16'


def test_legacy_features_json_reads_the_same():
  """TFDS before 4.5 wrote features.json as nested {"type", "content"}."""
  def node(kind, content):
    return {'type': f'tensorflow_datasets.core.features.x.{kind}',
            'content': content}
  legacy = node('FeaturesDict', {
      'video': node('Video', {'shape': [24, 128, 128, 3],
                              'encoding_format': 'png',
                              'ffmpeg_extra_args': []}),
      'segmentations': node('Sequence', {
          'feature': node('Image', {'shape': [128, 128, 1],
                                    'dtype': 'uint8',
                                    'encoding_format': 'png'}),
          'length': 24}),
      'instances': node('Sequence', {'feature': node('FeaturesDict', {
          'positions': node('Tensor', {'shape': [24, 3],
                                       'dtype': 'float32'}),
          'bboxes': node('Sequence', {'feature': node('BBoxFeature', {}),
                                      'length': None}),
          'shape_label': node('ClassLabel', {'num_classes': 3}),
      }), 'length': None}),
      'metadata': node('FeaturesDict', {
          'video_name': node('Text', {}),
          'num_instances': node('Tensor', {'shape': [], 'dtype': 'uint16'})}),
  })
  leaves = movi.feature_leaves(legacy)
  assert leaves['video'] == movi.Leaf(shape=(24,), dtype='bytes',
                                      sequence_rank=1,
                                      image_shape=(128, 128, 3),
                                      image_dtype='uint8')
  assert leaves['segmentations'].shape == (24,)
  assert leaves['instances/positions'] == movi.Leaf(
      shape=(None, 24, 3), dtype='float32', sequence_rank=1)
  assert leaves['instances/bboxes'] == movi.Leaf(
      shape=(None, None, 4), dtype='float32', sequence_rank=2)
  assert leaves['instances/shape_label'].dtype == 'int64'
  assert leaves['metadata/num_instances'] == movi.Leaf(shape=(),
                                                       dtype='uint16')


def test_resized_conversion(converted):
  data_dir, _ = converted
  small, full = _source(data_dir, 'train', (16, 16)), _source(data_dir,
                                                              'train')
  item, reference = small[1], full[1]
  assert item['video'].shape == (T, 16, 16, 3)
  np.testing.assert_array_equal(
      item['segmentations'],
      media.resize_labels(reference['segmentations'], (16, 16)))
  np.testing.assert_array_equal(item['video'],
                                media.resize_frames(reference['video'],
                                                    (16, 16)))
  # Normalised boxes do not depend on the stored resolution.
  np.testing.assert_array_equal(item['boxes'], reference['boxes'])


def test_max_objects_crops_like_savi(movi_download, tmp_path):
  folder, examples = movi_download
  assert _convert(folder, tmp_path, '--resolution=32', '--max_objects=2',
                  '--splits=val') == 0
  item = _source(tmp_path, 'val')[0]
  example = examples['validation'][0]
  ids = example['segmentations'][..., 0]
  assert ids.max() > 2
  np.testing.assert_array_equal(item['segmentations'],
                                np.where(ids <= 2, ids, 0))
  assert item['boxes'].shape == (T, 2, 4)
  assert int(item['num_instances']) == len(example['instances'])


def test_splits_come_from_the_download(movi_download, tmp_path, capsys):
  folder, _ = movi_download
  assert movi.available_splits(folder) == ('train', 'val')
  assert _convert(folder, tmp_path, '--splits=test') == 1
  assert "movi_a has no 'test' split" in capsys.readouterr().err


def _damaged_copy(folder, tmp_path, shard, edit):
  copy = tmp_path / 'movi_a'
  copy.mkdir()
  for path in folder.iterdir():
    (copy / path.name).write_bytes(path.read_bytes())
  target = copy / shard
  data = edit(target.read_bytes())
  if data is None:
    target.unlink()
  else:
    target.write_bytes(data)
  return copy


def _one_error_line(capsys):
  err = capsys.readouterr().err
  lines = [line for line in err.splitlines() if line.startswith('error:')]
  assert len(lines) == 1 and 'Traceback' not in err, err
  return lines[0]


@pytest.mark.parametrize('edit, needle', [
    (lambda data: data[:-100], 'truncated'),
    (lambda data: None, 'of the 2 train shards listed in dataset_info.json '
     'are missing, e.g. movi_a-train.tfrecord-00001-of-00002'),
    # A byte in the middle of the second record's data.
    (lambda data: data[:len(data) * 3 // 4] + bytes([data[len(data) * 3 // 4]
                                                     ^ 0xFF])
     + data[len(data) * 3 // 4 + 1:], 'data checksum mismatch'),
])
def test_a_damaged_download_is_one_error_line_naming_the_file(
    movi_download, tmp_path, capsys, edit, needle):
  folder, _ = movi_download
  shard = 'movi_a-train.tfrecord-00001-of-00002'
  copy = _damaged_copy(folder, tmp_path, shard, edit)
  assert _convert(copy, tmp_path / 'data', '--resolution=32') == 1
  line = _one_error_line(capsys)
  assert needle in line and ('missing' in needle or shard in line), line
  if 'checksum' in needle:  # found while converting: that file is named
    assert 'record ' in line and 'download this file again' in line


def test_a_record_that_is_not_an_example_names_the_file(movi_download,
                                                        tmp_path, capsys):
  from slotformer_jax.data import tfrecord  # pylint: disable=g-import-not-at-top
  folder, _ = movi_download
  shard = 'movi_a-validation.tfrecord-00000-of-00001'
  copy = _damaged_copy(folder, tmp_path, shard, lambda data: data)
  # Valid framing and checksums around bytes that are no Example proto.
  records = list(tfrecord.iter_records(copy / shard))
  fx.write_tfrecords(copy / shard, [records[0], b'\xff' * 64])
  assert _convert(copy, tmp_path / 'data', '--splits=val') == 1
  line = _one_error_line(capsys)
  assert f'{shard} record 1: unreadable MOVi example' in line, line


def test_not_movi_and_no_download(tmp_path, capsys):
  assert _convert(tmp_path, tmp_path / 'data') == 1
  assert 'no dataset_info.json' in capsys.readouterr().err
  other = tmp_path / 'mnist'
  other.mkdir()
  tfds.features.FeaturesDict(
      {'image': tfds.features.Image(shape=(4, 4, 1))}).save_config(str(other))
  (other / 'dataset_info.json').write_text(json.dumps(
      {'name': 'mnist', 'splits': [{'name': 'train', 'shardLengths': ['1']}]}))
  assert _convert(other, tmp_path / 'data') == 1
  assert 'is not a MOVi dataset' in _one_error_line(capsys)


def test_unprepared_movi_names_the_command(tmp_path):
  with pytest.raises(MissingInputError, match='--dataset=movi --source='):
    _source(tmp_path, 'train')


def test_configs_load():
  from pipeline_helpers import load_config  # pylint: disable=g-import-not-at-top
  for letter, instances in movi.MAX_INSTANCES.items():
    if letter == 'movi_f':
      continue
    config = load_config('movi', letter[-1])
    assert config.data.name == letter
    assert config.data.max_instances == instances
    assert config.savi.num_slots == instances + 1
    assert config.data.resolution == (64, 64)
    assert (config.slotformer.burn_in + config.evaluation.rollout_steps
            == 24)
    assert config.evaluation.skip_first_frame
  with pytest.raises(ValueError, match='unknown MOVi variant'):
    load_config('movi', 'g')


# 65 s: -m slow. The default suite reads and converts MOVi (the tests above)
# and runs the whole pipeline on converted OBJ3D (test_datasets_obj3d.py).
@pytest.mark.slow
def test_pipeline_trains_and_evaluates_on_movi(converted, tmp_path):
  """`python -m slotformer_jax.main --config=configs/movi.py:fixture` on the
  converted fixture: every stage of --mode=all, then the results."""
  data_dir, _ = converted
  workdir = tmp_path / 'run'
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS='cpu',
             SLOTFORMER_DATA_DIR=str(tmp_path / 'cache'))
  env.pop('XLA_FLAGS', None)  # one device: the fixture's batches are 2
  result = subprocess.run(
      [sys.executable, '-m', 'slotformer_jax.main',
       f'--config={ROOT / "configs" / "movi.py"}:fixture',
       f'--workdir={workdir}', f'--config.data.data_dir={data_dir}'],
      cwd=str(tmp_path), env=env, capture_output=True, text=True,
      timeout=600)
  assert result.returncode == 0, result.stderr[-3000:]
  metrics = json.loads((workdir / 'eval' / 'metrics.json').read_text())
  assert metrics['protocol']['split'] == 'val'
  assert metrics['savi']['num_videos'] == 2
  assert metrics['savi']['num_frames'] == T
  for name in ('fg_ari', 'ar'):
    per_step = metrics['rollout']['slotformer'][name]['per_step']
    assert len(per_step) == T - 2 and all(v is not None for v in per_step)
  assert -1 <= metrics['savi']['fg_ari'] <= 1
  assert any(p.name.endswith('.gif') for p in (workdir / 'render').iterdir())


@pytest.mark.slow
def test_savi_plus_plus_trains_and_evaluates_on_movi(converted, tmp_path):
  """`configs/movi.py:savipp_fixture` on the converted fixture with its flow
  and depth: SAVi++ (ResNet-34 + Transformer encoder, conditional on the
  boxes, the random resized crop, flow + depth targets), extraction,
  SlotFormer with L_I on flow + depth, evaluation, rendering, explorer."""
  data_dir, _ = converted
  workdir = tmp_path / 'run'
  env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS='cpu',
             SLOTFORMER_DATA_DIR=str(tmp_path / 'cache'))
  env.pop('XLA_FLAGS', None)  # one device: the fixture's batches are 2
  result = subprocess.run(
      [sys.executable, '-m', 'slotformer_jax.main',
       f'--config={ROOT / "configs" / "movi.py"}:savipp_fixture',
       f'--workdir={workdir}', f'--config.data.data_dir={data_dir}'],
      cwd=str(tmp_path), env=env, capture_output=True, text=True,
      timeout=900)
  assert result.returncode == 0, result.stderr[-3000:]
  log = result.stderr
  for stage in ('train_savi', 'extract_slots', 'train_slotformer', 'evaluate',
                'render', 'explore'):
    assert f'{stage} took' in log, stage
  # One loss per target in both stages (SAVi's recon, SlotFormer's L_I).
  for term in ('recon_loss_flow', 'recon_loss_depth', 'image_loss_flow',
               'image_loss_depth'):
    assert re.search(rf'{term}=[0-9.]+', log), term
  metrics = json.loads((workdir / 'eval' / 'metrics.json').read_text())
  assert metrics['protocol']['split'] == 'val'
  assert metrics['savi']['num_videos'] == 2
  assert -1 <= metrics['savi']['fg_ari'] <= 1
  assert 'psnr' not in metrics['savi']  # SAVi++ decodes no frames
  # Its pictures show every method's flow and depth (no frames decoded).
  render = workdir / 'render'
  assert (render / 'rollout_000.png').exists()
  assert (render / 'rollout_000.gif').exists()
  for name in ('fg_ari', 'fg_miou', 'ar'):
    per_step = metrics['rollout']['slotformer'][name]['per_step']
    assert len(per_step) == T - 2 and all(v is not None for v in per_step)
  # So does the explorer, the data's flow and depth above them.
  page = (workdir / 'explore' / 'index.html').read_text()
  for row in ('"flow"', '"depth ', '"SlotFormer flow"', '"SlotFormer depth ',
              '"copy-last flow"', 'decoded flow x alpha'):
    assert row in page, row
