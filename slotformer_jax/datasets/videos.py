"""A folder of your own videos: the dataset, its layout and its conversion.

A video is a file of a known suffix (``VIDEO_SUFFIXES``: ffmpeg from
``imageio-ffmpeg``, GIFs by Pillow) or a folder of numbered png / jpg frames,
anywhere under ``config.data.source``. Splits are ``train/``, ``val/``,
``test/`` when present, else a stable hash of each relative path
(``split_of``). Each is resampled to ``fps`` frames per second (0: the
file's own rate), then keeps ``num_frames`` frames, every
``frame_stride``-th, cropped or padded to ``resolution``, decoded as a
stream; unusable files are
skipped, one escaped line each. Stored: ``video`` uint8 [num_frames, H, W, 3]
RGB and ``video_name``; no masks. The layout in full: docs/datasets.md,
"Your own videos".
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import os
import re
import subprocess
import tempfile
import threading
from collections.abc import Iterable
from collections.abc import Iterator
from pathlib import Path

import ml_collections
import numpy as np
import tensorflow_datasets as tfds
from PIL import Image
from PIL import ImageSequence

from slotformer_jax.data import media
from slotformer_jax.data import sources
from slotformer_jax.datasets import base
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import shown

NAME = 'videos'
SPLITS: tuple[str, ...] = ('train', 'val', 'test')
VIDEO_SUFFIXES = ('.mp4', '.m4v', '.webm', '.mov', '.avi', '.mkv')
GIF_SUFFIX = '.gif'
FRAME_SUFFIXES = ('.png', '.jpg', '.jpeg')
FITS = ('crop', 'pad')
# Seconds ffmpeg may take for one video before it is skipped ('too_slow').
DECODE_TIMEOUT_S = 300.0
# The highest data.fps (config/checks.py states the same rule).
MAX_FPS = 1000.0
FPS_RULE = "a frame rate in [0, 1000] (0: the file's own)"
# A GIF frame shorter than this (ms; often 0: no duration) plays for
# GIF_DEFAULT_MS, as browsers and ffmpeg's GIF reader play it.
GIF_MIN_MS = 20
GIF_DEFAULT_MS = 100
CONVERTER_VERSION = 1

LAYOUT = """\
<source>/**/<name>.mp4|.webm|.mov|.avi|.mkv|.m4v|.gif   (one video per file)
<source>/**/<folder>/<numbered frames>.png|.jpg        (one video per folder)
optional: <source>/train/, <source>/val/, <source>/test/ (else split by a hash
of each video's path, data.val_fraction / data.test_fraction)"""


@dataclasses.dataclass(frozen=True)
class Options(base.ConversionOptions):
  """Conversion parameters (``config.data`` fields of the same names).

  Attributes:
    resolution: (H, W) of the stored frames.
    num_frames: frames kept per video (after the stride).
    fps: resample each video to this many frames per second first (0: the
      file's own rate; a folder of frames has none and is skipped).
    frame_stride: then keep every n-th frame (2 halves 30 fps).
    fit: 'crop' (fill the frame, cut the centre) or 'pad' (black bars).
    val_fraction, test_fraction: shares of the videos hashed into val and
      test when the source has no split folders.
  """

  resolution: tuple[int, int] = (64, 64)
  num_frames: int = 32
  fps: float = 0.0
  frame_stride: int = 1
  fit: str = 'crop'
  val_fraction: float = 0.1
  test_fraction: float = 0.1
  version = CONVERTER_VERSION

  def __post_init__(self):
    super().__post_init__()
    fps = self.fps
    if (not isinstance(fps, (int, float)) or isinstance(fps, bool)
        or not 0 <= fps <= MAX_FPS):
      raise ValueError(f'fps must be {FPS_RULE}, got {fps!r}')
    object.__setattr__(self, 'fps', float(fps))
    if self.frame_stride < 1:
      raise ValueError(f'frame_stride must be >= 1, got {self.frame_stride}')
    if self.fit not in FITS:
      raise ValueError(f'fit must be one of {FITS}, got {self.fit!r}')
    if not (0 <= self.val_fraction and 0 <= self.test_fraction
            and self.val_fraction + self.test_fraction < 1):
      raise ValueError('val_fraction and test_fraction must be >= 0 with a '
                       f'sum below 1, got {self.val_fraction} and '
                       f'{self.test_fraction}')

  @property
  def params(self) -> dict[str, object]:
    params = super().params
    if not self.fps:  # the folders converted before fps existed stay found
      del params['fps']
    return params


@dataclasses.dataclass(frozen=True)
class VideoJob:
  """One video: a file (``kind`` 'file', 'gif') or a folder of frames
  ('frames'); 'folder_link' and 'link' are refused when converted."""

  key: str
  path: Path
  kind: str
  root: Path


def split_of(key: str, options: Options) -> str:
  """The split of a video (its path relative to the source) without split
  folders: a stable hash of the path, so adding videos moves no old one."""
  digest = hashlib.sha256(key.encode('utf-8', 'backslashreplace')).digest()
  draw = int.from_bytes(digest[:8], 'big') / 2.0**64
  if draw < options.test_fraction:
    return 'test'
  if draw < options.test_fraction + options.val_fraction:
    return 'val'
  return 'train'


def _kind(name: str) -> str | None:
  suffix = os.path.splitext(name)[1].lower()
  if suffix in VIDEO_SUFFIXES:
    return 'file'
  return 'gif' if suffix == GIF_SUFFIX else None


def _frame_files(folder: Path) -> list[Path]:
  names = [name for name in os.listdir(folder)
           if os.path.splitext(name)[1].lower() in FRAME_SUFFIXES
           and not name.startswith('.')]
  return [folder / name for name in sorted(names, key=media.natural_key)]


def _all_videos(root: Path) -> tuple[VideoJob, ...]:
  """Every video under ``root`` (resolved), in path order; symlinked folders
  are listed (to be refused), never entered."""
  jobs = []
  for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
    here = Path(dirpath)
    dirnames[:] = sorted((d for d in dirnames if not d.startswith('.')),
                         key=media.natural_key)
    relative = here.relative_to(root)
    for name in dirnames:
      if (here / name).is_symlink():
        jobs.append(VideoJob(shown((relative / name).as_posix(), 1000),
                             here / name, 'folder_link', root))
    if relative.parts and any(os.path.splitext(f)[1].lower() in FRAME_SUFFIXES
                              and not f.startswith('.') for f in filenames):
      jobs.append(VideoJob(shown(relative.as_posix(), 1000), here, 'frames',
                           root))
    for name in sorted(filenames, key=media.natural_key):
      kind = _kind(name)
      if kind is None or name.startswith('.'):
        continue
      if (here / name).is_symlink():
        kind = 'link'
      jobs.append(VideoJob(shown((relative / name).as_posix(), 1000),
                           here / name, kind, root))
  return tuple(sorted(jobs, key=lambda job: media.natural_key(job.key)))


def has_split_folders(source: Path) -> bool:
  return any((source / split).is_dir() for split in SPLITS)


def discover(source: Path, split: str, options: Options) -> list[VideoJob]:
  """The videos of ``split``, in path order.

  Raises:
    FileNotFoundError: the source holds no video at all.
    base.ConversionError: none falls in ``split`` (names the fix).
  """
  root = Path(os.path.realpath(source))
  everything = _all_videos(root)
  if not everything:
    raise base.layout_error('videos', LAYOUT, source, source / '<videos>',
                            ' (no video file or folder of frames)',
                            what='videos')
  if has_split_folders(root):
    jobs = [job for job in everything if job.key.split('/')[0] == split]
    fix = f'add videos to {split}/'
  else:
    jobs = [job for job in everything if split_of(job.key, options) == split]
    fix = (f'add videos, raise data.{split}_fraction, or sort them into '
           'train/ val/ test/ folders') if split != 'train' else (
               'lower data.val_fraction / data.test_fraction')
  if not jobs:
    raise base.ConversionError(
        f'no video of {shown(source)} ({len(everything)} found) is in split '
        f'{split!r}; {fix}')
  return jobs


# ----------------------------------------------------------------------------
# Decoding
# ----------------------------------------------------------------------------


def fit_frame(frame: np.ndarray, resolution: tuple[int, int], fit: str
              ) -> np.ndarray:
  """uint8 [h, w, 3] -> [H, W, 3], the aspect ratio kept: 'crop' scales
  to cover and keeps the centre, 'pad' scales to fit and adds black bars
  (Pillow's antialiased bilinear filter; identity at the same size)."""
  height, width = resolution
  h, w = frame.shape[:2]
  if (h, w) == (height, width):
    return np.ascontiguousarray(frame)
  scale = (max if fit == 'crop' else min)(height / h, width / w)
  size = (max(1, round(w * scale)), max(1, round(h * scale)))
  image = np.asarray(Image.fromarray(np.ascontiguousarray(frame)).resize(
      size, Image.BILINEAR))
  out = np.zeros((height, width, 3), np.uint8)
  top, left = (height - size[1]) // 2, (width - size[0]) // 2
  if fit == 'crop':
    return np.ascontiguousarray(image[-top:-top + height, -left:-left + width])
  out[top:top + size[1], left:left + size[0]] = image
  return out


def _ffmpeg_filter(options: Options) -> str:
  height, width = options.resolution
  steps = []
  if options.fps:  # resampled first: the frame shown at each 1/fps step
    steps.append(f'fps={options.fps:.12g}')
  if options.frame_stride > 1:
    steps.append(f'select=not(mod(n\\,{options.frame_stride}))')
  if options.fit == 'crop':
    steps.append(f'scale={width}:{height}:force_original_aspect_ratio='
                 f'increase:flags=bilinear,crop={width}:{height}')
  else:
    steps.append(f'scale={width}:{height}:force_original_aspect_ratio='
                 f'decrease:flags=bilinear,pad={width}:{height}:(ow-iw)/2:'
                 '(oh-ih)/2:black')
  return ','.join(steps)


# ffmpeg 6+: 'no decoder found for: none'; older: 'Decoder (codec none) not
# found for input stream'.
_NO_DECODER = re.compile(r'no decoder found|decoder \(codec .*\) not found',
                         re.IGNORECASE)


class _Deadline(threading.Timer):
  """A Timer that records whether it fired."""

  fired = False

  def run(self):
    self.finished.wait(self.interval)
    if not self.finished.is_set():
      self.fired = True
      self.function(*self.args, **self.kwargs)
    self.finished.set()


def decode_file(path: Path, options: Options, *, name: str = '',
                timeout_s: float = DECODE_TIMEOUT_S) -> np.ndarray:
  """uint8 [<= num_frames, H, W, 3]: the frames kept of a video file,
  scaled by ffmpeg as they are decoded (bounded memory); ffmpeg stops
  after the last one.

  Raises:
    media.SkipVideo: 'unsupported_codec' (ffmpeg has no decoder for its
      video stream), 'unreadable_video' (ffmpeg decodes no frame: names its
      last error line), 'too_slow' (more than ``timeout_s``).
  """
  import imageio_ffmpeg  # pylint: disable=g-import-not-at-top
  name = name or shown(path)
  height, width = options.resolution
  command = [imageio_ffmpeg.get_ffmpeg_exe(), '-nostdin', '-v', 'error',
             '-threads', '1', '-i', 'file:' + os.fspath(path.absolute()),
             '-an', '-sn', '-dn', '-vf', _ffmpeg_filter(options),
             '-fps_mode', 'passthrough', '-frames:v', str(options.num_frames),
             '-f', 'rawvideo', '-pix_fmt', 'rgb24', 'pipe:1']
  frame_bytes = height * width * 3
  frames = []
  with tempfile.TemporaryFile() as errors:
    # No preexec_fn: the child is started without running Python's fork
    # hooks (JAX warns about os.fork() in a threaded process otherwise).
    process = subprocess.Popen(command, stdin=subprocess.DEVNULL,
                               stdout=subprocess.PIPE, stderr=errors,
                               start_new_session=True)
    timer = _Deadline(timeout_s, process.kill)
    timer.start()
    try:
      while len(frames) < options.num_frames:
        raw = process.stdout.read(frame_bytes)
        if len(raw) < frame_bytes:
          break
        frames.append(np.frombuffer(raw, np.uint8).reshape(height, width, 3))
    finally:
      process.stdout.close()
      process.kill()
      process.wait()
      timer.cancel()
    if timer.fired:
      raise media.SkipVideo('too_slow', f'{name}: ffmpeg took more than '
                            f'{timeout_s:.0f} s')
    if not frames:
      errors.seek(0)
      lines = errors.read(4000).decode('utf-8', 'replace').strip().splitlines()
      codec = [line for line in lines if _NO_DECODER.search(line)]
      if codec:  # ffmpeg's last line is then 'Error opening output files'
        line = re.sub(r'^\[[^]]*\]\s*', '', codec[0])  # '[vist#0:0 @ 0x..]'
        raise media.SkipVideo('unsupported_codec', f'{name}: ffmpeg has no '
                              'decoder for its video stream '
                              f'({shown(line, 200)})')
      raise media.SkipVideo('unreadable_video', f'{name}: ' + shown(
          lines[-1] if lines else 'no frame could be decoded', 200))
  return np.stack(frames)


def at_rate(frames: Iterable[tuple[np.ndarray, float]], fps: float
            ) -> Iterator[np.ndarray]:
  """The frame shown at each 1/``fps`` step of (frame, duration in ms)
  pairs, as ffmpeg's ``fps`` filter picks it: frame i, starting at t_i,
  falls on step round(t_i * fps) (halves up), and each step shows the last
  frame that fell on it or before; as many steps as round(total * fps),
  at least one."""
  elapsed, step, previous = 0.0, 0, None
  for frame, duration_ms in frames:
    slot = math.floor(elapsed * fps / 1000 + 0.5)
    while previous is not None and step < slot:
      yield previous
      step += 1
    previous, elapsed = frame, elapsed + duration_ms
  if previous is None:
    return
  for _ in range(step, max(math.floor(elapsed * fps / 1000 + 0.5), 1)):
    yield previous


def _gif_frames(image: Image.Image) -> Iterator[tuple[np.ndarray, float]]:
  """(RGB frame, duration in ms) of each frame of a GIF, one at a time."""
  for frame in ImageSequence.Iterator(image):
    duration = frame.info.get('duration') or 0
    yield (np.asarray(frame.convert('RGB')),
           duration if duration >= GIF_MIN_MS else GIF_DEFAULT_MS)


def decode_gif(path: Path, options: Options, *, name: str = '') -> np.ndarray:
  """uint8 [<= num_frames, H, W, 3] of a GIF, one frame decoded at a time
  (resampled to ``options.fps`` by its frame durations: ``at_rate``).

  Raises:
    media.SkipVideo('unreadable_video'): not a GIF Pillow can decode, or
      larger than ``media.MAX_IMAGE_PIXELS`` per frame.
  """
  name = name or shown(path)
  frames = []
  try:
    with Image.open(path) as image:
      width, height = image.size
      if width * height > media.MAX_IMAGE_PIXELS:
        raise media.SkipVideo('unreadable_video', f'{name}: {width}x{height}'
                              ' pixels per frame is more than '
                              f'{media.MAX_IMAGE_PIXELS}')
      stream = _gif_frames(image)
      shown_frames = (at_rate(stream, options.fps) if options.fps
                      else (frame for frame, _ in stream))
      for index, frame in enumerate(shown_frames):
        if index % options.frame_stride:
          continue
        frames.append(fit_frame(frame, options.resolution, options.fit))
        if len(frames) == options.num_frames:
          break
  except media.SkipVideo:
    raise
  except Exception as error:  # pylint: disable=broad-except
    # Whatever a damaged or crafted file makes Pillow raise.
    raise media.SkipVideo('unreadable_video',
                          f'{name}: {shown(str(error), 200)}') from None
  if not frames:
    raise media.SkipVideo('unreadable_video', f'{name}: no frame')
  return np.stack(frames)


def decode_frames(folder: Path, options: Options, *, name: str = ''
                  ) -> np.ndarray:
  """uint8 [<= num_frames, H, W, 3] of a folder of numbered frames.

  Raises:
    media.SkipVideo: 'unknown_rate' (``options.fps`` set: frames have no
      rate), 'unreadable_frame' (a frame cannot be read: named).
  """
  if options.fps:
    raise media.SkipVideo('unknown_rate', f'{name or shown(folder)}: a '
                          'folder of frames has no frame rate to resample '
                          f'to fps {options.fps:g}: data.fps=0 reads it '
                          '(data.frame_stride thins it)')
  files = _frame_files(folder)[::options.frame_stride][:options.num_frames]
  if not files:
    raise media.SkipVideo('unreadable_video', f'{name or shown(folder)}: no '
                          'png or jpg frame')
  return np.stack([fit_frame(media.read_image(path), options.resolution,
                             options.fit) for path in files])


def _refused(job: VideoJob) -> media.SkipVideo | None:
  """Why a job is not read at all (None: it is)."""
  if job.kind == 'folder_link':
    return media.SkipVideo('symlinked_folder', f'{job.key}: a symlinked '
                           'folder is not followed (it could loop or lead '
                           'out of the source)')
  if job.kind == 'link':
    try:
      target = Path(os.path.realpath(job.path, strict=True))
    except (OSError, RuntimeError):
      return media.SkipVideo('broken_symlink', f'{job.key}: a symlink that '
                             'loops or leads nowhere')
    if not target.is_relative_to(job.root):
      return media.SkipVideo('outside_source', f'{job.key}: a symlink out of '
                             'the source folder')
  elif job.kind == 'frames':
    for path in _frame_files(job.path):
      target = Path(os.path.realpath(path))
      if path.is_symlink() and not target.is_relative_to(job.root):
        return media.SkipVideo('outside_source', f'{job.key}: frame '
                               f'{shown(path.name)} is a symlink out of the '
                               'source folder')
  elif job.path.stat().st_size == 0:
    return media.SkipVideo('empty_file', f'{job.key}: an empty file')
  return None


def read_video(path: Path, options: Options, name: str = '') -> np.ndarray:
  """uint8 [<= num_frames, H, W, 3]: the frames ``options`` keep of a video
  file, GIF or folder of frames (fewer when it is shorter).

  Raises:
    media.SkipVideo: it cannot be decoded (one line naming it).
  """
  name = name or shown(path)
  if path.is_dir():
    return decode_frames(path, options, name=name)
  if path.suffix.lower() == GIF_SUFFIX:
    return decode_gif(path, options, name=name)
  return decode_file(path, options, name=name)


def convert_video(job: VideoJob, options: Options) -> dict[str, object]:
  """One video -> its example.

  Raises:
    media.SkipVideo: refused (``_refused``), undecodable, or fewer than
      ``num_frames`` frames after the stride ('too_short').
  """
  refused = _refused(job)
  if refused is not None:
    raise refused
  video = read_video(job.path, options, job.key)
  if len(video) < options.num_frames:
    rate = f'fps {options.fps:g}, ' if options.fps else ''
    raise media.SkipVideo(
        'too_short', f'{job.key}: {len(video)} frames ({rate}frame_stride '
        f'{options.frame_stride}), {options.num_frames} needed '
        '(data.num_frames)')
  return {'video': video, 'video_name': job.key}


def features(options: Options) -> tfds.features.FeaturesDict:
  h, w = options.resolution
  return tfds.features.FeaturesDict({
      'video': base.tensor((options.num_frames, h, w, 3), np.uint8),
      'video_name': tfds.features.Text(),
  })


def describe(options: Options) -> str:
  rate = f'{options.fps:g} fps, ' if options.fps else ''
  return (f'A folder of videos: {options.num_frames} frames ({rate}every '
          f'{options.frame_stride}) at {options.resolution[0]}x'
          f'{options.resolution[1]}, {options.fit}, RGB.')


def conversion(options: Options, source: Path) -> base.Conversion:
  """The conversion of ``source`` with ``options``: its folder name hashes
  the source's resolved path too, so two folders of videos never share
  one."""
  params = {**options.params, 'source': os.path.realpath(source)}
  h, w = options.resolution
  return base.Conversion(
      name=NAME, config_name=base.digest_name(
          f'r{h}x{w}_t{options.num_frames}_s{options.frame_stride}', params),
      description=describe(options), params=params,
      features_fn=functools.partial(features, options),
      convert_fn=functools.partial(convert_video, options=options))


def options_of(data_config: ml_collections.ConfigDict) -> Options:
  """The conversion options a run's ``config.data`` asks for."""
  fields = {f.name for f in dataclasses.fields(Options)}
  values = {k: data_config[k] for k in fields if k in data_config}
  values['resolution'] = tuple(values.get('resolution', (64, 64)))
  if values.get('fps') is None:  # an unset placeholder: the file's own rate
    values.pop('fps', None)
  return Options(**values)


@dataclasses.dataclass(frozen=True)
class VideoFolder(base.Converted):
  """A converted dataset the data stage converts itself from
  ``config.data.source``, into the folder its options and source name."""

  def source_of(self, data_config: ml_collections.ConfigDict
                ) -> Path | None:
    source = data_config.get('source')
    return None if source is None else Path(source).expanduser()

  def options_of(self, data_config: ml_collections.ConfigDict) -> Options:
    return options_of(data_config)

  def config_problems(self, data_config: ml_collections.ConfigDict
                      ) -> list[str]:
    source = self.source_of(data_config)
    problems = []
    if source is None:
      problems.append('data.source must name your folder of videos: '
                      '--config.data.source=/my/videos')
    elif not source.is_dir():
      problems.append(f'data.source={shown(source)} is not a folder')
    try:
      options_of(data_config)
    except (ValueError, TypeError) as error:
      problems.append(f'data.{error}')
    return problems

  def num_frames(self, data_config: ml_collections.ConfigDict) -> int:
    return options_of(data_config).num_frames

  def conversion_command(self, data_config: ml_collections.ConfigDict) -> str:
    return (f'{super().conversion_command(data_config)} (or any command of '
            'the run with --config.data.source=/my/videos: its data stage '
            'converts them)')

  def dataset_dir(self, data_config: ml_collections.ConfigDict) -> Path:
    source = self.source_of(data_config)
    if source is None:
      return super().dataset_dir(data_config)
    spec = conversion(options_of(data_config), source)
    folder = spec.dataset_dir(sources.resolve_data_dir(data_config.data_dir))
    if not (folder / 'dataset_info.json').is_file():
      raise MissingInputError(
          f'the videos of {shown(source)} are not converted (expected '
          f'{folder}); the data stage converts them: run with '
          '--mode=prepare_data (or any mode)')
    return folder


DATASET = base.register(VideoFolder(
    names=(NAME,), label='videos', command=NAME, splits=SPLITS,
    layout=LAYOUT, features=functools.partial(features, Options()),
    options=Options, discover=discover, conversion=conversion,
    download='/my/videos'))
