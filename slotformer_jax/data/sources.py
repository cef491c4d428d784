"""Reading videos: the interface every dataset's reader shares, and the
array_record TFDS reader they use.

A *source* is the videos of one split, indexable like a list::

    source = datasets.get(config.data.name).open(config.data, 'train')
    len(source)            # number of videos
    source[i]['video']     # uint8 [T, H, W, 3]

Converted and generated datasets are ``array_record`` TFDS folders (one
example per video, in index order; chunked ``2.0.0`` or whole-video ``1.0.0``
layout, ``data/chunked.py``) read by :class:`TfdsVideoSource`;
:func:`open_prepared_dataset` opens any such folder. Also here: where the
data live (:func:`resolve_data_dir`), the folders of generated datasets, and
the RGB <-> BGR view (:class:`ChannelOrderSource`). Which dataset lives where
is the dataset module's (``slotformer_jax/datasets/``).

Reading never writes: opening finds a folder, verifies the split's recorded
checksums (``data/integrity.py``) and opens it; making data, recording
checksums and replacing a damaged cache are the data stage's
(``stages/data.py``, ``data/write/``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import chunked
from slotformer_jax.data import integrity
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from tensorflow_datasets.core.example_parser import tf_example_pb2

_Example = tf_example_pb2.Example


_DATASET_INFO = 'dataset_info.json'
_WARNED_WHOLE_VIDEO: set[str] = set()
logger = logging.getLogger(__name__)


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

  Reads both layouts (``data/chunked.py``): a chunked folder (``2.0.0``,
  ``video_chunks.json``) through its index, so :meth:`num_frames` needs no
  decoding and :meth:`clip` decompresses only the chunks that hold the
  clip's frames; a whole-video folder (``1.0.0``, one record per video)
  through ``tfds.builder_from_directory(dir).as_data_source(split)`` (which
  needs neither TensorFlow nor the builder class), where :meth:`clip`
  decodes the whole video and ``supports_clips`` is False. Items are plain
  dicts of numpy arrays (scalars become 0-d arrays), the same in both
  layouts.

  ``records_read`` counts the records read so far (tests and benchmarks).
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
    self.records_read = 0
    # The numpy decoder returns scalars as Python ints; restore stored dtypes.
    self._dtypes = {}
    for key, feature in builder.info.features.items():
      dtype = getattr(feature, 'np_dtype', None)
      if isinstance(dtype, np.dtype):
        self._dtypes[key] = dtype
    index = chunked.read_index(self.dataset_dir)
    if index is None:  # whole-video layout
      self._layout = None
      self._source = builder.as_data_source(split)
      self._len = len(self._source)
      if os.fspath(self.dataset_dir) not in _WARNED_WHOLE_VIDEO:
        _WARNED_WHOLE_VIDEO.add(os.fspath(self.dataset_dir))
        logger.warning(
            '%s holds whole-video records (layout 1.0.0): it is read as it '
            'is, but every training clip decompresses its whole video. '
            'Preparing it again writes the chunked layout (2.0.0, '
            'docs/datasets.md) next to it, read from then on.',
            self.dataset_dir)
      return
    if split not in index['splits']:
      raise ValueError(f'{self.dataset_dir / chunked.INDEX_FILE} has no '
                       f'split {split!r}; the folder is damaged. {self.fix}')
    self._layout = chunked.Layout(builder.info.features,
                                  int(index['frames_per_chunk']))
    if (sorted(self._layout.time) != sorted(index['time_fields'])
        or sorted(self._layout.header) != sorted(index['header_fields'])):
      raise UserError(f'{self.dataset_dir}: {chunked.INDEX_FILE} does not '
                      f'match features.json; the folder is damaged. '
                      f'{self.fix}')
    entry = index['splits'][split]
    self._frames = np.asarray(entry['num_frames'], np.int64)
    self._first = np.asarray(entry['first_record'], np.int64)
    self._len = len(self._frames)
    # pylint: disable=g-import-not-at-top
    from array_record.python import array_record_data_source
    # The shard lengths of dataset_info.json: no file is opened until a
    # record of it is read (as tfds's as_data_source does), so a damaged
    # shard fails at its first read, with the error below.
    instructions = builder.info.splits[split].file_instructions
    have = sum(int(i.take) for i in instructions)
    if have != int(entry['num_records']):
      raise UserError(
          f'{self.dataset_dir}: split {split!r} has {have} records but '
          f'{chunked.INDEX_FILE} lists {entry["num_records"]}; the dataset '
          f'cache is damaged. {self.fix}')
    self._records = array_record_data_source.ArrayRecordDataSource(
        instructions)
    # Chunks of raw-bytes tensors (what every writer here makes) are parsed
    # straight from the tf.train.Example: the same bytes TFDS's decoder
    # hands to np.frombuffer, without its per-record Python walk (about
    # 100 us of the 200-300 us a 4-frame 64x64 chunk costs).
    self._raw_chunks = None
    time_features = [builder.info.features[k] for k in self._layout.time]
    if all(getattr(f, '_encoding', None) == tfds.features.Encoding.BYTES
           for f in time_features):
      self._raw_chunks = [(k, f.np_dtype, tuple(f.shape[1:]))
                          for k, f in zip(self._layout.time, time_features)]

  @property
  def supports_clips(self) -> bool:
    """Whether :meth:`clip` reads less than the whole video (chunked)."""
    return self._layout is not None

  @property
  def time_fields(self) -> tuple[str, ...]:
    """The fields :meth:`clip` cuts along time without the whole video
    (chunked layout; none for whole videos)."""
    return self._layout.time if self._layout is not None else ()

  def __len__(self) -> int:
    return self._len

  def _check_index(self, index: int) -> int:
    # Python-style negative indices, and a clear error past the end (the
    # underlying reader would raise a less obvious one).
    n = self._len
    index = int(index)
    if not -n <= index < n:
      raise IndexError(f'index {index} out of range for {n} videos')
    return index % n

  def _damaged(self, index: int, error: Exception) -> UserError:
    # The reader's own message ('Invalid Riegeli/records file') names no
    # file; this one names the folder and the fix.
    return UserError(
        f'{self.dataset_dir}: reading video {index} of split '
        f'{self.split!r} failed ({type(error).__name__}: '
        f'{str(error).splitlines()[0][:200] if str(error) else ""}); the '
        f'dataset cache is damaged. {self.fix}')

  def _decode(self, records: range, features: Any, index: int
              ) -> list[dict[str, Any]]:
    out = []
    raw = (self._raw_chunks if features is self._layout.chunk_features
           else None)
    try:
      for key in records:
        record = self._records[key]
        if raw is None:
          out.append(features.deserialize_example_np(record))
        else:
          feature = _Example.FromString(record).features.feature
          out.append({
              name: np.frombuffer(feature[name].bytes_list.value[0],
                                  dtype).reshape((-1,) + shape)
              for name, dtype, shape in raw})
        self.records_read += 1
    except Exception as error:  # pylint: disable=broad-except
      raise self._damaged(index, error) from None
    return out

  def _header(self, index: int) -> dict[str, Any]:
    if not self._layout.header:
      return {}
    first = int(self._first[index])
    return self._decode(range(first, first + 1),
                        self._layout.header_features, index)[0]

  def _frames_of(self, index: int, begin: int, end: int,
                 keys: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """Frames ``[begin, end)`` of the time fields `keys` (default: every
    one), from the chunks that hold them (a view of one chunk when they lie
    in one; only the fields asked for are joined across chunks)."""
    k = self._layout.frames_per_chunk
    keys = self._layout.time if keys is None else tuple(keys)
    if end <= begin:  # no frame (a video of none): empty arrays, no read
      return {key: np.zeros((0,) + tuple(self.info.features[key].shape[1:]),
                            self.info.features[key].np_dtype)
              for key in keys}
    first = int(self._first[index]) + bool(self._layout.header)
    c0, c1 = begin // k, (end - 1) // k
    chunks = self._decode(range(first + c0, first + c1 + 1),
                          self._layout.chunk_features, index)
    out = {}
    for key in keys:
      parts = [np.asarray(chunk[key]) for chunk in chunks]
      whole = parts[0] if len(parts) == 1 else np.concatenate(parts)
      out[key] = whole[begin - c0 * k:end - c0 * k]
    return out

  def num_frames(self, index: int) -> int:
    """T of video ``index`` (chunked: from the index, no read)."""
    index = self._check_index(index)
    if self._layout is None:
      return int(np.shape(self[index]['video'])[0])
    return int(self._frames[index])

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    index = self._check_index(index)
    if self._layout is None:
      try:
        example = self._source[index]
        self.records_read += 1
      except Exception as error:  # pylint: disable=broad-except
        raise self._damaged(index, error) from None
    else:
      example = {**self._header(index),
                 **self._frames_of(index, 0, int(self._frames[index]))}
      # The whole-video decoder's order (TFDS decodes in sorted key order).
      example = {key: example[key] for key in sorted(self.info.features)}
    return {key: _as_numpy(value, self._dtypes.get(key))
            for key, value in example.items()}

  def header(self, index: int) -> dict[str, Any]:
    """The per-video fields of video ``index`` (those without its time
    axis: names, scalars, per-object arrays, the ranges of stored flows),
    without its frames (chunked: one record; whole videos: the video)."""
    index = self._check_index(index)
    if self._layout is None:
      time = chunked.time_fields(self.info.features)
      return {key: value for key, value in self[index].items()
              if key not in time}
    return {key: _as_numpy(value, self._dtypes.get(key))
            for key, value in self._header(index).items()}

  def clip(self, index: int, start: int, length: int, stride: int = 1,
           fields: Sequence[str] = ('video',)) -> dict[str, np.ndarray]:
    """Frames ``start, start + stride, ...`` (``length`` of them) of the
    requested fields of video ``index``, as ``pipeline._slice_item`` cuts
    them from ``self[index]`` (per-video scalars passed through; a
    non-scalar field without the video's time axis is an error), reading
    only the chunks that hold them (and the header when a per-video field
    is asked for).

    Raises:
      ValueError: the clip does not fit in the video, or a requested field
        is not sliceable (see ``pipeline._slice_item``).
      KeyError: a field the dataset does not have.
    """
    index = self._check_index(index)
    fields = tuple(fields)
    if self._layout is None:
      from slotformer_jax.data import pipeline  # pylint: disable=g-import-not-at-top
      return pipeline._slice_item(self[index], fields, index, start, length,  # pylint: disable=protected-access
                                  stride)
    num_frames = int(self._frames[index])
    end = start + (length - 1) * stride + 1
    if length < 1 or stride < 1 or start < 0 or end > num_frames:
      raise ValueError(
          f'video {index} has {num_frames} frames; a clip of {length} frames '
          f'with stride {stride} from frame {start} does not fit')
    for field in fields:
      if field not in self.info.features:
        raise KeyError(f'item {index} has no field {field!r}; it has '
                       f'{sorted(self.info.features)}')
    item: dict[str, Any] = {}
    if any(f in self._layout.header for f in fields):
      item.update({key: _as_numpy(value, self._dtypes.get(key))
                   for key, value in self._header(index).items()})
    if not any(f in self._layout.time for f in fields):
      return _slice_header_only(item, fields, index, start, length, stride)
    frames = self._frames_of(index, start, end,
                             [f for f in fields if f in self._layout.time])
    out = {}
    for field in fields:
      if field in self._layout.time:
        out[field] = _as_numpy(frames[field], self._dtypes.get(field))[::stride]
        continue
      value = np.asarray(item[field])
      if value.ndim == 0:
        out[field] = value
      elif value.shape[0] == num_frames:  # as _slice_item would cut it
        out[field] = value[start:end:stride]
      else:
        raise ValueError(
            f'item {index}: field {field!r} has {value.shape[0]} steps on '
            f'its first axis but the video has {num_frames}; every requested '
            'non-scalar field must have time first')
    return out

  def __repr__(self) -> str:
    layout = ('whole videos' if self._layout is None else
              f'chunks of {self._layout.frames_per_chunk} frames')
    return (f'TfdsVideoSource({os.fspath(self.dataset_dir)!r}, '
            f'split={self.split!r}, len={len(self)}, {layout})')


def _slice_header_only(item: Mapping[str, Any], fields: Sequence[str],
                       index: int, start: int, length: int, stride: int
                       ) -> dict[str, np.ndarray]:
  """A clip of per-video fields only: as ``pipeline._slice_item``."""
  from slotformer_jax.data import pipeline  # pylint: disable=g-import-not-at-top
  return pipeline._slice_item(item, fields, index, start, length, stride)  # pylint: disable=protected-access


def _as_numpy(value: Any, dtype: np.dtype | None) -> Any:
  """Leaves as numpy arrays (nested feature dicts of real datasets kept)."""
  if isinstance(value, Mapping):
    return {key: _as_numpy(leaf, None) for key, leaf in value.items()}
  return np.asarray(value, dtype=dtype)


def find_dataset_dirs(root: Path) -> list[Path]:
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


def _newest_versions(candidates: list[Path]) -> list[Path]:
  """One version folder per conversion folder: the newest (a dataset
  converted again after the chunked layout, 2.0.0, next to its whole-video
  1.0.0 folder is read from 2.0.0)."""
  newest: dict[Path, Path] = {}
  for path in candidates:
    if not tfds.core.Version.is_valid(path.name):
      newest[path] = path
      continue
    kept = newest.get(path.parent)
    if kept is None or tfds.core.Version(path.name) > tfds.core.Version(
        kept.name):
      newest[path.parent] = path
  return sorted(newest.values())


def find_prepared_dataset(
    path: str | os.PathLike[str], *,
    resolution: Sequence[int] | None = None) -> Path:
  """The TFDS version folder of a converted (array_record TFDS) dataset.

  Args:
    path: a TFDS version folder (holding ``dataset_info.json``) or a folder
      containing exactly one such folder up to three levels down (e.g.
      ``<data_dir>/clevrer`` holding ``clevrer/<config>/<version>``).
    resolution: optional (H, W): picks among several prepared versions, and
      is checked against the frames.

  Raises:
    FileNotFoundError: nothing prepared under ``path``.
    ValueError: ambiguous folder, or wrong resolution.
  """
  root = Path(path).expanduser()
  candidates = find_dataset_dirs(root) if root.is_dir() else []
  if not candidates:
    raise FileNotFoundError(
        f'No prepared TFDS dataset (no {_DATASET_INFO}) under {root}.')
  candidates = _newest_versions(candidates)
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
  return dataset_dir


def open_prepared_dataset(
    path: str | os.PathLike[str], split: str, *,
    resolution: Sequence[int] | None = None) -> TfdsVideoSource:
  """Opens one split of a converted dataset (:func:`find_prepared_dataset`
  finds its folder).

  Raises:
    FileNotFoundError: nothing prepared under ``path``.
    ValueError: ambiguous folder, or wrong resolution / split.
  """
  return TfdsVideoSource(find_prepared_dataset(path, resolution=resolution),
                         split)


# ----------------------------------------------------------------------------
# Where the data live
# ----------------------------------------------------------------------------

DATA_DIR_ENV = 'SLOTFORMER_DATA_DIR'
# The command that makes generated data (stages/data.py); every --mode runs
# it first, so readers only meet a missing dataset outside main.
PREPARE_COMMAND = ('python -m slotformer_jax.main --config=<config> '
                   '--workdir=<workdir> --mode=prepare_data')


def default_data_dir() -> Path:
  """``$SLOTFORMER_DATA_DIR`` if set, else ``~/.cache/slotformer_jax``."""
  env = os.environ.get(DATA_DIR_ENV)
  if env:
    return Path(env).expanduser()
  return Path('~/.cache/slotformer_jax').expanduser()


def resolve_data_dir(data_dir: str | os.PathLike[str] | None) -> Path:
  """``data_dir`` as a Path, or the default when it is None / empty."""
  if data_dir is None or not os.fspath(data_dir):
    return default_data_dir()
  return Path(data_dir).expanduser()


def generated_dir(data_dir: str | os.PathLike[str], name: str, slug: str
                  ) -> Path:
  """The TFDS version folder of generated dataset ``name`` whose generation
  parameters give ``slug``: the chunked layout's version (a 1.0.0 folder of
  an older checkout, whole-video records, is left alone and a 2.0.0 one
  generated)."""
  return Path(data_dir) / name / slug / chunked.TFDS_VERSION


def is_complete(dataset_dir: str | os.PathLike[str]) -> bool:
  """Whether a TFDS build finished in ``dataset_dir`` (a stat, no read)."""
  return (Path(dataset_dir) / _DATASET_INFO).is_file()


def not_generated(what: str, path: str | os.PathLike[str]
                  ) -> MissingInputError:
  """The one-line error of a reader that finds no generated ``what``."""
  return MissingInputError(
      f'{what} is not generated yet (no {os.fspath(path)}); generate it with '
      f'{PREPARE_COMMAND} (every --mode runs that stage first)')


def open_generated(what: str, dataset_dir: Path, split: str
                   ) -> TfdsVideoSource:
  """A split of a generated TFDS dataset, its checksums verified.

  Raises:
    MissingInputError: it is not generated (names the command).
    UserError: its checksums say it is damaged.
  """
  if not is_complete(dataset_dir):
    raise not_generated(what, dataset_dir)
  try:
    integrity.verify_checksums(dataset_dir, split)
  except integrity.DamagedDataset as error:
    raise UserError(f'{what} is damaged ({error}); {PREPARE_COMMAND} '
                    'regenerates it') from None
  return TfdsVideoSource(dataset_dir, split, fix=(
      f'Delete {dataset_dir}: it is regenerated on the next run.'))


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

  # Clips pass through (see TfdsVideoSource.clip).
  @property
  def supports_clips(self) -> bool:
    return bool(getattr(self.source, 'supports_clips', False))

  @property
  def time_fields(self) -> tuple[str, ...]:
    return tuple(getattr(self.source, 'time_fields', ()))

  def num_frames(self, index: int) -> int:
    return self.source.num_frames(index)

  def header(self, index: int) -> dict[str, Any]:
    return self.source.header(index)

  def clip(self, index: int, start: int, length: int, stride: int = 1,
           fields: Sequence[str] = ('video',)) -> dict[str, np.ndarray]:
    item = dict(self.source.clip(index, start, length, stride, fields))
    if 'video' in item:
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
