"""A folder of your own videos (datasets/videos.py): fixtures written here
with imageio (mp4, gif) and Pillow (a folder of png frames), next to the bad
files a real folder holds; converted by the data stage from
`config.data.source`, read back, and the tiny pipeline run on them."""

import dataclasses
import json
import logging
import os
import time
import warnings

import imageio.v2 as imageio
import numpy as np
import pytest
from PIL import Image

from pipeline_helpers import accept
from pipeline_helpers import check
from pipeline_helpers import load_config
from pipeline_helpers import prepare_data
from pipeline_helpers import run_stages
from pipeline_helpers import slots_of
from slotformer_jax import api
from slotformer_jax import datasets
from slotformer_jax import inference
from slotformer_jax import predict
from slotformer_jax.data import media
from slotformer_jax.datasets import base
from slotformer_jax.datasets import videos
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import UserError
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding

# The fixtures are written through imageio-ffmpeg, whose subprocess runs a
# preexec_fn (JAX warns of os.fork); the reader does not (checked below).
pytestmark = pytest.mark.filterwarnings('ignore:os.fork')
RESOLUTION = (16, 16)
NUM_FRAMES = 8


def moving_square(num_frames, height, width, seed):
  """uint8 [T, H, W, 3]: a red square crossing a gray floor."""
  rng = np.random.default_rng(seed)
  frames = np.full((num_frames, height, width, 3), 90, np.uint8)
  side = max(2, min(height, width) // 4)
  y = int(rng.integers(0, height - side))
  for t in range(num_frames):
    x = (t * 2 + int(rng.integers(0, 3))) % (width - side)
    frames[t, y:y + side, x:x + side] = (220, 50, 40)
  return frames


def write_mp4(path, frames):
  imageio.mimwrite(path, frames, fps=10, macro_block_size=1)


def write_unknown_codec(path):
  """An mp4 whose H.264 stream is tagged with a codec no one knows."""
  write_mp4(path, moving_square(8, 16, 16, 0))
  data = path.read_bytes() if hasattr(path, 'read_bytes') else open(
      path, 'rb').read()
  assert b'avc1' in data
  with open(path, 'wb') as f:
    f.write(data.replace(b'avc1', b'zzzz'))


def numbered_frames(count):
  """uint8 [count, 16, 16, 3]: frame i gray at 12 * i, told apart after a
  lossy codec by ``frame_numbers``."""
  return np.stack([np.full((16, 16, 3), 12 * i, np.uint8)
                   for i in range(count)])


def frame_numbers(frames):
  return [int(round(float(frame.mean()) / 12)) for frame in frames]


def write_pngs(folder, frames):
  os.makedirs(folder, exist_ok=True)
  for index, frame in enumerate(frames):
    Image.fromarray(frame).save(os.path.join(folder, f'frame_{index + 1}.png'))


def write_folder(root):
  """train/ val/ test/ of good videos, and bad files in train/. Returns the
  png frames of test/seq (at the stored resolution)."""
  train, val, test = (os.path.join(root, s) for s in videos.SPLITS)
  for folder in (train, val, test):
    os.makedirs(folder)
  for index in range(3):
    write_mp4(os.path.join(train, f'clip_{index}.mp4'),
              moving_square(12, 24, 32, index))
  imageio.mimwrite(os.path.join(train, 'loop.gif'),
                   moving_square(10, 20, 20, 7), duration=0.1)
  write_pngs(os.path.join(train, 'frames'), moving_square(9, 16, 16, 8))
  write_mp4(os.path.join(val, 'v.mp4'), moving_square(10, 16, 16, 9))
  imageio.mimwrite(os.path.join(val, 'w.gif'), moving_square(10, 16, 16, 10),
                   duration=0.1)
  seq = moving_square(NUM_FRAMES, 16, 16, 11)
  write_pngs(os.path.join(test, 'seq'), seq)
  write_mp4(os.path.join(test, 't.mp4'), moving_square(8, 32, 16, 12))
  # What a real folder holds besides: one line each, never a crash.
  open(os.path.join(train, 'empty.mp4'), 'wb').close()
  with open(os.path.join(train, 'notes.mp4'), 'w') as f:
    f.write('not a video\n')
  with open(os.path.join(train, 'clip_0.mp4'), 'rb') as f:
    data = f.read()
  with open(os.path.join(train, 'truncated.mp4'), 'wb') as f:
    f.write(data[:len(data) // 2])
  write_mp4(os.path.join(train, 'one_frame.mp4'), moving_square(1, 16, 16, 0))
  write_mp4(os.path.join(train, 'short.mp4'), moving_square(5, 16, 16, 0))
  write_unknown_codec(os.path.join(train, 'codec.mp4'))
  os.symlink('/etc/hostname', os.path.join(train, 'outside.mp4'))
  os.symlink('self.mp4', os.path.join(train, 'self.mp4'))
  os.symlink('..', os.path.join(train, 'up'))
  write_mp4(os.path.join(train, 'bell\x07\x1b[2J.mp4'),
            moving_square(4, 16, 16, 0))
  return seq


SKIPPED = {'empty.mp4': 'empty_file', 'notes.mp4': 'unreadable_video',
           'truncated.mp4': 'unreadable_video', 'one_frame.mp4': 'too_short',
           'short.mp4': 'too_short', 'codec.mp4': 'unsupported_codec',
           'outside.mp4': 'outside_source',
           'self.mp4': 'broken_symlink', 'up': 'symlinked_folder',
           'bell\\x07\\x1b[2J.mp4': 'too_short'}


def videos_config(source, data_dir):
  """configs/videos.py:tiny at 16x16, a few steps per stage."""
  config = load_config('videos', 'tiny')
  config.data.source = str(source)
  config.data.data_dir = str(data_dir)
  config.data.num_workers = 1
  config.data.resolution = RESOLUTION
  config.data.num_frames = NUM_FRAMES
  config.data.frame_stride = 1
  config.data.max_skip_fraction = 0.9
  config.savi.decoder.features = (8, 8)
  config.savi.encoder.features = (8, 8)
  config.savi.encoder.strides = (1, 1)
  config.savi.num_slots = 3
  config.savi.clip_length = 2
  config.savi.batch_size = 4
  config.savi.num_train_steps = config.slotformer.num_train_steps = 2
  config.savi.log_every = config.savi.checkpoint_every = 2
  config.slotformer.log_every = config.slotformer.checkpoint_every = 2
  config.slotformer.batch_size = 4
  config.extraction.batch_size = 4
  config.evaluation.batch_size = 4
  config.evaluation.metrics = ('psnr', 'ssim')
  config.evaluation.savi_metrics = True
  config.render.num_videos = 1
  config.explore.num_videos = 1
  return config


@pytest.fixture(scope='module')
def converted(tmp_path_factory):
  """(config, png frames of test/seq, log lines of the conversion)."""
  root = tmp_path_factory.mktemp('videos')
  seq = write_folder(root / 'source')
  config = videos_config(root / 'source', root / 'data')
  with _Lines() as handler:
    prepare_data(config)
  return config, seq, handler.lines


def name_of(example):
  name = np.asarray(example['video_name']).item()
  return name.decode() if isinstance(name, bytes) else name


class _Lines(logging.Handler):
  """The messages logged at INFO and above while it is entered."""

  def __init__(self):
    super().__init__(logging.INFO)
    self.lines = []

  def emit(self, record):
    self.lines.append(record.getMessage())

  def __enter__(self):
    root = logging.getLogger()
    self._level = root.level
    root.setLevel(logging.INFO)
    root.addHandler(self)
    return self

  def __exit__(self, *exc):
    root = logging.getLogger()
    root.removeHandler(self)
    root.setLevel(self._level)


def test_conversion_keeps_the_good_videos_and_names_each_bad_one(converted):
  config, _, lines = converted
  dataset = datasets.get('videos')
  folder = dataset.dataset_dir(config.data)
  with open(folder / 'conversion_report.json') as f:
    report = json.load(f)
  assert report['num_examples'] == {'train': 5, 'val': 2, 'test': 2}
  assert {s['key'].split('/', 1)[1]: s['reason']
          for s in report['skipped']} == SKIPPED
  skipped = [line for line in lines if line.startswith('Skipped ')]
  assert len(skipped) == len(SKIPPED)
  # Names are escaped where they are shown: no byte a terminal acts on.
  assert not any(ch in line for line in skipped for ch in '\x07\x1b\n')
  source = dataset.open(config.data, 'train')
  names = sorted(name_of(source[i]) for i in range(len(source)))
  assert names == ['train/clip_0.mp4', 'train/clip_1.mp4', 'train/clip_2.mp4',
                   'train/frames', 'train/loop.gif']
  assert source[0]['video'].shape == (NUM_FRAMES, *RESOLUTION, 3)


def test_png_frames_are_stored_bit_for_bit(converted):
  config, seq, _ = converted
  source = datasets.get('videos').open(config.data, 'test')
  stored = {name_of(source[i]): source[i]['video']
            for i in range(len(source))}
  np.testing.assert_array_equal(stored['test/seq'], seq)
  # The mp4 went through a lossy codec: close, not equal.
  assert stored['test/t.mp4'].shape == (NUM_FRAMES, *RESOLUTION, 3)


def test_a_second_data_stage_converts_nothing(converted, caplog):
  config, _, _ = converted
  with caplog.at_level(logging.INFO):
    prepare_data(config)
  assert not any('Converting' in r.getMessage() for r in caplog.records)


def test_hashed_splits_do_not_move_when_videos_are_added(tmp_path):
  options = videos.Options(resolution=RESOLUTION, num_frames=2,
                           val_fraction=0.25, test_fraction=0.25)
  for index in range(12):
    write_pngs(tmp_path / f'clip_{index}', moving_square(2, 16, 16, index))
  before = {split: [job.key for job in videos.discover(tmp_path, split,
                                                       options)]
            for split in videos.SPLITS}
  for index in range(12, 40):
    write_pngs(tmp_path / f'clip_{index}', moving_square(2, 16, 16, index))
  after = {split: [job.key for job in videos.discover(tmp_path, split,
                                                      options)]
           for split in videos.SPLITS}
  for split in videos.SPLITS:
    assert set(before[split]) <= set(after[split])
  assert sum(map(len, after.values())) == 40
  assert all(after.values())


def test_a_split_with_no_video_is_one_line_that_names_the_fix(tmp_path):
  write_pngs(tmp_path / 'train' / 'a', moving_square(2, 16, 16, 0))
  options = videos.Options(resolution=RESOLUTION, num_frames=2)
  assert [job.key for job in videos.discover(tmp_path, 'train', options)
          ] == ['train/a']
  with pytest.raises(base.ConversionError, match='add videos to val/'):
    videos.discover(tmp_path, 'val', options)


def test_frames_out_of_the_source_or_none_at_all_are_skipped(tmp_path):
  source = tmp_path / 'source'
  write_pngs(tmp_path / 'elsewhere', moving_square(2, 16, 16, 0))
  os.makedirs(source / 'linked')
  os.symlink(tmp_path / 'elsewhere' / 'frame_1.png',
             source / 'linked' / 'frame_1.png')
  os.makedirs(source / 'hidden')
  write_pngs(source / 'hidden', moving_square(1, 16, 16, 0))
  os.rename(source / 'hidden' / 'frame_1.png', source / 'hidden' / '.f.png')
  options = videos.Options(resolution=RESOLUTION, num_frames=1,
                           val_fraction=0, test_fraction=0)
  jobs = videos.discover(source, 'train', options)
  assert [job.key for job in jobs] == ['linked']  # a hidden frame: no video
  with pytest.raises(media.SkipVideo, match='outside_source'):
    videos.convert_video(jobs[0], options)


def test_a_frame_claiming_a_huge_size_is_refused_before_decoding(tmp_path):
  write_pngs(tmp_path / 'seq', moving_square(2, 16, 16, 0))
  path = tmp_path / 'seq' / 'frame_2.png'
  data = bytearray(path.read_bytes())
  data[16:24] = (10_000).to_bytes(4, 'big') * 2  # IHDR width, height
  path.write_bytes(bytes(data))
  options = videos.Options(resolution=RESOLUTION, num_frames=2)
  with pytest.raises(media.SkipVideo, match='10000x10000 pixels'):
    videos.read_video(tmp_path / 'seq', options)


def test_fit_crops_or_pads_keeping_the_aspect_ratio():
  frame = np.zeros((8, 16, 3), np.uint8)
  frame[:, :4] = 255  # a white left quarter
  cropped = videos.fit_frame(frame, (8, 8), 'crop')
  padded = videos.fit_frame(frame, (8, 8), 'pad')
  assert cropped.shape == padded.shape == (8, 8, 3)
  assert cropped[:, 0].min() == 0  # the white quarter was cut away
  np.testing.assert_array_equal(padded[:2], 0)  # black bars above ...
  np.testing.assert_array_equal(padded[-2:], 0)  # ... and below
  assert padded[3:5, 0].min() > 200  # the white quarter kept


def test_ffmpeg_pads_or_crops_a_wide_video(tmp_path):
  path = tmp_path / 'wide.mp4'
  write_mp4(path, moving_square(3, 24, 32, 0))  # gray floor, 4:3
  pad = videos.read_video(path, videos.Options(
      resolution=(16, 16), num_frames=3, fit='pad'))
  crop = videos.read_video(path, videos.Options(
      resolution=(16, 16), num_frames=3, fit='crop'))
  assert pad.shape == crop.shape == (3, 16, 16, 3)
  assert pad[:, :2].max() < 5 and pad[:, -2:].max() < 5  # black bars
  assert crop[:, :2].min() > 40  # the floor, no bar


def test_a_long_video_decodes_only_the_frames_kept(tmp_path):
  path = tmp_path / 'long.mp4'
  write_mp4(path, moving_square(60, 64, 64, 0))
  options = videos.Options(resolution=(16, 16), num_frames=5, frame_stride=3)
  with warnings.catch_warnings():
    warnings.simplefilter('error', RuntimeWarning)  # os.fork under JAX
    frames = videos.read_video(path, options)
  assert frames.shape == (5, 16, 16, 3)
  with pytest.raises(media.SkipVideo, match='too_slow'):
    videos.decode_file(path, options, timeout_s=0.0)


def test_a_codec_ffmpeg_cannot_decode_is_one_line_at_once(tmp_path):
  path = tmp_path / 'codec\x1b.mp4'
  write_unknown_codec(path)
  start = time.monotonic()
  with pytest.raises(media.SkipVideo) as error:
    videos.read_video(path, videos.Options(resolution=RESOLUTION))
  assert time.monotonic() - start < 10
  assert error.value.reason == 'unsupported_codec'
  assert 'no decoder' in error.value.message, error.value.message
  assert '\\x1b' in error.value.message
  assert not any(ch in error.value.message for ch in '\x1b\n')


def test_fps_resamples_an_mp4_and_a_gif_alike_before_the_stride(tmp_path):
  frames = numbered_frames(20)
  imageio.mimwrite(tmp_path / 'a.mp4', frames, fps=20, macro_block_size=1)
  Image.fromarray(frames[0]).save(
      tmp_path / 'a.gif', save_all=True, duration=50,  # ms: 20 fps
      append_images=[Image.fromarray(frame) for frame in frames[1:]])
  expected = {(0, 1): list(range(20)), (10, 1): list(range(0, 20, 2)),
              (10, 2): list(range(0, 20, 4)),
              # ffmpeg's fps filter: the last frame starting before each
              # step's midpoint.
              (7, 1): [1, 4, 7, 9, 12, 15, 18]}
  for (fps, stride), numbers in expected.items():
    options = videos.Options(resolution=(16, 16), num_frames=100, fps=fps,
                             frame_stride=stride)
    for name in ('a.mp4', 'a.gif'):
      got = videos.read_video(tmp_path / name, options)
      assert frame_numbers(got) == numbers, (name, fps, stride)
  # num_frames still bounds the frames decoded.
  assert len(videos.read_video(tmp_path / 'a.mp4', videos.Options(
      resolution=(16, 16), num_frames=3, fps=40))) == 3


def test_a_gif_without_durations_plays_at_10_fps(tmp_path):
  frames = numbered_frames(10)
  Image.fromarray(frames[0]).save(
      tmp_path / 'a.gif', save_all=True,
      append_images=[Image.fromarray(frame) for frame in frames[1:]])
  got = videos.read_video(tmp_path / 'a.gif', videos.Options(
      resolution=(16, 16), num_frames=100, fps=5))
  assert frame_numbers(got) == [0, 2, 4, 6, 8]


def test_a_folder_of_frames_has_no_rate_to_resample(tmp_path):
  write_pngs(tmp_path / 'seq', numbered_frames(4))
  with pytest.raises(media.SkipVideo, match='unknown_rate: .*data.fps=0'):
    videos.read_video(tmp_path / 'seq', videos.Options(
        resolution=(16, 16), num_frames=2, fps=10))


def test_data_fps_is_checked_before_any_work(tmp_path):
  config = videos_config(tmp_path, tmp_path / 'data')
  for good in (0, 12.5):
    config.data.fps = good
    check(config, ('prepare_data',))
  for bad in (-1, 5000, float('nan')):
    config.data.fps = bad
    with pytest.raises(ConfigError) as error:
      check(config, ('prepare_data',))
    message = str(error.value)
    assert message.count('data.fps must be a frame rate in [0, 1000]') == 1
    assert '\n' not in message
  assert videos.Options(fps=10).params != videos.Options().params
  # A folder converted before fps existed keeps its name.
  assert 'fps' not in videos.Options().params


def test_the_config_names_a_missing_source_in_one_line(tmp_path):
  config = videos_config(tmp_path / 'nowhere', tmp_path / 'data')
  with pytest.raises(ConfigError, match='is not a folder'):
    check(config, ('prepare_data',))
  config.data.source = None
  with pytest.raises(ConfigError, match='--config.data.source=/my/videos'):
    check(config, ('prepare_data',))
  config.data.source = str(tmp_path)
  with pytest.raises(UserError, match='no video file'):
    prepare_data(config)


@pytest.fixture(scope='module')
def trained(converted, tmp_path_factory):
  """(config, workdir, what each stage returned, log lines): the tiny
  pipeline on the converted folder, once for the tests below."""
  config, _, _ = converted
  workdir = tmp_path_factory.mktemp('run') / 'run'
  accept(config, workdir)  # config.json, as main writes it
  with _Lines() as handler:
    out = run_stages(config, workdir, sharding.make_mesh())
  return config, workdir, out, handler.lines


def test_the_tiny_pipeline_runs_on_the_folder(trained):
  _, workdir, out, lines = trained
  metrics = json.dumps(out['evaluate'])
  assert 'psnr' in metrics and 'ssim' in metrics and 'fg_ari' not in metrics
  assert 'copy_last' in metrics
  assert sum('no ground-truth masks' in line for line in lines) == 1
  assert (workdir / 'explore').is_dir() or any(
      'explore' in str(p) for p in workdir.rglob('*.html'))


def test_the_api_gives_the_stages_slots_and_rollouts(trained):
  config, workdir, _, _ = trained
  model = api.WorldModel.load(workdir)
  assert model.expected.resolution == RESOLUTION
  assert model.expected.fps == config.data.fps == 0
  run = Run.create(config, str(workdir), sharding.make_mesh())
  stage_slots = slots_of(config, workdir, 'test')
  videos_ = run.videos('test')
  dynamics = run.dynamics('slotformer')
  burn_in = config.slotformer.burn_in
  for index in range(len(videos_)):
    frames = videos_[index]['video']
    slots = model.encode(frames)
    np.testing.assert_allclose(slots, stage_slots[index]['slots'],
                               atol=2e-5, rtol=1e-5)
    rollout = model.rollout(slots[:burn_in], 3)
    expected = inference.rollout_slots(
        dynamics.params, stage_slots[index]['slots'][None, :burn_in],
        model=dynamics.module, num_steps=3)[0]
    np.testing.assert_allclose(rollout, expected, atol=2e-5, rtol=1e-5)
    decoded = model.decode(rollout)
    assert decoded.frames.shape == (3, *RESOLUTION, 3)
    assert decoded.frames.dtype == np.uint8
    assert decoded.masks.shape == (3, config.savi.num_slots, *RESOLUTION)
    np.testing.assert_allclose(decoded.masks.sum(1), 1, atol=1e-5)


def test_the_api_resizes_with_a_notice_or_refuses(trained, caplog):
  _, workdir, _, _ = trained
  big = moving_square(4, 32, 48, 0)
  with caplog.at_level(logging.WARNING):
    slots = api.WorldModel.load(workdir).encode(big)
  assert slots.shape[0] == 4
  # The notice, and nothing else: no orbax warning of a read-only folder.
  assert [r.getMessage()[:22] for r in caplog.records] == [
      'frames are 48x32, the ']
  with pytest.raises(UserError, match='frames are 48x32, the model reads'):
    api.WorldModel.load(workdir, on_mismatch='refuse').encode(big)
  with pytest.raises(UserError, match='uint8'):
    api.WorldModel.load(workdir).encode(big.astype(np.float32))


def test_the_api_reads_a_file_at_the_models_frame_rate(trained, tmp_path):
  _, workdir, _, _ = trained
  model = api.WorldModel.load(workdir)
  # As a model trained with data.fps=10 and data.frame_stride=1 reads.
  model.expected = dataclasses.replace(model.expected, fps=10.0)
  clip = tmp_path / 'clip.mp4'
  imageio.mimwrite(clip, numbered_frames(20), fps=20, macro_block_size=1)
  assert frame_numbers(model.read_video(clip)) == list(range(0, 20, 2))
  write_pngs(tmp_path / 'seq', numbered_frames(4))
  with pytest.raises(UserError, match='no frame rate'):
    model.read_video(tmp_path / 'seq')


def test_predict_draws_a_clip_that_is_not_in_the_folder(trained, tmp_path,
                                                       capsys):
  _, workdir, _, _ = trained
  clip = tmp_path / 'new clip.mp4'
  write_mp4(clip, moving_square(10, 40, 40, 99))
  out = tmp_path / 'out'
  assert predict.main([f'--workdir={workdir}', f'--video={clip}',
                       f'--out={out}', '--rollout=4']) == 0
  assert sorted(p.name for p in out.iterdir()) == [
      'explore', 'prediction.gif', 'prediction.png', 'slots.npz']
  page = (out / 'explore' / 'index.html').read_text()
  assert 'new clip.mp4' in page and 'freeze' in page
  strip = np.asarray(Image.open(out / 'prediction.png'))
  assert strip.ndim == 3 and strip.shape[1] > strip.shape[0]
  with Image.open(out / 'prediction.gif') as gif:
    assert gif.n_frames == 2 + 4
  with np.load(out / 'slots.npz') as saved:
    assert saved['predicted'].shape[0] == 4
  # A clip shorter than the burn-in, a file that is no video: one line.
  short = tmp_path / 'short.gif'
  imageio.mimwrite(short, moving_square(1, 16, 16, 0), duration=0.1)
  for bad in (short, tmp_path / 'nothing.mp4'):
    capsys.readouterr()
    assert predict.main([f'--workdir={workdir}', f'--video={bad}',
                         f'--out={tmp_path / "bad"}']) == 1
    err = capsys.readouterr().err
    assert err.startswith('error: ') and err.count('\n') == 1, err
  assert not (tmp_path / 'bad').exists()
