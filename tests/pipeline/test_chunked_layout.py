"""The chunked record layout (data/chunked.py): the same videos, the same
batches, fewer records read; whole-video (1.0.0) folders still read."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest
import tensorflow_datasets as tfds

from slotformer_jax.datasets.base import Conversion
from slotformer_jax.data import chunked
from slotformer_jax.data import integrity
from slotformer_jax.data import pipeline
from slotformer_jax.data import slots
from slotformer_jax.data import sources
from slotformer_jax.data.write import records as chunked_writer
from slotformer_jax.data.write import convert as writer
from slotformer_jax.errors import UserError

LENGTHS = [7, 9, 13, 6, 17, 8, 12, 10]
OBJECTS = 3


def _tensor(shape, dtype):
  return tfds.features.Tensor(shape=shape, dtype=dtype,
                              encoding=tfds.features.Encoding.BYTES)


def _features() -> tfds.features.FeaturesDict:
  return tfds.features.FeaturesDict({
      'video': _tensor((None, 6, 5, 3), np.uint8),
      'segmentations': _tensor((None, 6, 5), np.uint8),
      'boxes': _tensor((None, OBJECTS, 4), np.float32),
      'visible': _tensor((None, OBJECTS), np.bool_),
      'shapes': _tensor((OBJECTS,), np.int32),
      'num_objects': tfds.features.Scalar(np.int32),
      'video_name': tfds.features.Text(),
  })


def _example(index: int, length: int) -> dict:
  rng = np.random.default_rng(index)
  return {
      'video': rng.integers(0, 256, (length, 6, 5, 3), dtype=np.uint8),
      'segmentations': rng.integers(0, 4, (length, 6, 5), dtype=np.uint8),
      'boxes': rng.random((length, OBJECTS, 4), dtype=np.float32),
      'visible': rng.random((length, OBJECTS)) > 0.5,
      'shapes': np.arange(OBJECTS, dtype=np.int32) + index,
      'num_objects': index % 3 + 1,
      'video_name': f'video_{index}',
  }


def _write(root: Path, frames_per_chunk: int, version: str,
           lengths=tuple(LENGTHS)) -> Path:
  return chunked_writer.write_folder(
      root / f'k{frames_per_chunk}' / 'toy' / 'cfg' / version, name='toy',
      features=_features(), description='toy videos',
      splits={'train': (_example(i, t) for i, t in enumerate(lengths))},
      sizes={'train': len(lengths)}, frames_per_chunk=frames_per_chunk,
      videos_per_shard=3)


@pytest.fixture(scope='module')
def folders(tmp_path_factory):
  root = tmp_path_factory.mktemp('layouts')
  return {k: _write(root, k, '1.0.0' if k == 0 else '2.0.0')
          for k in (0, 1, 3, 4)}


def _open(folders, k):
  return sources.TfdsVideoSource(folders[k], 'train')


def _assert_items_equal(a, b):
  assert list(a) == list(b)
  for key in a:
    x, y = np.asarray(a[key]), np.asarray(b[key])
    assert x.dtype == y.dtype and x.shape == y.shape, key
    assert np.array_equal(x, y), key


def test_whole_videos_are_equal_across_layouts(folders):
  old = _open(folders, 0)
  assert not old.supports_clips and old.time_fields == ()
  for k in (1, 3, 4):
    new = _open(folders, k)
    assert new.supports_clips and len(new) == len(old) == len(LENGTHS)
    assert set(new.time_fields) == {'video', 'segmentations', 'boxes',
                                    'visible'}
    for i in range(len(LENGTHS)):
      assert new.num_frames(i) == LENGTHS[i] == old.num_frames(i)
      _assert_items_equal(old[i], new[i])
    _assert_items_equal(old[-1], new[-1])
    with pytest.raises(IndexError):
      new[len(LENGTHS)]  # pylint: disable=pointless-statement


@pytest.mark.parametrize('k', [1, 3, 4])
@pytest.mark.parametrize('clip_length,stride,fields', [
    (6, 1, ('video',)),        # 6: the whole of the shortest video
    (3, 2, ('video', 'segmentations', 'boxes', 'visible')),
    (1, 1, ('video',)),
    (4, 1, ('video', 'num_objects', 'boxes')),
    (2, 3, ('segmentations', 'video_name', 'video')),
])
def test_batches_are_bit_identical_to_the_whole_video_layout(
    folders, k, clip_length, stride, fields):
  old, new = _open(folders, 0), _open(folders, k)
  assert (clip_length - 1) * stride + 1 <= min(LENGTHS)
  for step in range(6):
    kwargs = dict(batch_size=5, clip_length=clip_length, seed=3,
                  fields=fields, frame_stride=stride)
    _assert_items_equal(pipeline.make_train_batch(old, step, **kwargs),
                        pipeline.make_train_batch(new, step, **kwargs))


def test_worker_processes_read_chunked_clips_like_the_thread(folders):
  # The chunked source pickled into reader workers (spawn) gives the stream
  # the in-process reader gives on the old layout.
  kwargs = dict(batch_size=5, clip_length=3, seed=4, frame_stride=2,
                fields=('video', 'segmentations', 'boxes'), start_step=2)
  old = pipeline.train_batches(_open(folders, 0), **kwargs)
  new = pipeline.train_batches(_open(folders, 4), num_workers=2, **kwargs)
  try:
    for _ in range(5):
      _assert_items_equal(next(old), next(new))
  finally:
    old.close()
    new.close()


def test_clips_reaching_the_last_frame_and_spanning_chunks(folders):
  old, new = _open(folders, 0), _open(folders, 3)
  for index, length in enumerate(LENGTHS):
    for start in range(length):
      for stride in (1, 2):
        clip = (length - 1 - start) // stride + 1
        fields = ('video', 'boxes', 'num_objects')
        _assert_items_equal(
            pipeline._slice_item(old[index], fields, index, start, clip,
                                 stride),
            new.clip(index, start, clip, stride, fields))
  with pytest.raises(ValueError, match='does not fit'):
    new.clip(0, 5, 3, 1)
  with pytest.raises(KeyError, match='no field'):
    new.clip(0, 0, 1, 1, ('video', 'depth'))
  with pytest.raises(ValueError, match='time first'):
    new.clip(0, 0, 2, 1, ('video', 'shapes'))


def test_stream_resume_and_second_host_match_the_old_layout(folders):
  old, new = _open(folders, 0), _open(folders, 4)
  kwargs = dict(clip_length=2, seed=7, fields=('video', 'visible'),
                frame_stride=2)
  full = pipeline.train_batches(old, batch_size=4, prefetch=0, **kwargs)
  expected = [next(full) for _ in range(8)]
  resumed = pipeline.train_batches(new, batch_size=4, start_step=5,
                                   prefetch=0, **kwargs)
  for step in range(5, 8):
    _assert_items_equal(expected[step], next(resumed))
  for step in range(8):  # host 1 of 2 reads rows [2, 4) of the same batch
    part = pipeline.make_train_batch(new, step, batch_size=2,
                                     process_index=1, process_count=2,
                                     **kwargs)
    _assert_items_equal({k: v[2:4] for k, v in expected[step].items()}, part)


def test_a_clip_reads_only_its_chunks(folders):
  new = _open(folders, 4)   # video 4: 17 frames, chunks of 4
  before = new.records_read
  new.clip(4, 0, 1)
  assert new.records_read - before == 1
  before = new.records_read
  new.clip(4, 2, 6)          # frames 2..7: chunks 0 and 1
  assert new.records_read - before == 2
  before = new.records_read
  new.clip(4, 8, 4, 2, ('video', 'num_objects'))  # 8..14: chunks 2, 3 + header
  assert new.records_read - before == 3
  before = new.records_read
  new.num_frames(4)           # from the index
  assert new.records_read == before
  new[4]                      # header + ceil(17 / 4) chunks
  assert new.records_read - before == 1 + 5
  old = _open(folders, 0)
  pipeline.make_train_batch(old, 0, batch_size=3, clip_length=1, seed=0)
  assert old.records_read == 3


def test_a_damaged_chunk_names_the_folder_and_the_fix(folders, tmp_path):
  import shutil  # pylint: disable=g-import-not-at-top
  folder = tmp_path / 'toy' / 'cfg' / '2.0.0'
  shutil.copytree(folders[4], folder)
  shard = sorted(folder.glob('toy-train.array_record-*'))[1]
  with open(shard, 'r+b') as f:
    f.truncate(os.path.getsize(shard) - 50)
  with pytest.raises(integrity.DamagedDataset, match=shard.name):
    integrity.verify_checksums(folder, 'train')
  source = sources.TfdsVideoSource(folder, 'train')
  source.clip(0, 0, 2)   # the first shard is intact
  with pytest.raises(UserError) as error:
    source.clip(4, 0, 2)
  assert str(folder) in str(error.value)
  assert 'Delete' in str(error.value) and 'prepare it again' in str(
      error.value)


def test_the_index_is_checksummed_and_versioned(folders, tmp_path):
  import shutil  # pylint: disable=g-import-not-at-top
  folder = tmp_path / 'toy' / 'cfg' / '2.0.0'
  shutil.copytree(folders[4], folder)
  index_path = folder / chunked.INDEX_FILE
  assert index_path in integrity.checksummed_files(folder)
  index = json.loads(index_path.read_text())
  assert index['frames_per_chunk'] == 4 and index['layout'] == 'chunked'
  assert index['splits']['train']['num_frames'] == LENGTHS
  index['layout_version'] = 99
  index_path.write_text(json.dumps(index))
  with pytest.raises(integrity.DamagedDataset, match=chunked.INDEX_FILE):
    integrity.verify_checksums(folder, 'train')
  with pytest.raises(UserError, match='version 99'):
    sources.TfdsVideoSource(folder, 'train')


def test_channel_order_passes_clips_through(folders):
  old = sources.with_channel_order(_open(folders, 0), 'bgr')
  new = sources.with_channel_order(_open(folders, 4), 'bgr')
  assert new.supports_clips and not old.supports_clips
  for step in range(3):
    kwargs = dict(batch_size=4, clip_length=3, seed=1,
                  fields=('video', 'segmentations'))
    _assert_items_equal(pipeline.make_train_batch(old, step, **kwargs),
                        pipeline.make_train_batch(new, step, **kwargs))


def _write_slots(tmp_path, seed):
  """Random slots (2 x 3) of every video of LENGTHS; their folder."""
  rng = np.random.default_rng(seed)
  slot_dir = str(tmp_path / 'slots')
  w = slots.SlotWriter(slot_dir, len(LENGTHS), 2, 3, savi_step=0)
  for i, t in enumerate(LENGTHS):
    w.add(i, rng.standard_normal((t, 2, 3), dtype=np.float32))
  w.close()
  return slot_dir


def test_slot_batches_with_frames_match_the_old_layout(folders, tmp_path):
  slot_dir = _write_slots(tmp_path, seed=0)
  old = slots.SlotSource(slot_dir, _open(folders, 0))
  new = slots.SlotSource(slot_dir, _open(folders, 3))
  bare = slots.SlotSource(slot_dir)
  for fields, source_pair in ((('slots', 'video'), (old, new)),
                              (('video', 'slots'), (old, new)),
                              (('slots',), (bare, new))):
    for step in range(5):
      kwargs = dict(batch_size=4, clip_length=2, seed=2, fields=fields,
                    frame_stride=2)
      _assert_items_equal(
          pipeline.make_train_batch(source_pair[0], step, **kwargs),
          pipeline.make_train_batch(source_pair[1], step, **kwargs))
  reads = new._video_source.records_read  # pylint: disable=protected-access
  pipeline.make_train_batch(new, 0, batch_size=4, clip_length=1, seed=0,
                            fields=('slots', 'video'))
  assert new._video_source.records_read - reads == 4  # pylint: disable=protected-access


def test_video_from_reads_only_the_clip_frames_it_keeps(folders, tmp_path):
  """L_I's stream (stages/dynamics.py): the video from clip frame
  `video_from` on; the slots whole; fewer chunk records read."""
  slot_dir = _write_slots(tmp_path, seed=1)
  full = slots.SlotSource(slot_dir, _open(folders, 3))
  kwargs = dict(batch_size=4, clip_length=6, seed=3,
                fields=('slots', 'video'))
  for k in (0, 3):  # whole-video and chunked records
    tail = slots.SlotSource(slot_dir, _open(folders, k), video_from=4)
    for step in range(4):
      want = pipeline.make_train_batch(full, step, **kwargs)
      got = pipeline.make_train_batch(tail, step, **kwargs)
      np.testing.assert_array_equal(got['slots'], want['slots'])
      assert got['video'].shape[1] == 2
      np.testing.assert_array_equal(got['video'], want['video'][:, 4:])
  # One frame, the clip's last: one chunk record per clip (the whole clip
  # spans two or three chunks of 3).
  tail = slots.SlotSource(slot_dir, _open(folders, 3), video_from=5)
  reads = tail._video_source.records_read  # pylint: disable=protected-access
  batch = pipeline.make_train_batch(tail, 0, **kwargs)
  assert batch['video'].shape[1] == 1
  assert tail._video_source.records_read - reads == 4  # pylint: disable=protected-access
  with pytest.raises(ValueError, match='no video frames'):
    slots.SlotSource(slot_dir, _open(folders, 3), video_from=6).clip(
        0, 0, 6, 1, ('slots', 'video'))
  with pytest.raises(ValueError, match='video_from'):
    slots.SlotSource(slot_dir, video_from=-1)


@dataclasses.dataclass(frozen=True)
class _Job:
  key: str
  index: int


def _convert_job(job: _Job) -> dict:
  return _example(job.index, LENGTHS[job.index])


def test_the_converter_writes_the_chunked_layout(tmp_path):
  spec = Conversion(
      name='toy', config_name='cfg', description='toy videos', params={},
      features_fn=_features, convert_fn=_convert_job)
  jobs = {'train': [_Job(f'v{i}', i) for i in range(len(LENGTHS))]}
  new = writer.convert(spec, jobs, tmp_path / 'new', num_workers=1,
                       videos_per_shard=3, progress=False)
  old = writer.convert(spec, jobs, tmp_path / 'old', num_workers=1,
                       videos_per_shard=3, progress=False, frames_per_chunk=0)
  assert new.dataset_dir.name == '2.0.0' == writer.VERSION
  assert old.dataset_dir.name == '1.0.0'
  assert integrity.verify_checksums(new.dataset_dir, 'train')
  assert (new.dataset_dir / chunked.INDEX_FILE).is_file()
  assert not (old.dataset_dir / chunked.INDEX_FILE).is_file()
  a = sources.TfdsVideoSource(old.dataset_dir, 'train')
  b = sources.open_prepared_dataset(tmp_path / 'new' / 'toy', 'train')
  assert b.supports_clips and not a.supports_clips
  for i in range(len(LENGTHS)):
    _assert_items_equal(a[i], b[i])
  assert json.loads((new.dataset_dir / 'video_names.json').read_text()) == {
      'train': [f'v{i}' for i in range(len(LENGTHS))]}


def _record_options(dataset_dir: Path) -> set[str]:
  """The writer options of every shard file (array_record stores them)."""
  from array_record.python import array_record_module  # pylint: disable=g-import-not-at-top
  options = set()
  for path in dataset_dir.glob('*.array_record-*'):
    reader = array_record_module.ArrayRecordReader(os.fspath(path))
    options.add(reader.writer_options_string())
    reader.close()
  return options


def test_chunks_are_uncompressed_unless_asked_and_read_alike(tmp_path):
  spec = Conversion(
      name='toy', config_name='cfg', description='toy videos', params={},
      features_fn=_features, convert_fn=_convert_job)
  jobs = {'train': [_Job(f'v{i}', i) for i in range(len(LENGTHS))]}
  plain = writer.convert(spec, jobs, tmp_path / 'plain', num_workers=1,
                         videos_per_shard=3, progress=False)
  packed = writer.convert(spec, jobs, tmp_path / 'packed', num_workers=1,
                          videos_per_shard=3, progress=False, compressed=True)
  whole = writer.convert(spec, jobs, tmp_path / 'whole', num_workers=1,
                         videos_per_shard=3, progress=False,
                         frames_per_chunk=0, compressed=False)
  for result, compressed in ((plain, False), (packed, True)):
    options, = _record_options(result.dataset_dir)
    assert ('uncompressed' in options.split(',')) is not compressed, options
    index = chunked.read_index(result.dataset_dir)
    assert index['compressed'] is compressed
  # Whole-video records keep array_record's compression (the old layout).
  options, = _record_options(whole.dataset_dir)
  assert 'uncompressed' not in options.split(','), options
  a = sources.TfdsVideoSource(plain.dataset_dir, 'train')
  b = sources.TfdsVideoSource(packed.dataset_dir, 'train')
  for i in range(len(LENGTHS)):
    _assert_items_equal(a[i], b[i])
    _assert_items_equal(a.clip(i, 1, 4, 1, ('video', 'boxes')),
                        b.clip(i, 1, 4, 1, ('video', 'boxes')))
  # The embedded writer's default is the converter's: uncompressed.
  options, = _record_options(_write(tmp_path / 'embedded', 4, '2.0.0'))
  assert 'uncompressed' in options.split(','), options


def test_a_conversion_resumed_with_the_other_compression_is_one_line(
    tmp_path):
  spec = Conversion(
      name='toy', config_name='cfg', description='toy videos', params={},
      features_fn=_features, convert_fn=_convert_job)
  jobs = {'train': [_Job(f'v{i}', i) for i in range(len(LENGTHS))]}
  first = writer.convert(spec, {'train': jobs['train']}, tmp_path,
                         num_workers=1, videos_per_shard=3, progress=False)
  # Un-finish it, keeping shard 0 and its sidecar; the rest is redone
  # compressed.
  dataset_dir = first.dataset_dir
  (dataset_dir / 'dataset_info.json').unlink()
  for path in dataset_dir.glob('_progress/train-0000[12].json'):
    path.unlink()
  with pytest.raises(writer.ConversionError) as error:
    writer.convert(spec, jobs, tmp_path, num_workers=1, videos_per_shard=3,
                   progress=False, compressed=True)
  message = str(error.value)
  assert '\n' not in message
  assert 'compressed and uncompressed' in message and '--overwrite' in message


def test_an_old_folder_is_read_and_a_new_conversion_next_to_it_wins(
    folders, tmp_path, caplog):
  import shutil  # pylint: disable=g-import-not-at-top
  conversion = tmp_path / 'toy' / 'cfg'
  shutil.copytree(folders[0], conversion / '1.0.0')
  with caplog.at_level('WARNING'):
    old = sources.open_prepared_dataset(tmp_path / 'toy', 'train')
  assert old.dataset_dir.name == '1.0.0' and not old.supports_clips
  assert 'whole-video records' in caplog.text
  batch = pipeline.make_train_batch(old, 0, batch_size=2, clip_length=3,
                                    seed=0)
  assert batch['video'].shape == (2, 3, 6, 5, 3)
  shutil.copytree(folders[4], conversion / '2.0.0')
  new = sources.open_prepared_dataset(tmp_path / 'toy', 'train')
  assert new.dataset_dir.name == '2.0.0' and new.supports_clips


def test_token_batches_with_frames_match_the_old_layout(folders, tmp_path):
  rng = np.random.default_rng(0)
  token_dir = str(tmp_path / 'tokens')
  w = slots.TokenWriter(token_dir, len(LENGTHS), 4, dvae_step=0)
  for i, t in enumerate(LENGTHS):
    w.add(i, rng.integers(0, 4096, (t, 4)))
  w.close()
  old = slots.TokenSource(token_dir, _open(folders, 0))
  new = slots.TokenSource(token_dir, _open(folders, 4))
  assert new.supports_clips and not old.supports_clips
  for fields in (('video', 'tokens'), ('tokens', 'video'), ('tokens',)):
    for step in range(4):
      kwargs = dict(batch_size=4, clip_length=3, seed=5, fields=fields,
                    frame_stride=2)
      _assert_items_equal(pipeline.make_train_batch(old, step, **kwargs),
                          pipeline.make_train_batch(new, step, **kwargs))
