"""OBJ3D: fixtures in the published layout -> convert -> read back.

Also covers what every converter shares (``writer.py``): resuming an
interrupted conversion, multi-host conversion where each host reads only its
shards, parallel worker processes, and a config running the pipeline stages
on converted data.
"""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import ml_collections
import numpy as np
import pytest

import dataset_fixtures as fx
from slotformer_jax.datasets.base import Conversion
from slotformer_jax import datasets
from slotformer_jax.datasets import obj3d
from slotformer_jax.data import pipeline
from slotformer_jax.data import prepare
from slotformer_jax.data import sources
from slotformer_jax.data.write import convert as writer
from pipeline_helpers import slots_of
from pipeline_helpers import run_stage
from dataset_fixtures import data_section

FRAMES = 10   # frames per fixture video (OBJ3D: 100)
KEEP = 6      # --num_frames (OBJ3D: the first 50)
SRC = 24      # fixture frame size (OBJ3D: 64x64)
RES = 16      # converted resolution
# Folder names sort numerically, not as text: '2' before '10'.
TRAIN_VIDEOS = ('0', '1', '2', '10')


def frame_level(video: int, t: int) -> int:
  """Grey level of frame t (1-based, as the file names) of a video."""
  return 8 * t + 3 * video


def write_video(folder: Path, video: int, *, frames: int = FRAMES,
                alpha: bool = False) -> None:
  for t in range(1, frames + 1):
    image = np.full((SRC, SRC, 4 if alpha else 3), frame_level(video, t),
                    np.uint8)
    image[:4, :4, :3] = (255, 0, 0)   # a red corner, to check channel order
    if alpha:
      image[..., 3] = 7   # dropped, not composited
    fx.write_png(folder / obj3d.FRAME_TEMPLATE.format(t), image)


def make_source(base: Path) -> Path:
  root = base / 'OBJ3D'
  for number in TRAIN_VIDEOS:
    write_video(root / 'train' / number, int(number), alpha=number == '1')
  for split, numbers in (('val', ('0', '1')), ('test', ('0',))):
    for number in numbers:
      write_video(root / split / number, 20 + int(number))
  return root


def convert_args(root: Path, data_dir: Path, *extra: str) -> list[str]:
  return ['--dataset=obj3d', f'--source={root}', f'--data_dir={data_dir}',
          f'--resolution={RES}', f'--num_frames={KEEP}', '--num_workers=1',
          '--no_progress', *extra]


def data_config(data_dir: Path, **extra) -> ml_collections.ConfigDict:
  return data_section(name='obj3d', data_dir=str(data_dir),
                      resolution=(RES, RES), **extra)


@pytest.fixture(scope='module')
def converted(tmp_path_factory):
  base = tmp_path_factory.mktemp('obj3d')
  root = make_source(base)
  assert prepare.main(convert_args(root, base / 'data')) == 0
  return root, base / 'data'


def test_shapes_frame_selection_and_order(converted):
  _, data_dir = converted
  train = datasets.get_video_source(data_config(data_dir), 'train')
  assert len(train) == len(TRAIN_VIDEOS)
  for index, number in enumerate(TRAIN_VIDEOS):
    item = train[index]
    assert str(item['video_name'].item(), 'utf-8') == number
    video = item['video']
    assert video.shape == (KEEP, RES, RES, 3) and video.dtype == np.uint8
    # test_1 .. test_KEEP in order, resized (flat regions keep their level).
    np.testing.assert_allclose(
        video[:, -1, -1].astype(float).mean(-1),
        [frame_level(int(number), t) for t in range(1, KEEP + 1)], atol=1)
    np.testing.assert_array_equal(video[:, 0, 0], [[255, 0, 0]] * KEEP)
  # The RGBA video: alpha dropped without compositing.
  assert train[1]['video'][0, -1, -1].tolist() == [frame_level(1, 1)] * 3
  assert [len(datasets.get_video_source(data_config(data_dir), s))
          for s in ('val', 'test')] == [2, 1]
  # OBJ3D has no masks or boxes.
  assert 'segmentations' not in train[0]


def test_channel_order_and_training_batches(converted):
  _, data_dir = converted
  bgr = datasets.get_video_source(data_config(data_dir, channel_order='bgr'),
                                 'train')
  np.testing.assert_array_equal(bgr[0]['video'][0, 0, 0], [0, 0, 255])
  batch = next(pipeline.train_batches(
      datasets.get_video_source(data_config(data_dir), 'train'), batch_size=3,
      clip_length=3, seed=0, frame_stride=2, prefetch=0))
  assert batch['video'].shape == (3, 3, RES, RES, 3)
  steps = np.diff(batch['video'][:, :, -1, -1].astype(float).mean(-1), axis=1)
  np.testing.assert_allclose(steps, 16, atol=1)   # 2 frames x 8 levels


def test_bad_inputs_are_skipped_and_reported(tmp_path, capsys):
  root = make_source(tmp_path)
  train = root / 'train'
  write_video(train / '3', 3, frames=KEEP - 1)                 # too short
  write_video(train / '4', 4)
  (train / '4' / 'test_2.png').write_bytes(b'\x89PNG\r\n\x1a\n broken')
  write_video(train / '5', 5)
  fx.write_png(train / '5' / 'test_3.png', np.zeros((SRC, SRC + 2, 3),
                                                    np.uint8))  # other size
  args = convert_args(root, tmp_path / 'data', '--splits=train',
                      '--videos_per_shard=3')
  assert prepare.main(args) == 1    # 3 of 7 skipped: more than 5 %
  err = capsys.readouterr().err
  assert 'Too many videos could not be converted' in err
  assert 'test_6.png is missing' in err
  result = prepare.run(prepare.build_parser().parse_args(
      args + ['--max_skip_fraction=0.5']))
  assert result.complete and result.num_examples == {'train': 4}
  assert result.skip_counts() == {'train': {
      'truncated_video': 1, 'unreadable_frame': 1, 'frame_size_mismatch': 1}}
  assert 'Skipped 3 videos' in writer.summary(result)
  report = json.loads((result.dataset_dir / writer.REPORT_FILE).read_text())
  assert sorted(s['key'] for s in report['skipped']) == ['3', '4', '5']
  names = datasets.get_video_source(data_config(tmp_path / 'data'), 'train')
  assert [str(names[i]['video_name'].item(), 'utf-8')
          for i in range(4)] == list(TRAIN_VIDEOS)


def test_missing_folders_name_the_layout(tmp_path, capsys):
  root = make_source(tmp_path)
  (root / 'val').rename(tmp_path / 'val_elsewhere')
  assert prepare.main(convert_args(root, tmp_path / 'data')) == 1
  err = capsys.readouterr().err
  assert f'{root / "val"} not found' in err
  assert 'test_1.png ... test_100.png' in err   # the layout is shown
  (root / 'val').mkdir()
  with pytest.raises(FileNotFoundError, match='has no video folders'):
    obj3d.discover(root, 'val', obj3d.Options())
  assert prepare.main(convert_args(tmp_path / 'nowhere', tmp_path / 'd')) == 1
  assert 'is not a folder' in capsys.readouterr().err


def _spec_and_jobs(root: Path) -> tuple[Conversion,
                                        dict[str, list[obj3d.VideoJob]]]:
  options = obj3d.Options(resolution=(RES, RES), num_frames=KEEP)
  spec = obj3d.DATASET.spec(options, root)
  return spec, {'train': obj3d.discover(root, 'train', options)}


class _Recorder:
  """A picklable convert_fn that records (or interrupts at) the videos."""

  def __init__(self, convert_fn, stop_at: str | None = None):
    self.convert_fn = convert_fn
    self.stop_at = stop_at
    self.seen: list[str] = []

  def __call__(self, job):
    if job.key == self.stop_at:
      raise KeyboardInterrupt
    self.seen.append(job.key)
    return self.convert_fn(job)


def test_resume_after_interruption(tmp_path):
  root = make_source(tmp_path)
  spec, jobs = _spec_and_jobs(root)
  interrupted = _Recorder(spec.convert_fn, stop_at='10')
  with pytest.raises(KeyboardInterrupt):
    writer.convert(spec.__class__(**{**spec.__dict__,
                                     'convert_fn': interrupted}),
                   jobs, tmp_path / 'data', num_workers=1, videos_per_shard=2,
                   progress=False)
  assert interrupted.seen == ['0', '1', '2']   # shard 0 done, shard 1 not
  dataset_dir = spec.dataset_dir(tmp_path / 'data')
  assert not (dataset_dir / 'dataset_info.json').exists()
  with pytest.raises(FileNotFoundError):
    sources.open_prepared_dataset(tmp_path / 'data' / 'obj3d', 'train')
  resumed = _Recorder(spec.convert_fn)
  result = writer.convert(
      spec.__class__(**{**spec.__dict__, 'convert_fn': resumed}), jobs,
      tmp_path / 'data', num_workers=1, videos_per_shard=2, progress=False)
  assert resumed.seen == ['2', '10']    # only the unfinished shard
  assert result.complete and result.num_examples == {'train': 4}
  # Resuming with other inputs would mix datasets: refused.
  (dataset_dir / 'dataset_info.json').unlink()
  with pytest.raises(writer.ConversionError, match='list of input videos'):
    writer.convert(spec, {'train': jobs['train'][:3]}, tmp_path / 'data',
                   num_workers=1, videos_per_shard=2, progress=False)


def test_multi_host_conversion_reads_only_own_shards(tmp_path):
  root = make_source(tmp_path)
  spec, jobs = _spec_and_jobs(root)
  seen = {}
  for host in (0, 1):
    recorder = _Recorder(spec.convert_fn)
    result = writer.convert(
        spec.__class__(**{**spec.__dict__, 'convert_fn': recorder}), jobs,
        tmp_path / 'data', num_workers=1, videos_per_shard=1,
        process_index=host, process_count=2, progress=False)
    seen[host] = recorder.seen
    # Host 0 finishes first and cannot write the metadata yet.
    assert result.complete == (host == 1)
  assert seen == {0: ['0', '2'], 1: ['1', '10']}
  source = datasets.get_video_source(data_config(tmp_path / 'data'), 'train')
  assert [str(source[i]['video_name'].item(), 'utf-8')
          for i in range(len(source))] == list(TRAIN_VIDEOS)


def test_parallel_workers_match_serial(tmp_path, converted):
  root, serial_dir = converted
  assert prepare.main(convert_args(root, tmp_path / 'data', '--splits=train',
                                   '--num_workers=2',
                                   '--videos_per_shard=2')) == 0
  serial = datasets.get_video_source(data_config(serial_dir), 'train')
  parallel = datasets.get_video_source(data_config(tmp_path / 'data'), 'train')
  for i in range(len(serial)):
    np.testing.assert_array_equal(parallel[i]['video'], serial[i]['video'])
  # Running the finished conversion again converts nothing.
  result = prepare.run(prepare.build_parser().parse_args(convert_args(
      root, tmp_path / 'data', '--splits=train', '--videos_per_shard=2')))
  assert result.complete and result.videos_processed == 0


# ----------------------------------------------------------------------------
# configs/obj3d.py on converted data
# ----------------------------------------------------------------------------

CONFIGS = Path(__file__).resolve().parents[2] / 'configs'


def tiny_obj3d_config(data_dir: Path) -> ml_collections.ConfigDict:
  """configs/obj3d.py with tiny overrides (what --config.<field> would set)."""
  spec = importlib.util.spec_from_file_location('obj3d_config',
                                                CONFIGS / 'obj3d.py')
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  config = module.get_config()
  config.data.data_dir = str(data_dir)
  config.data.resolution = (RES, RES)
  savi = config.savi
  savi.num_slots, savi.slot_size = 3, 16
  savi.encoder.features, savi.encoder.strides = (8, 8), (1, 1)
  savi.encoder.output_size = 16
  savi.slot_attention.mlp_size = 16
  savi.predictor.num_layers, savi.predictor.num_heads = 1, 2
  savi.predictor.mlp_size = 16
  savi.predictor.kind, savi.predictor.lstm_size = 'transformer', 0
  savi.decoder.features, savi.decoder.kernel_size = (8,), 3
  savi.batch_size, savi.clip_length = 4, 2
  savi.num_train_steps = savi.log_every = savi.checkpoint_every = 1
  dynamics = config.slotformer
  dynamics.burn_in, dynamics.rollout = 2, 1
  dynamics.embed_dim, dynamics.num_layers, dynamics.num_heads = 16, 1, 2
  dynamics.image_loss_weight = 0.0
  dynamics.batch_size = 4
  dynamics.num_train_steps = dynamics.log_every = 1
  dynamics.checkpoint_every = 1
  config.extraction.batch_size, config.extraction.chunk_length = 4, KEEP
  return config


def test_config_fields_select_conversion_and_channel_order(converted,
                                                           tmp_path):
  root, _ = converted
  data_dir = tmp_path / 'data'
  # Two conversions of the same videos at the same resolution.
  assert prepare.main(convert_args(root, data_dir, '--splits=train')) == 0
  assert prepare.main(convert_args(root, data_dir, '--splits=train',
                                   '--limit=2')) == 0
  config = tiny_obj3d_config(data_dir)
  config.lock()   # as main.py's --config flag: only existing fields
  with pytest.raises(ValueError, match='data.prepared_config'):
    datasets.get_video_source(config.data, 'train')
  config.data.prepared_config = obj3d.Options(
      resolution=(RES, RES), num_frames=KEEP).config_name
  config.data.channel_order = 'bgr'
  source = datasets.get_video_source(config.data, 'train')
  assert len(source) == len(TRAIN_VIDEOS)
  np.testing.assert_array_equal(source[0]['video'][0, 0, 0], [0, 0, 255])
  config.data.prepared_config += '_first2'
  assert len(datasets.get_video_source(config.data, 'train')) == 2


def test_obj3d_config_runs_the_pipeline_on_converted_data(converted, tmp_path):
  # Imported here: the other tests need no JAX.
  from slotformer_jax.runtime import sharding  # pylint: disable=g-import-not-at-top
  _, data_dir = converted
  config = tiny_obj3d_config(data_dir)
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  run_stage(config, workdir, mesh, 'train_savi')
  run_stage(config, workdir, mesh, 'extract_slots')
  for split, count in (('train', 4), ('val', 2), ('test', 1)):
    source = slots_of(config, workdir, split, ('video',))
    assert len(source) == count
    item = source[0]
    assert item['slots'].shape == (KEEP, 3, 16)
    assert item['video'].shape == (KEEP, RES, RES, 3)
  run_stage(config, workdir, mesh, 'train_slotformer')
  assert os.listdir(os.path.join(workdir, 'slotformer', 'checkpoints'))


@pytest.mark.parametrize('kind', ['fifo', 'dev_zero'])
def test_a_frame_that_is_no_regular_file_is_named_not_missing(
    tmp_path, kind):
  """Issue 61, case 10: a FIFO frame, or a link to /dev/zero, skipped the
  video as 'test_1.png is missing (8 frames, 8 needed)'; reading either
  must not block or run forever (the alarm fails the test instead)."""
  import signal  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import media  # pylint: disable=g-import-not-at-top
  from slotformer_jax.datasets import obj3d  # pylint: disable=g-import-not-at-top
  write_video(tmp_path / '7', 7)
  frame = tmp_path / '7' / 'test_1.png'
  os.remove(frame)
  if kind == 'fifo':
    os.mkfifo(frame)
  else:
    os.symlink('/dev/zero', frame)

  def fire(signum, stack):
    raise TimeoutError('blocked on a frame that is no regular file')
  previous = signal.signal(signal.SIGALRM, fire)
  signal.alarm(20)
  try:
    with pytest.raises(media.SkipVideo) as skipped:
      obj3d.convert_video(
          obj3d.VideoJob(key='7', folder=tmp_path / '7'),
          obj3d.Options(resolution=(RES, RES), num_frames=KEEP))
  finally:
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)
  message = str(skipped.value)
  assert 'missing' not in message, message
  assert ('is a FIFO, not a regular file' if kind == 'fifo'
          else 'is a character device, not a regular file') in message
