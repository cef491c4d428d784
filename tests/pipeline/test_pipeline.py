"""Tests of the host-side batching and of the shared source interface."""

from __future__ import annotations

import gc
import itertools
import shutil
import threading
from pathlib import Path

import ml_collections
import numpy as np
import pytest

from dataset_fixtures import data_section
from slotformer_jax import datasets
from slotformer_jax.data import pipeline
from slotformer_jax.data import sources
from slotformer_jax.datasets import synthetic
from slotformer_jax.datasets.synthetic import SyntheticConfig
from slotformer_jax.stages import data as data_stage


class FakeSource:
  """Videos whose pixels encode (video, frame): video[t] == 10 * i + t.

  Lengths vary per video (``lengths[i]``); each item also carries slots-like
  float32 [T, 2, 3] features and a scalar.
  """

  def __init__(self, lengths: list[int], fail_at: int | None = None):
    self.lengths = lengths
    self.fail_at = fail_at
    self.reads = 0

  def __len__(self) -> int:
    return len(self.lengths)

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    if index == self.fail_at:
      raise RuntimeError(f'broken record {index}')
    self.reads += 1
    t = np.arange(self.lengths[index])
    code = (100 * index + t).astype(np.int32)
    return {
        'video': np.broadcast_to(code[:, None, None, None] % 256,
                                 (len(t), 2, 2, 3)).astype(np.uint8),
        'code': code,
        'slots': np.broadcast_to(code[:, None, None],
                                 (len(t), 2, 3)).astype(np.float32),
        'num_objects': np.int32(index % 3),
    }


def _decode(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  return codes // 100, codes % 100


def _take(iterator, n: int) -> list[dict[str, np.ndarray]]:
  batches = list(itertools.islice(iterator, n))
  iterator.close()
  return batches


def _assert_batches_equal(a, b):
  assert len(a) == len(b)
  for x, y in zip(a, b):
    assert x.keys() == y.keys()
    for key in x:
      np.testing.assert_array_equal(x[key], y[key])


def test_train_batches_shapes_dtypes_and_clip_content():
  source = FakeSource([12, 9, 20, 7, 15])
  it = pipeline.train_batches(source, batch_size=4, clip_length=3, seed=0,
                              fields=('video', 'code', 'slots', 'num_objects'),
                              frame_stride=2)
  for batch in _take(it, 6):
    assert batch['video'].shape == (4, 3, 2, 2, 3)
    assert batch['video'].dtype == np.uint8
    assert batch['slots'].shape == (4, 3, 2, 3)
    assert batch['slots'].dtype == np.float32
    assert batch['num_objects'].shape == (4,)
    videos, frames = _decode(batch['code'])
    # One video per clip, frames every `frame_stride`, inside the video.
    assert (videos == videos[:, :1]).all()
    assert (np.diff(frames, axis=1) == 2).all()
    lengths = np.array(source.lengths)[videos[:, 0]]
    assert (frames[:, 0] >= 0).all() and (frames[:, -1] < lengths).all()
    np.testing.assert_array_equal(batch['num_objects'], videos[:, 0] % 3)
    np.testing.assert_array_equal(batch['video'][:, :, 0, 0, 0],
                                  batch['code'] % 256)


def test_train_batches_deterministic_and_seeded():
  source = FakeSource([10] * 7)
  kwargs = dict(batch_size=3, clip_length=4, fields=('code',))
  a = _take(pipeline.train_batches(source, seed=5, **kwargs), 8)
  b = _take(pipeline.train_batches(source, seed=5, prefetch=0, **kwargs), 8)
  c = _take(pipeline.train_batches(source, seed=6, **kwargs), 8)
  _assert_batches_equal(a, b)
  assert any((x['code'] != y['code']).any() for x, y in zip(a, c))


def test_resume_equals_uninterrupted_run():
  source = FakeSource([8, 11, 9, 30, 6, 10])
  kwargs = dict(batch_size=4, clip_length=5, seed=1, fields=('code',))
  full = _take(pipeline.train_batches(source, **kwargs), 12)
  resumed = _take(pipeline.train_batches(source, start_step=7, **kwargs), 5)
  _assert_batches_equal(full[7:], resumed)


def test_every_video_once_per_epoch():
  source = FakeSource([6] * 12)
  batches = _take(pipeline.train_batches(source, batch_size=4, clip_length=2,
                                         seed=3, fields=('code',)), 6)
  videos = np.concatenate([_decode(b['code'])[0][:, 0] for b in batches])
  assert sorted(videos[:12]) == list(range(12))  # epoch 0
  assert sorted(videos[12:]) == list(range(12))  # epoch 1
  assert (videos[:12] != videos[12:]).any()      # reshuffled


@pytest.mark.parametrize('process_count', [2, 4])
def test_hosts_rows_concatenate_to_the_one_host_batch(process_count):
  # 10 videos, 3 rows per host: with 2 hosts step 1 (positions 6..11) holds
  # the end of epoch 0 and the start of epoch 1; with 4 (12 rows) every
  # step holds two epochs.
  source = FakeSource([8, 11, 9, 30, 6, 10, 7, 12, 9, 14])
  kwargs = dict(clip_length=3, seed=4, frame_stride=2,
                fields=('code', 'slots', 'num_objects'))
  steps = 7
  one = _take(pipeline.train_batches(
      source, batch_size=3 * process_count, **kwargs), steps)
  hosts = [_take(pipeline.train_batches(
      source, batch_size=3, process_index=p, process_count=process_count,
      **kwargs), steps) for p in range(process_count)]
  for s in range(steps):
    for key in kwargs['fields']:
      np.testing.assert_array_equal(
          np.concatenate([host[s][key] for host in hosts]), one[s][key],
          err_msg=f'step {s} {key}')


def _old_plan(seed, step, batch_size, num_videos):
  """The single-process plan before hosts shared one global plan."""
  positions = np.arange(step * batch_size, (step + 1) * batch_size)
  epochs, offsets = np.divmod(positions, num_videos)
  videos = np.array([np.random.default_rng([seed, 0, 0, e]).permutation(
      num_videos)[o] for e, o in zip(epochs, offsets)])
  return videos, np.random.default_rng([seed, 1, 0, step]).random(batch_size)


def test_one_host_stream_is_the_old_plan():
  lengths = [12, 9, 20, 7, 15, 30, 8]
  source = FakeSource(lengths)
  batches = _take(pipeline.train_batches(
      source, batch_size=4, clip_length=3, seed=9, frame_stride=2,
      fields=('code',)), 9)
  span = (3 - 1) * 2 + 1
  for s, batch in enumerate(batches):
    videos, fractions = _old_plan(9, s, 4, len(lengths))
    starts = (fractions * (np.array(lengths)[videos] - span + 1)).astype(int)
    np.testing.assert_array_equal(batch['code'][:, 0], 100 * videos + starts,
                                  err_msg=f'step {s}')


def test_train_hosts_check_their_index():
  with pytest.raises(ValueError, match='process_index < process_count'):
    pipeline.train_batches(FakeSource([6] * 4), batch_size=2, clip_length=2,
                           seed=0, process_index=2, process_count=2)


def test_short_video_raises():
  source = FakeSource([10, 3, 10])
  it = pipeline.train_batches(source, batch_size=3, clip_length=4, seed=0,
                              fields=('code',))
  with pytest.raises(ValueError, match='video 1 has 3 frames'):
    for _ in range(5):
      next(it)


def test_mismatched_time_axis_raises():
  class Bad(FakeSource):

    def __getitem__(self, index):
      item = super().__getitem__(index)
      item['slots'] = item['slots'][:-1]
      return item

  with pytest.raises(ValueError, match='time first'):
    next(pipeline.train_batches(Bad([5, 5]), batch_size=1, clip_length=2,
                                seed=0, fields=('code', 'slots')))


def _prefetch_threads() -> list[threading.Thread]:
  return [t for t in threading.enumerate()
          if t.name == 'slotformer-data-prefetch' and t.is_alive()]


def test_prefetch_thread_stops_when_consumer_stops():
  assert not _prefetch_threads()
  source = FakeSource([10] * 4)
  it = pipeline.train_batches(source, batch_size=2, clip_length=2, seed=0,
                              prefetch=2)
  next(it)
  next(it)
  assert len(_prefetch_threads()) == 1
  it.close()
  assert not _prefetch_threads()
  reads = source.reads
  # Dropping the iterator without close() also stops the thread.
  it = pipeline.train_batches(source, batch_size=2, clip_length=2, seed=0)
  next(it)
  del it
  gc.collect()
  assert not _prefetch_threads()
  # The producer stays at most `prefetch` + 1 batches ahead.
  assert source.reads - reads <= (2 + 1 + 1) * 2


def test_prefetch_error_reaches_consumer():
  source = FakeSource([10] * 3, fail_at=2)
  it = pipeline.train_batches(source, batch_size=3, clip_length=2, seed=0)
  with pytest.raises(RuntimeError, match='broken record 2'):
    next(it)
  assert not _prefetch_threads()


def test_eval_batches_padding_and_mask():
  source = FakeSource([9, 8, 10, 12, 9, 8, 11, 9, 10, 8])
  batches = list(pipeline.eval_batches(source, batch_size=4, num_frames=8,
                                       fields=('video', 'code')))
  assert len(batches) == 3
  for batch in batches:
    assert batch['video'].shape == (4, 8, 2, 2, 3)
    assert batch['mask'].dtype == np.bool_ and batch['index'].shape == (4,)
  np.testing.assert_array_equal(batches[-1]['mask'], [True, True, False, False])
  np.testing.assert_array_equal(batches[-1]['index'], [8, 9, 9, 9])
  index = np.concatenate([b['index'][b['mask']] for b in batches])
  np.testing.assert_array_equal(index, np.arange(10))
  for batch in batches:
    videos, frames = _decode(batch['code'])
    np.testing.assert_array_equal(videos[:, 0], batch['index'])
    assert (frames == np.arange(8)).all()


def test_eval_batches_all_frames_and_errors():
  same = FakeSource([6] * 5)
  batch = next(pipeline.eval_batches(same, batch_size=2, fields=('code',)))
  assert batch['code'].shape == (2, 6)
  mixed = FakeSource([6, 7])
  with pytest.raises(ValueError, match='num_frames'):
    next(pipeline.eval_batches(mixed, batch_size=2, fields=('code',)))
  with pytest.raises(ValueError, match='fewer than num_frames'):
    next(pipeline.eval_batches(mixed, batch_size=2, num_frames=7,
                               fields=('code',)))


def test_eval_sharding_disjoint_complete_and_lockstep():
  source = FakeSource([5] * 11)
  per_host, counts = [], []
  for p in range(4):
    batches = list(pipeline.eval_batches(source, batch_size=2,
                                         fields=('code',), process_index=p,
                                         process_count=4, max_videos=10))
    counts.append(len(batches))
    per_host.append([int(i) for b in batches for i in b['index'][b['mask']]])
    assert all(i % 4 == p for i in per_host[-1])
  assert len(set(counts)) == 1  # same number of steps on every host
  flat = sorted(itertools.chain(*per_host))
  assert flat == list(range(10))  # disjoint and complete (max_videos=10)


# --- sources -----------------------------------------------------------------

TINY = SyntheticConfig(resolution=(32, 32), num_frames=8, num_train=4,
                       num_val=2, num_test=2)


def _data_config(root: Path, **overrides) -> ml_collections.ConfigDict:
  """A run's data section (every field at its default) for the small
  embedded dataset under `root`, with `overrides`."""
  fields = dict(
      name='synthetic', data_dir=str(root), resolution=(32, 32), num_frames=8,
      min_objects=3, max_objects=5, seed=0, num_train=4, num_val=2,
      num_test=2, num_workers=1)
  fields.update(overrides)
  return data_section(**fields)


@pytest.fixture(scope='module')
def data_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
  root = tmp_path_factory.mktemp('data')
  data_stage.prepare_dataset(_data_config(root))  # builds the cache
  return root


def test_synthetic_source_through_the_pipeline(data_root):
  source = datasets.get_video_source(_data_config(data_root), 'train')
  assert len(source) == 4
  item = source[3]
  assert item['video'].shape == (8, 32, 32, 3) and item['video'].dtype == np.uint8
  assert item['num_objects'].dtype == np.int32
  np.testing.assert_array_equal(item['video'],
                                synthetic.generate_video(TINY, 'train', 3)['video'])
  with pytest.raises(IndexError):
    source[4]
  fields = ('video', 'segmentations', 'boxes', 'visible')
  batch = next(pipeline.train_batches(source, batch_size=3, clip_length=4,
                                      seed=0, fields=fields, prefetch=0))
  assert batch['video'].shape == (3, 4, 32, 32, 3)
  assert batch['segmentations'].shape == (3, 4, 32, 32)
  assert batch['boxes'].shape == (3, 4, 6, 4) and batch['visible'].dtype == bool
  val = datasets.get_video_source(_data_config(data_root), 'val')
  batches = list(pipeline.eval_batches(val, batch_size=3, num_frames=5))
  assert len(batches) == 1  # 2 videos: one batch of 2, not of 3
  np.testing.assert_array_equal(batches[0]['mask'], [True, True])
  assert batches[0]['video'].shape == (2, 5, 32, 32, 3)


@pytest.mark.parametrize('name', sorted(
    name for name, dataset in datasets.DATASETS.items()
    if isinstance(dataset, datasets.Converted)))
def test_missing_real_dataset_error_names_the_path(tmp_path, name):
  config = _data_config(tmp_path, name=name)
  with pytest.raises(FileNotFoundError) as error:
    datasets.get_video_source(config, 'train')
  message = str(error.value)
  assert str(tmp_path / name) in message
  # MOVi: one converter for every variant (--dataset=movi).
  command = 'movi' if name.startswith('movi_') else name
  assert f'python -m slotformer_jax.data.prepare --dataset={command} ' in (
      message)


def test_prepared_real_dataset_is_opened(data_root, tmp_path):
  # Stand-in for a converted dataset: any array_record TFDS folder.
  built = next((data_root / 'synthetic_obj3d').glob('*/2.0.0'))
  target = tmp_path / 'clevrer' / 'clevrer' / 'default' / '1.0.0'
  shutil.copytree(built, target)
  source = datasets.get_video_source(_data_config(tmp_path, name='clevrer'),
                                    'test')
  assert len(source) == 2 and source[1]['video'].shape == (8, 32, 32, 3)
  with pytest.raises(ValueError, match='64x64'):
    datasets.get_video_source(
        _data_config(tmp_path, name='clevrer', resolution=(64, 64)), 'test')
  with pytest.raises(ValueError, match='no split'):
    datasets.get_video_source(_data_config(tmp_path, name='clevrer'), 'dev')


def test_unknown_dataset_name(tmp_path):
  with pytest.raises(ValueError, match='Unknown dataset'):
    datasets.get_video_source(_data_config(tmp_path, name='mnist'), 'train')


def test_default_data_dir(monkeypatch, tmp_path):
  monkeypatch.setenv(sources.DATA_DIR_ENV, str(tmp_path))
  assert sources.default_data_dir() == tmp_path
  monkeypatch.delenv(sources.DATA_DIR_ENV)
  assert sources.default_data_dir() == Path.home() / '.cache' / 'slotformer_jax'


def test_clip_source_starts_each_clip_at_its_frame():
  source = FakeSource([10, 12])
  clips = pipeline.ClipSource(source, [(1, 3), (0, 0), (1, 5)],
                              time_fields=('code', 'slots'))
  assert len(clips) == 3
  batch = next(iter(pipeline.eval_batches(
      clips, batch_size=3, fields=('code', 'slots'), num_frames=4)))
  videos, frames = _decode(batch['code'])
  np.testing.assert_array_equal(videos[:, 0], [1, 0, 1])
  np.testing.assert_array_equal(frames, [[3, 4, 5, 6], [0, 1, 2, 3],
                                         [5, 6, 7, 8]])
  np.testing.assert_array_equal(batch['slots'][..., 0, 0], batch['code'])
  assert clips[0]['num_objects'] == 1  # non-time entries pass through


def test_clevrer_evaluation_clips_skip_entering_objects():
  from slotformer_jax.datasets import clevrer as clevrer_clips  # pylint: disable=g-import-not-at-top
  # evaluation.clips='clevrer' through the registry, as evaluation finds it.
  rule = datasets.clip_rule('clevrer')
  burn_in, rollout, stride, length = 4, 3, 2, 40
  span = (burn_in + rollout - 1) * stride  # 12 full-rate frames
  seen = clevrer_clips.MIN_BURN_IN_FRAMES_VISIBLE
  # Video 0: every object visible from the start -> the first start of each
  # half-span block. Video 1: an object enters at frame 5, so the clips in
  # which it would be seen in fewer than `seen` burn-in frames are dropped.
  calm = np.ones((length, 2), bool)
  entering = calm.copy()
  entering[:5, 1] = False
  videos = [{'in_view': calm, 'has_annotations': np.bool_(True)},
            {'in_view': entering, 'has_annotations': np.bool_(True)}]
  clips = rule(videos, 2, burn_in, rollout, stride)
  assert [s for v, s in clips if v == 0] == list(
      range(0, length - span, span // 2))
  late_entry = lambda start: (start + (burn_in - seen) * stride < 5
                              <= start + span)
  entering_starts = [s for v, s in clips if v == 1]
  assert entering_starts and not any(map(late_entry, entering_starts))
  assert late_entry(0) and entering_starts[0] == min(
      s for s in range(length - span) if not late_entry(s))
  with pytest.raises(ValueError, match="'val' split"):
    rule(
        [{'in_view': calm, 'has_annotations': np.bool_(False)}], 1, burn_in,
        rollout, stride)


def test_host_batches_give_every_host_the_same_number_of_batches():
  plans = [list(pipeline.host_batches(3, 2, p, 5)) for p in range(5)]
  assert {len(plan) for plan in plans} == {1}
  seen = sorted(int(i) for plan in plans for indices, valid in plan
                for i in indices[valid])
  assert seen == [0, 1, 2]
  # Hosts 3 and 4 have no item at all: padded with item 0, none valid.
  for p in (3, 4):
    (indices, valid), = plans[p]
    assert indices.tolist() == [0] and not valid.any()


@pytest.mark.parametrize('items,batch,hosts,devices,plan', [
    (2, 16, 1, 1, (1, 2)),     # a 2-video split: one batch of 2
    (2, 16, 1, 4, (1, 4)),     # ... rounded up to the host's devices
    (16, 16, 1, 1, (1, 16)),
    (17, 16, 1, 1, (2, 9)),    # 18 slots for 17 videos, not 32
    (17, 16, 1, 4, (2, 12)),
    (10, 2, 4, 1, (2, 2)),     # 3 per host
    (0, 8, 1, 1, (0, 8)),
])
def test_host_batch_plan_pads_less_than_a_device_row_per_batch(
    items, batch, hosts, devices, plan):
  assert pipeline.host_batch_plan(items, batch, hosts, devices) == plan
  num_batches, size = plan
  per_host = -(-items // hosts)
  assert num_batches * size >= per_host
  assert num_batches * size - per_host < max(1, num_batches * devices)
  assert size % devices == 0 and size <= batch


def test_host_batch_plan_refuses_a_batch_that_does_not_split():
  with pytest.raises(ValueError, match='not a multiple of 4'):
    pipeline.host_batch_plan(8, 6, 1, 4)


def test_encoding_videos_on_a_host_without_any(monkeypatch):
  """More processes than videos: the host without a video still runs the
  same batches and chunks (for the collectives) and yields nothing."""
  import jax  # pylint: disable=g-import-not-at-top
  import jax.numpy as jnp  # pylint: disable=g-import-not-at-top
  from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
  from slotformer_jax import inference  # pylint: disable=g-import-not-at-top
  from slotformer_jax.runtime import sharding  # pylint: disable=g-import-not-at-top
  source = [{'video': np.full((5, 2, 2, 3), 7, np.uint8)}]
  mesh = jax.sharding.Mesh(np.array(jax.devices()[:1]), ('data',))
  calls = []

  def encode(batch_index, chunk, frames, carry):
    calls.append((batch_index, chunk, frames.shape))
    return jnp.asarray(frames, jnp.float32)[..., 0], carry

  # Process 1 of 2 (the one video belongs to process 0); the collectives of
  # a real 2-process run are stood in for by this process's own arrays.
  monkeypatch.setattr(jax, 'process_index', lambda: 1)
  monkeypatch.setattr(jax, 'process_count', lambda: 2)
  monkeypatch.setattr(multihost_utils, 'process_allgather',
                      lambda tree, tiled=False: jax.tree.map(np.asarray, tree))
  monkeypatch.setattr(sharding, 'to_global_batch',
                      lambda batch, mesh: batch)
  out = list(inference.encode_videos(source, encode, chunk_length=2,
                                     batch_size=1, mesh=mesh, desc='test'))
  assert out == []
  assert calls == [(0, 0, (1, 2, 2, 2, 3)), (0, 1, (1, 2, 2, 2, 3)),
                   (0, 2, (1, 2, 2, 2, 3))]
