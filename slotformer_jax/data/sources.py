"""Random-access video sources: the reader interface every dataset shares.

A *source* is the videos of one split, indexable like a list::

    source = get_video_source(data_config, 'train')
    len(source)            # number of videos
    source[i]['video']     # uint8 [T, H, W, 3]

Every dataset is stored as an ``array_record`` TFDS folder (one example per
video, examples in index order) and read through :class:`TfdsVideoSource`;
:func:`open_prepared_dataset` opens any such folder, so the converted real
datasets and the embedded synthetic one share one reader.

Data config fields (``ml_collections.ConfigDict``; all but ``name`` optional):

* ``name``: ``'synthetic'`` (generated on first use, see ``convert/synthetic.py``) or
  one of ``'obj3d' | 'clevrer' | 'physion' | 'phyre' | 'movi_a' ... 'movi_f'``
  (must have been converted with ``python -m slotformer_jax.data.prepare`` into
  ``<data_dir>/<name>``; MOVi with ``--dataset=movi``).
* ``data_dir``: root of the cache / converted data. Default:
  ``$SLOTFORMER_DATA_DIR``, else ``~/.cache/slotformer_jax``.
* ``resolution``: (H, W) of the frames. Default (64, 64). For a real dataset
  it selects between several converted versions and is checked.
* ``num_frames``: synthetic only, frames per video. Default 40.
* ``min_objects``, ``max_objects``: synthetic only, static objects per video
  (plus the launched sphere). Default 3, 5.
* ``seed``: synthetic only, generation seed. Default 0.
* ``num_train``, ``num_val``, ``num_test``: synthetic only, videos per split.
  Default 1000, 100, 100.
* ``supersample``: synthetic only, anti-aliasing factor. Default 2.
* ``object_scale``: synthetic only, multiplies object sizes. Default 1.
* ``distinct_colors``: synthetic only, no repeated colour in a video.
  Default False.
* ``num_workers``: synthetic and the embedded task families (contact,
  PHYRE-like), generator processes. Default: all cores.
* ``channel_order``: real datasets only, ``'rgb'`` (default) or ``'bgr'``:
  the channel order of the ``video`` frames handed out. Conversions store
  RGB; ``'bgr'`` reverses the channels at read time (see
  :class:`ChannelOrderSource`), e.g. for models trained on OpenCV-decoded
  frames like the official CLEVRER ones.
* ``prepared_config``: real datasets only, the config folder under
  ``<data_dir>/<name>`` to read (e.g. ``'ball_within_template_fold0_...'``)
  when several conversions exist that ``resolution`` does not tell apart.

Items are dicts of numpy arrays whose first axis is time (plus per-video
scalars / metadata); arrays may be read-only views of the decoded record.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import ml_collections
import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import integrity
from slotformer_jax.data.convert import synthetic
from slotformer_jax.data.data_dir import DATA_DIR_ENV  # noqa: F401 (re-export)
from slotformer_jax.data.data_dir import default_data_dir  # noqa: F401 (re-export)
from slotformer_jax.data.data_dir import resolve_data_dir
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError

logger = logging.getLogger(__name__)

# Kubric's MOVi variants: one converter (--dataset=movi), one name each.
MOVI_DATASETS: tuple[str, ...] = tuple(f'movi_{v}' for v in 'abcdef')
REAL_DATASETS: tuple[str, ...] = ('obj3d', 'clevrer', 'physion',
                                  'phyre') + MOVI_DATASETS
_DATASET_INFO = 'dataset_info.json'


class VideoSource(Protocol):
  """Random access over the videos of one split.

  ``__getitem__`` returns ``'video'``: uint8 [T, H, W, 3] always, and
  optionally ``'segmentations'``: uint8 [T, H, W], ``'boxes'``: float32
  [T, O, 4], ``'visible'``: bool [T, O], and dataset-specific extras.
  """

  def __len__(self) -> int:
    ...

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    ...


class TfdsVideoSource:
  """A split of an ``array_record`` TFDS folder as a :class:`VideoSource`.

  Thin wrapper over ``tfds.builder_from_directory(dir).as_data_source(split)``
  (which needs neither TensorFlow nor the builder class) that returns plain
  dicts of numpy arrays (scalars become 0-d arrays).
  """

  def __init__(self, dataset_dir: str | os.PathLike[str], split: str, *,
               fix: str = ''):
    self.dataset_dir = Path(dataset_dir)
    self.split = split
    # What to do when a record cannot be read (named in the error).
    self.fix = fix or f'Delete {self.dataset_dir} and prepare it again.'
    builder = tfds.builder_from_directory(os.fspath(self.dataset_dir))
    if split not in builder.info.splits:
      raise ValueError(f'{self.dataset_dir} has no split {split!r}; it has '
                       f'{sorted(builder.info.splits)}')
    self.info = builder.info
    self._source = builder.as_data_source(split)
    # The numpy decoder returns scalars as Python ints; restore stored dtypes.
    self._dtypes = {}
    for key, feature in builder.info.features.items():
      dtype = getattr(feature, 'np_dtype', None)
      if isinstance(dtype, np.dtype):
        self._dtypes[key] = dtype

  def __len__(self) -> int:
    return len(self._source)

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    # Python-style negative indices, and a clear error past the end (the
    # underlying reader would raise a less obvious one).
    n = len(self._source)
    index = int(index)
    if not -n <= index < n:
      raise IndexError(f'index {index} out of range for {n} videos')
    try:
      example = self._source[index % n]
    except Exception as error:  # pylint: disable=broad-except
      # The reader's own message ('Invalid Riegeli/records file') names no
      # file; this one names the folder and the fix.
      raise UserError(
          f'{self.dataset_dir}: reading video {index} of split '
          f'{self.split!r} failed ({type(error).__name__}: '
          f'{str(error).splitlines()[0][:200] if str(error) else ""}); the '
          f'dataset cache is damaged. {self.fix}') from None
    return {key: _as_numpy(value, self._dtypes.get(key))
            for key, value in example.items()}

  def __repr__(self) -> str:
    return (f'TfdsVideoSource({os.fspath(self.dataset_dir)!r}, '
            f'split={self.split!r}, len={len(self)})')


def _as_numpy(value: Any, dtype: np.dtype | None) -> Any:
  """Leaves as numpy arrays (nested feature dicts of real datasets kept)."""
  if isinstance(value, Mapping):
    return {key: _as_numpy(leaf, None) for key, leaf in value.items()}
  return np.asarray(value, dtype=dtype)


def _find_dataset_dirs(root: Path) -> list[Path]:
  """TFDS version folders (holding dataset_info.json) at or below ``root``."""
  if (root / _DATASET_INFO).is_file():
    return [root]
  # <root>/<builder>/<config>/<version>/ at most three levels down; skip the
  # temporary folders of unfinished tfds builds ('incomplete.*').
  found = []
  for depth in range(1, 4):
    pattern = '/'.join(['*'] * depth) + '/' + _DATASET_INFO
    found += sorted(
        p.parent for p in root.glob(pattern)
        if not any(part.startswith('incomplete.')
                   for part in p.relative_to(root).parts))
  return found


def _video_resolution(dataset_dir: Path) -> tuple[int, int] | None:
  builder = tfds.builder_from_directory(os.fspath(dataset_dir))
  video = builder.info.features['video']
  shape = getattr(video, 'shape', None)
  if shape is None or len(shape) < 3 or None in shape[-3:-1]:
    return None
  return int(shape[-3]), int(shape[-2])


def open_prepared_dataset(
    path: str | os.PathLike[str], split: str, *,
    resolution: Sequence[int] | None = None) -> TfdsVideoSource:
  """Opens one split of a converted (array_record TFDS) dataset.

  Args:
    path: a TFDS version folder (holding ``dataset_info.json``) or a folder
      containing exactly one such folder up to three levels down (e.g.
      ``<data_dir>/clevrer`` holding ``clevrer/<config>/<version>``).
    split: split name, e.g. 'train'.
    resolution: optional (H, W): picks among several prepared versions, and
      is checked against the frames.

  Raises:
    FileNotFoundError: nothing prepared under ``path``.
    ValueError: ambiguous folder, or wrong resolution / split.
  """
  root = Path(path).expanduser()
  candidates = _find_dataset_dirs(root) if root.is_dir() else []
  if not candidates:
    raise FileNotFoundError(
        f'No prepared TFDS dataset (no {_DATASET_INFO}) under {root}.')
  want = tuple(int(r) for r in resolution) if resolution is not None else None
  if want is not None and len(candidates) > 1:
    candidates = [c for c in candidates if _video_resolution(c) == want] or (
        candidates)
  if len(candidates) > 1:
    listing = '\n  '.join(os.fspath(c) for c in candidates)
    raise ValueError(f'Several prepared datasets under {root}; pass one of '
                     'them (or set resolution; for a config: set '
                     'data.prepared_config to the folder name between '
                     f'{root.name}/ and the version):\n  {listing}')
  dataset_dir = candidates[0]
  if want is not None:
    have = _video_resolution(dataset_dir)
    if have is not None and have != want:
      raise ValueError(f'{dataset_dir} holds {have[0]}x{have[1]} frames but '
                       f'resolution {want[0]}x{want[1]} was requested.')
  return TfdsVideoSource(dataset_dir, split)


def synthetic_config_from_data_config(
    data_config: ml_collections.ConfigDict) -> synthetic.SyntheticConfig:
  """The generation parameters named by a data config (defaults filled in)."""
  defaults = synthetic.SyntheticConfig()
  return synthetic.SyntheticConfig(
      resolution=tuple(data_config.get('resolution', defaults.resolution)),
      num_frames=int(data_config.get('num_frames', defaults.num_frames)),
      min_objects=int(data_config.get('min_objects', defaults.min_objects)),
      max_objects=int(data_config.get('max_objects', defaults.max_objects)),
      seed=int(data_config.get('seed', defaults.seed)),
      num_train=int(data_config.get('num_train', defaults.num_train)),
      num_val=int(data_config.get('num_val', defaults.num_val)),
      num_test=int(data_config.get('num_test', defaults.num_test)),
      supersample=int(data_config.get('supersample', defaults.supersample)),
      object_scale=float(data_config.get('object_scale',
                                         defaults.object_scale)),
      distinct_colors=bool(data_config.get('distinct_colors',
                                           defaults.distinct_colors)),
  )


def prepared_dataset_path(data_dir: str | os.PathLike[str] | None,
                          name: str) -> Path:
  """Where ``python -m slotformer_jax.data.prepare`` puts dataset ``name``."""
  return resolve_data_dir(data_dir) / name


def get_video_source(data_config: ml_collections.ConfigDict,
                     split: str) -> VideoSource:
  """The videos of ``split`` for the dataset described by ``data_config``.

  'synthetic' is generated into the cache on first use (later calls with the
  same parameters reuse it); real datasets must have been converted first.
  """
  name = data_config.get('name')
  data_dir = data_config.get('data_dir', None)
  if name == 'synthetic':
    config = synthetic_config_from_data_config(data_config)
    if split not in synthetic.SPLITS or config.num_videos(split) == 0:
      raise ValueError(f'synthetic split {split!r} is empty or unknown; '
                       f'splits are {synthetic.SPLITS} with sizes '
                       f'{[config.num_videos(s) for s in synthetic.SPLITS]}')
    dataset_dir = synthetic.build_synthetic_dataset(
        config, resolve_data_dir(data_dir),
        num_workers=data_config.get('num_workers', None))
    try:
      if not integrity.verify_checksums(dataset_dir, split):
        integrity.record_checksums(dataset_dir)  # built by an older version
    except integrity.DamagedDataset as error:
      # A cache is regenerable: say so, set it aside, build it again.
      logger.warning('the synthetic dataset cache is damaged (%s); '
                     'regenerating it', error)
      synthetic.discard_dataset(dataset_dir)
      dataset_dir = synthetic.build_synthetic_dataset(
          config, resolve_data_dir(data_dir),
          num_workers=data_config.get('num_workers', None))
    return TfdsVideoSource(dataset_dir, split, fix=(
        f'Delete {dataset_dir}: it is regenerated on the next run.'))
  if name in EMBEDDED_TASK_DATASETS:
    return _embedded_task_source(data_config, split)
  if name == 'clevrer_like':
    # The CLEVRER-like VQA family, generated on first use like 'synthetic'.
    from slotformer_jax.data import clevrer_like  # pylint: disable=g-import-not-at-top
    root = clevrer_like.build_dataset(
        clevrer_like.config_from_data_config(data_config),
        resolve_data_dir(data_dir),
        num_workers=data_config.get('num_workers', None))
    return clevrer_like.NpyVideoSource(root, split)
  if name in REAL_DATASETS:
    path = prepared_dataset_path(data_dir, name)
    # MOVi: one converter for every variant, the download names which.
    command, download = (('movi', f'/path/to/{name}/128x128/1.0.0')
                         if name in MOVI_DATASETS
                         else (name, '/path/to/download'))
    if not path.is_dir() or not _find_dataset_dirs(path):
      raise MissingInputError(
          f'Dataset {name!r} is not prepared: expected an array_record TFDS '
          f'folder under {path}. Convert it first with\n'
          f'  python -m slotformer_jax.data.prepare --dataset={command} '
          f'--source={download} --data_dir={path.parent}')
    if data_config.get('prepared_config', None):
      path = path / data_config.prepared_config
    source = open_prepared_dataset(
        path, split, resolution=data_config.get('resolution', None))
    reconvert = (
        f'python -m slotformer_jax.data.prepare --dataset={command} '
        f'--source={download} --data_dir={resolve_data_dir(data_dir)} '
        '--overwrite (with the options it was converted with)')
    source.fix = f'Convert it again: {reconvert}'
    try:
      if not integrity.verify_checksums(source.dataset_dir, split):
        # Converted by an older version: trust it once, check from now on.
        logger.info('recording checksums of %s', source.dataset_dir)
        integrity.record_checksums(source.dataset_dir)
    except integrity.DamagedDataset as error:
      raise UserError(f'the converted {name} dataset is damaged: {error}. '
                      f'Convert it again: {reconvert}') from None
    return with_channel_order(source, data_config.get('channel_order', 'rgb'))
  raise ConfigError(f'Unknown dataset name {name!r}; expected "synthetic", '
                    f'"clevrer_like", one of {EMBEDDED_TASK_DATASETS} or one '
                    f'of {REAL_DATASETS}.')


# The downstream-task families (data/convert/contact.py, phyre_like.py),
# generated on first use like 'synthetic'.
EMBEDDED_TASK_DATASETS = ('synthetic_contact', 'synthetic_phyre')


def _embedded_task_source(data_config: ml_collections.ConfigDict,
                          split: str) -> VideoSource:
  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data.convert import contact
  from slotformer_jax.data.convert import phyre_like
  root = resolve_data_dir(data_config.get('data_dir', None))
  if data_config.name == 'synthetic_contact':
    path = contact.build_contact_dataset(
        contact.config_from_data_config(data_config), root,
        num_workers=data_config.get('num_workers', None))
  else:
    path = phyre_like.build_video_dataset(data_config, root)
  return TfdsVideoSource(path, split)


# ----------------------------------------------------------------------------
# Channel order (real datasets)
# ----------------------------------------------------------------------------

CHANNEL_ORDERS: tuple[str, ...] = ('rgb', 'bgr')


class ChannelOrderSource:
  """A source whose ``video`` frames have their channels reversed (RGB<->BGR).

  The official SlotFormer CLEVRER models were trained on frames decoded by
  OpenCV, i.e. BGR; converted datasets store RGB, and this wrapper hands out
  BGR instead when the data config says ``channel_order='bgr'``. Costs one
  copy of the frames per item; other fields pass through.
  """

  def __init__(self, source: VideoSource):
    self.source = source

  def __len__(self) -> int:
    return len(self.source)

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    item = dict(self.source[index])
    item['video'] = np.ascontiguousarray(item['video'][..., ::-1])
    return item

  def __repr__(self) -> str:
    return f'ChannelOrderSource({self.source!r}, order=bgr)'


def with_channel_order(source: VideoSource, channel_order: str) -> VideoSource:
  """``source`` handing out ``channel_order`` frames (stored frames: RGB)."""
  order = str(channel_order).lower()
  if order not in CHANNEL_ORDERS:
    raise ValueError(f'channel_order must be one of {CHANNEL_ORDERS}, got '
                     f'{channel_order!r}')
  return source if order == 'rgb' else ChannelOrderSource(source)
