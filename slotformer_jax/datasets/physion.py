"""Physion (NeurIPS 2021 benchmark): published layout and conversion.

Splits: ``train`` / ``val`` (the Training videos, for the dynamics),
``readout_train`` / ``readout_val`` (Readout Fitting), ``test`` (Testing).
Stored per video: ``video`` uint8 [T, H, W, 3] (the first T = min(150,
length) frames, RGB, the whole frame resized), ``label`` int32 (1: the red
agent touches the yellow patient, 0: not, -1: unlabelled), ``scenario``
int32 (index into SCENARIOS), ``bad_stimulus`` bool (left out by the
official evaluation), ``video_name``. The layout, label files and split
lists: docs/datasets.md, "Physion".
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import hashlib
import io
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import media
from slotformer_jax.datasets import base
from slotformer_jax.errors import shown
from slotformer_jax.files import UntrustedFileError
from slotformer_jax.files import confined
from slotformer_jax.files import read_untrusted_json

logger = logging.getLogger(__name__)

NAME = 'physion'
SCENARIOS: tuple[str, ...] = ('Collide', 'Contain', 'Dominoes', 'Drape',
                              'Drop', 'Link', 'Roll', 'Support')
SPLITS: tuple[str, ...] = ('train', 'val', 'readout_train', 'readout_val',
                           'test')
DEFAULT_RESOLUTION = (128, 128)
TRAIN_DIR = 'PhysionTrainMP4s'
TEST_DIR = 'PhysionTestMP4s'
READOUT_LABELS = f'{TRAIN_DIR}/readout_labels.csv'
TEST_LABELS = f'{TEST_DIR}/labels.csv'
LABEL_COLUMN = 'ground truth outcome'
CONVERTER_VERSION = 1
# Testing stimuli that the official SlotFormer readout evaluation means to
# leave out (its splits/Physion/bad_stimuli.txt), normalised with
# stimulus_name(); a video is flagged (``bad_stimulus``) when its normalised
# name contains one. Three entries there keep '-redyellow_..._img' and so
# never match the official check (which strips '-redyellow' from the file
# name first); normalised here, they are flagged.
BAD_TEST_STIMULI: tuple[str, ...] = (
    'pilot_towers_nb4_fr015_SJ000_gr-01_mono1_dis1_occ1_boxroom_0001',
    'pilot_towers_nb4_fr015_SJ000_gr015sph_mono1_dis0_occ0_tdwroom_0000',
    'pilot_it2_collision_yeet_box_1_dis_1_occ_0005',
    'pilot_it2_collision_yeet_tdw_1_dis_1_occ_0006',
    'pilot_linking_nl1-8_mg000_aCylcap_bCyl_tdwroom_0013',
    'pilot_linking_nl1-8_mg000_aCylcap_bCyl_tdwroom_0022',
    'pilot-containment-box_0004',
    'pilot-containment-box_0012',
    'pilot-containment-box_0016',
    'pilot-containment-cone-plate_0003',
    'pilot-containment-cone-plate_0008',
    'pilot-containment-cone-plate_0013',
    'pilot-containment-cylinder-bowl_0003',
    'pilot-containment-cylinder-bowl_0006',
    'pilot-containment-cylinder-bowl_0008',
    'pilot-containment-cylinder-bowl_0010',
    'pilot-containment-cylinder-bowl_0016',
    'pilot-containment-cylinder-bowl_0018',
    'pilot-containment-cylinder-bowl_0024',
    'pilot_it2_drop_sizes_box_1_dis_1_occ_0007',
    'test10_0014',
    'test11_0015',
    'test13_0001',
    'test13_0010',
    'test14_0016',
    'test17_0004',
    'pilot_it2_rollingSliding_simple_ledge_box_1_dis_1_occ_0000',
    'pilot_it2_rollingSliding_simple_ledge_box_1_dis_1_occ_0001',
    'pilot_it2_rollingSliding_simple_ledge_box_1_dis_1_occ_0002',
)

LAYOUT = """\
<source>/PhysionTrainMP4s/<Scenario>_training_MP4s/*.mp4
<source>/PhysionTrainMP4s/<Scenario>_readout_MP4s/*.mp4
<source>/PhysionTrainMP4s/readout_labels.csv
<source>/PhysionTestMP4s/<Scenario>/mp4s-redyellow/*.mp4
<source>/PhysionTestMP4s/labels.csv
<Scenario>: Collide Contain Dominoes Drape Drop Link Roll Support
(PhysionTrainMP4s.tar.gz and Physion.zip from
https://github.com/cogtoolslab/physics-benchmarking-neurips2021, unpacked;
readout_labels.csv from that repository's data/ folder)"""

# split -> (subset, official split-file name)
_SUBSETS: Mapping[str, tuple[str, str]] = {
    'train': ('training', 'training_train.json'),
    'val': ('training', 'training_val.json'),
    'readout_train': ('readout', 'readout_train.json'),
    'readout_val': ('readout', 'readout_val.json'),
    'test': ('test', 'test_test.json'),
}


@dataclasses.dataclass(frozen=True)
class Options(base.ConversionOptions):
  """Conversion parameters.

  Attributes:
    resolution: (H, W) of the stored frames.
    num_frames: leading frames kept per video (150 in the paper).
    val_fraction: share of Training / Readout videos put in the *_val
      splits (by file-name hash) when no split files are given.
    split_files: folder with the official split lists (see module doc), or
      None.
  """

  resolution: tuple[int, int] = DEFAULT_RESOLUTION
  num_frames: int = 150
  val_fraction: float = 0.05
  split_files: str | None = None
  version = CONVERTER_VERSION

  def __post_init__(self):
    super().__post_init__()
    if not 0.0 <= self.val_fraction < 1.0:
      raise ValueError(f'val_fraction must be in [0, 1), got '
                       f'{self.val_fraction}')

  @property
  def params(self) -> dict[str, Any]:
    params = super().params
    if self.split_files is not None:
      # The lists' content, not their location, decides the splits.
      params['split_files'] = _split_files_digest(Path(self.split_files))
    return params


@dataclasses.dataclass(frozen=True)
class VideoJob:
  """One Physion video.

  Attributes:
    key: path relative to the source folder.
    video: the mp4.
    scenario: index into SCENARIOS.
    label: 1 / 0, -1 for the unlabelled Training subset, None when the
      label file has no entry for this labelled video (skipped).
    bad_stimulus: listed in BAD_TEST_STIMULI.
  """

  key: str
  video: Path
  scenario: int
  label: int | None
  bad_stimulus: bool


def _split_files_digest(folder: Path) -> str:
  digest = hashlib.sha256()
  for _, name in sorted(_SUBSETS.values()):
    path = folder / name
    digest.update(name.encode())
    digest.update(path.read_bytes() if path.is_file() else b'<missing>')
  return digest.hexdigest()[:16]


layout_error = functools.partial(base.layout_error, 'Physion', LAYOUT)


def stimulus_name(file_name: str) -> str:
  """Label-file key of a video file name: no '.mp4', '_img', '-redyellow'."""
  name = file_name[:-4] if file_name.endswith('.mp4') else file_name
  name = name.replace('-redyellow', '')
  return name[:-4] if name.endswith('_img') else name


# Physion's label files are a few hundred KB.
MAX_LABEL_FILE_BYTES = 256 << 20


def read_labels(path: Path) -> dict[str, int]:
  """{stimulus name: 1 / 0} from a Physion label CSV.

  Raises:
    FileNotFoundError / ValueError: missing or malformed file (not UTF-8,
      no label column, a label that is not True / False).
  """
  size = Path(path).stat().st_size
  if size > MAX_LABEL_FILE_BYTES:
    raise ValueError(f'{path} holds {size} bytes, more than the '
                     f'{MAX_LABEL_FILE_BYTES} a label file may have')
  data = Path(path).read_bytes()
  try:
    # utf-8-sig: a byte-order mark (spreadsheet exports) is not part of the
    # first column's name.
    text = data.decode('utf-8-sig')
  except UnicodeDecodeError as error:
    line = data[:error.start].count(b'\n') + 1
    raise ValueError(
        f'{path}:{line}: not UTF-8 text (byte {data[error.start]:#04x}); '
        're-save the label file as UTF-8 CSV') from None
  labels = {}
  with io.StringIO(text, newline='') as f:
    rows = csv.reader(f)
    header = next(rows, None)
    if not header or LABEL_COLUMN not in header:
      raise ValueError(f'{path}: expected a header with a "{LABEL_COLUMN}" '
                       f'column, got {shown(repr(header), 200)}')
    column = header.index(LABEL_COLUMN)
    for line, row in enumerate(rows, start=2):
      if not row:
        continue
      if len(row) <= column:
        raise ValueError(f'{path}:{line}: {len(row)} columns, the label is '
                         f'column {column + 1}')
      value = row[column].strip().lower()
      if value not in ('true', 'false', '1', '0'):
        raise ValueError(f'{path}:{line}: label {row[column]!r} is not '
                         'True/False')
      labels[stimulus_name(row[0].strip())] = int(value in ('true', '1'))
  return labels


def _scenario_dir(source: Path, subset: str, scenario: str) -> Path:
  if subset == 'test':
    return source / TEST_DIR / scenario / 'mp4s-redyellow'
  return source / TRAIN_DIR / f'{scenario}_{subset}_MP4s'


def _is_val(relative: str, val_fraction: float) -> bool:
  # A hash of the name (not a random draw) keeps the split independent of
  # the listing order and of which other files are present.
  digest = hashlib.sha256(Path(relative).name.encode()).digest()
  return int.from_bytes(digest[:8], 'big') / 2.0**64 < val_fraction


def read_split_list(path: Path) -> dict[str, list[str]]:
  """{scenario: [mp4 path relative to --source]} of an official split list,
  read with limits and type-checked (the paths are confined to --source
  where they are used).

  Raises:
    UntrustedFileError / ValueError: one line naming the file.
  """
  listed = read_untrusted_json(path, what='Physion split list',
                               max_bytes=256 << 20, max_depth=3)
  if not isinstance(listed, dict) or not all(
      isinstance(v, list) and all(isinstance(p, str) for p in v)
      for v in listed.values()):
    raise UntrustedFileError(f'{path} is not {{scenario: [relative mp4 '
                             'path, ...]}}')
  unknown = sorted(set(listed) - set(SCENARIOS))
  if unknown:
    raise UntrustedFileError(f'{path}: unknown scenarios '
                             f'{shown(", ".join(unknown), 200)}')
  return listed


def _listed_files(source: Path, split: str,
                  options: Options) -> list[tuple[int, Path]]:
  """(scenario index, mp4 path) of a split, in scenario then name order."""
  subset, list_name = _SUBSETS[split]
  if options.split_files is not None:
    list_path = Path(options.split_files) / list_name
    if not list_path.is_file():
      raise FileNotFoundError(f'Physion: split list {list_path} not found '
                              '(--split_files)')
    listed = read_split_list(list_path)
    return [(SCENARIOS.index(s), confined(source, rel, nested=True,
                                          what=f'{list_path}: the video'))
            for s in SCENARIOS
            for rel in sorted(listed.get(s, []), key=media.natural_key)]
  files = []
  missing = []
  for index, scenario in enumerate(SCENARIOS):
    folder = _scenario_dir(source, subset, scenario)
    if not folder.is_dir():
      missing.append(folder)
      continue
    videos = sorted((p for p in folder.iterdir()
                     if p.suffix == '.mp4' and not p.name.startswith('.')),
                    key=lambda p: media.natural_key(p.name))
    if split == 'test':
      chosen = videos
    else:
      want_val = split.endswith('val')
      chosen = [p for p in videos
                if _is_val(p.name, options.val_fraction) == want_val]
    files += [(index, p) for p in chosen]
  if missing:
    names = ', '.join(p.relative_to(source).as_posix() for p in missing)
    raise layout_error(source, missing[0],
                       f' ({len(missing)} scenario folders missing: {names})')
  return files


def _no_video_error(source: Path, split: str,
                    options: Options) -> Exception:
  """Why `split` has no video although its folders exist."""
  subset, list_name = _SUBSETS[split]
  if options.split_files is not None:
    return ValueError(f'Physion: the split list '
                      f'{Path(options.split_files) / list_name} lists no '
                      f'video for split {split!r}')
  folders = [_scenario_dir(source, subset, s) for s in SCENARIOS]
  count = sum(1 for folder in folders for p in folder.iterdir()
              if p.suffix == '.mp4' and not p.name.startswith('.'))
  if not count:
    return layout_error(source, _scenario_dir(source, subset, '<Scenario>')
                        / '*.mp4', f' (the {len(folders)} scenario folders '
                        'hold no .mp4)')
  # The hashed split of a small subset can come out empty.
  share = (options.val_fraction if split.endswith('val')
           else 1 - options.val_fraction)
  other = split[:-len('val')] + 'train' if split.endswith('val') else (
      split[:-len('train')] + 'val')
  return ValueError(
      f'Physion: none of the {count} {subset} videos falls in split '
      f'{split!r} (a hash of the file name puts a share of about {share:g} '
      f'there, --val_fraction={options.val_fraction:g}; every other video '
      f'went to {other!r}): with so few videos, change --val_fraction or '
      f'leave {split!r} out of --splits')


def discover(source: Path, split: str, options: Options) -> list[VideoJob]:
  """The videos of ``split`` with their labels.

  Raises:
    FileNotFoundError: a folder or label file of the published layout is
      missing, or its folders hold no video.
    ValueError: malformed label file or split list, or a hashed split that
      comes out empty (a small subset).
  """
  subset, _ = _SUBSETS[split]
  top = source / (TEST_DIR if subset == 'test' else TRAIN_DIR)
  if not top.is_dir():
    raise layout_error(source, top)
  labels: dict[str, int] | None = None
  if subset != 'training':
    label_path = source / (TEST_LABELS if subset == 'test' else READOUT_LABELS)
    if not label_path.is_file():
      raise layout_error(source, label_path)
    labels = read_labels(label_path)
  files = _listed_files(source, split, options)
  if not files:
    raise _no_video_error(source, split, options)
  jobs = []
  for scenario, path in files:
    name = stimulus_name(path.name)
    jobs.append(VideoJob(
        key=path.relative_to(source).as_posix(), video=path,
        scenario=scenario,
        label=-1 if labels is None else labels.get(name),
        bad_stimulus=subset == 'test' and any(
            bad in name for bad in BAD_TEST_STIMULI)))
  return jobs


def convert_video(job: VideoJob, options: Options) -> dict[str, Any]:
  """Decodes the first ``num_frames`` frames of one video and resizes them.

  Raises:
    media.SkipVideo: missing label, unreadable or truncated video.
  """
  if job.label is None:
    raise media.SkipVideo('missing_label',
                          f'{job.video}: no "{stimulus_name(job.video.name)}"'
                          ' row in the label file')
  frames, _ = media.decode_video(job.video, max_frames=options.num_frames)
  return {
      'video': media.resize_frames(frames, options.resolution),
      'label': job.label,
      'scenario': job.scenario,
      'bad_stimulus': job.bad_stimulus,
      'video_name': stimulus_name(job.video.name),
  }


def features(options: Options) -> tfds.features.FeaturesDict:
  h, w = options.resolution
  return tfds.features.FeaturesDict({
      'video': base.tensor((None, h, w, 3), np.uint8),
      'label': tfds.features.Scalar(np.int32),
      'scenario': tfds.features.Scalar(np.int32),
      'bad_stimulus': tfds.features.Scalar(np.bool_),
      'video_name': tfds.features.Text(),
  })


def describe(options: Options) -> str:
  h, w = options.resolution
  return (f'Physion: first {options.num_frames} frames per video at '
          f'{h}x{w} (RGB), contact labels for the Readout Fitting '
          'and Testing subsets.')


DATASET = base.register(base.Converted(
    names=(NAME,), label='Physion', command=NAME, splits=SPLITS,
    layout=LAYOUT, features=functools.partial(features, Options()),
    # The official frames were written to JPEG by cv2.imwrite (colours
    # kept) and read back with PIL's convert('RGB').
    official_channel_order='rgb',
    options=Options, discover=discover, convert=convert_video,
    stored=features, describe=describe))
