"""Kubric's MOVi (MOVi-A ... MOVi-F, TFDS): the datasets (one name per
variant, one converter), their layout and conversion.

Source: a TFDS version folder as on Kubric's public bucket
(``dataset_info.json``, ``features.json``, ``movi_<x>-<split>.tfrecord-*``),
read without TensorFlow (``data/tfrecord.py``, TFDS's NumPy Example parser
with specs from the download's ``features.json``, PIL for the PNGs).

Stored item (one per record, M rows for instances, row k - 1 = segmentation
id k): ``video`` uint8 [T, H, W, 3], ``segmentations`` uint8 [T, H, W],
``boxes`` float32 [T, M, 4] + ``visible`` bool [T, M] (CLEVRER's layout,
which AR reads), ``positions`` / ``velocities`` [T, M, 3],
``image_positions`` [T, M, 2], ``num_instances``, ``video_name``; and when
the download has them, ``forward_flow`` / ``backward_flow`` uint16
[T, H, W, 2] and ``depth`` uint16 [T, H, W, 1] in Kubric's encoding with
their ``<name>_range`` (decoded on reading: ``data/flow_depth.py``).
Splits: 'train', 'validation' -> 'val', 'test' (C/D/E). What is read, how
it is resized and what a damaged download gives: docs/datasets.md, "MOVi".
"""

from __future__ import annotations

import dataclasses
import functools
import io
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds
from google.protobuf.message import DecodeError
from PIL import Image

from slotformer_jax import targets
from slotformer_jax.data import flow_depth
from slotformer_jax.data import media
from slotformer_jax.data import tfrecord
from slotformer_jax.datasets import base
from slotformer_jax.errors import shown
from slotformer_jax.files import UntrustedFileError
from slotformer_jax.files import confined
from slotformer_jax.files import int_in_range
from slotformer_jax.files import read_untrusted_json

NAME = 'movi'
SPLITS: tuple[str, ...] = ('train', 'val', 'test')
# This project's split name -> MOVi's.
SOURCE_SPLITS: Mapping[str, str] = {
    'train': 'train', 'val': 'validation', 'test': 'test'}
DEFAULT_RESOLUTION = (64, 64)  # the SAVi paper's (SAVi-S)
# Most instances of a video per variant (Kubric's README; SAVi's configs use
# max_instances = 10 for A-C, 23 for D-E).
MAX_INSTANCES: Mapping[str, int] = {
    'movi_a': 10, 'movi_b': 10, 'movi_c': 10, 'movi_d': 23, 'movi_e': 23,
    'movi_f': 23}
# 2: flows and depth kept (folders of version 1 have neither).
CONVERTER_VERSION = 2

LAYOUT = """\
<source>/dataset_info.json, <source>/features.json
<source>/movi_X-train.tfrecord-00000-of-NNNNN ...
<source>/movi_X-validation.tfrecord-00000-of-NNNNN ...
<source>/movi_X-test.tfrecord-...   (MOVi-C/D/E)
(a TFDS version folder of Kubric's MOVi, e.g. a copy of
 gs://kubric-public/tfds/movi_a/128x128/1.0.0)"""

_VIDEO = 'video'
_SEGMENTATIONS = 'segmentations'
_POSITIONS = 'instances/positions'
_VELOCITIES = 'instances/velocities'
_IMAGE_POSITIONS = 'instances/image_positions'
_BBOXES = 'instances/bboxes'
_BBOX_FRAMES = 'instances/bbox_frames'
_NUM_INSTANCES = 'metadata/num_instances'
_VIDEO_NAME = 'metadata/video_name'
REQUIRED_FEATURES: tuple[str, ...] = (
    _VIDEO, _SEGMENTATIONS, _POSITIONS, _VELOCITIES, _IMAGE_POSITIONS,
    _BBOXES, _BBOX_FRAMES, _NUM_INSTANCES, _VIDEO_NAME)
# Flows and depth (the stored names are MOVi's): kept when the download has
# each with its range, in flow_depth.STORED's encoding.
FLOW_DEPTH: tuple[str, ...] = tuple(flow_depth.STORED)


def _range_key(name: str) -> str:
  return f'metadata/{flow_depth.range_field(name)}'


# ----------------------------------------------------------------------------
# features.json -> the serialized tensor specs of the Example protos
# ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Leaf:
  """How one feature of the tree is stored in the Example proto.

  Attributes:
    shape: the serialized shape (None: variable), sequence dimensions first;
      for encoded images only the sequence dimensions.
    dtype: numpy dtype name of the stored values ('bytes' for encoded images
      and text).
    sequence_rank: enclosing ``Sequence`` features (a ``Video`` counts one);
      >= 2 is stored ragged (``<key>/ragged_flat_values`` and
      ``<key>/ragged_row_lengths_<i>``), as TFDS's example serializer does.
    image_shape: (h, w, c) of an encoded image (frame), else None.
    image_dtype: dtype name of the decoded image, else ''.
  """

  shape: tuple[int | None, ...]
  dtype: str
  sequence_rank: int = 0
  image_shape: tuple[int | None, ...] | None = None
  image_dtype: str = ''


# What a downloaded features.json / dataset_info.json may hold (both are a
# few KB in every MOVi variant). A feature tree's numeric dtypes, by name;
# 'string' is TFDS's name for bytes.
_MAX_JSON_BYTES = 16 << 20
_MAX_JSON_DEPTH = 32
_NUMERIC_DTYPES = ('bool', 'int8', 'int16', 'int32', 'int64', 'uint8',
                   'uint16', 'uint32', 'uint64', 'float16', 'float32',
                   'float64')
# Source frames: MOVi has 24 frames of 128 or 256 (512 for MOVi-F) pixels.
MAX_SOURCE_SIDE = 1024
MAX_SOURCE_FRAMES = 1024
_MAX_SHARDS = 100_000
_MAX_SHARD_LENGTH = 10_000_000
# TFDS dataset names (snake case); also the output folder and shard prefix.
_DATASET_NAME = re.compile(r'[a-z][a-z0-9_]{0,63}')


class LayoutError(UntrustedFileError):
  """features.json or dataset_info.json is not what TFDS writes."""


def _object(value: Any, where: str) -> Mapping[str, Any]:
  if not isinstance(value, Mapping):
    raise LayoutError(f'features.json: {where} is a {type(value).__name__}, '
                      'not an object')
  return value


def _class_name(node: Mapping[str, Any], where: str) -> str:
  name = node.get('pythonClassName', node.get('type', ''))
  if not isinstance(name, str):
    raise LayoutError(f'features.json: {where}: the class name is a '
                      f'{type(name).__name__}, not a text')
  return name.rsplit('.', 1)[-1]


def _count(value: Any, where: str, *, most: int) -> int | None:
  """An int of features.json / dataset_info.json: JSON ints or the digit
  strings protobuf's JSON writes for int64 ('24'); None or < 0: variable."""
  if value is None:
    return None
  if isinstance(value, str) and re.fullmatch(r'-?[0-9]{1,12}', value):
    value = int(value)
  if isinstance(value, bool) or not isinstance(value, int):
    raise LayoutError(f'{where} is {shown(repr(value), 60)}, not an integer')
  if value > most:
    raise LayoutError(f'{where} is {value}, more than {most}')
  return None if value < 0 else value


def _dims(shape: Any, where: str) -> tuple[int | None, ...]:
  """A shape of either format: [24, 128, None] or {'dimensions': ['24', ...]}
  ('-1' / None: variable)."""
  if isinstance(shape, Mapping):
    shape = shape.get('dimensions', [])
  if shape is None:
    shape = []
  if not isinstance(shape, list) or len(shape) > 8:
    raise LayoutError(f'features.json: {where}: the shape '
                      f'{shown(repr(shape), 80)} is not a list of at most 8 '
                      'dimensions')
  return tuple(_count(d, f'features.json: {where}: a dimension',
                      most=1 << 31) for d in shape)


def _dtype(node: Mapping[str, Any], where: str, default: str | None) -> str:
  dtype = node.get('dtype', default)
  if dtype == 'string':
    return 'bytes'
  if dtype not in _NUMERIC_DTYPES:
    raise LayoutError(f'features.json: {where}: dtype '
                      f'{shown(repr(dtype), 60)} is not one of '
                      f'{", ".join(_NUMERIC_DTYPES)} or string')
  return dtype


def _content(node: Mapping[str, Any], class_name: str, where: str
             ) -> tuple[Mapping[str, Any], bool]:
  """(content, is_proto_json) of a feature node of either features.json
  format: TFDS >= 4.5 writes ``{"pythonClassName": ..., "<kind>": {...}}``
  (a FeatureConnector proto as JSON); older versions wrote
  ``{"type": ..., "content": ...}`` (``proto_cls`` set when the content is
  that proto as JSON)."""
  if 'pythonClassName' in node:
    kinds = [k for k in node if k not in ('pythonClassName', 'description',
                                          'valueRange')]
    if len(kinds) != 1:
      raise LayoutError(f'features.json: {where}: cannot read the '
                        f'{shown(class_name, 60)} node with keys '
                        f'{shown(sorted(node), 120)}')
    return _object(node[kinds[0]], where), True
  content = node.get('content', {})
  return _object({} if content is None else content, where), bool(
      node.get('proto_cls'))


def feature_leaves(node: Any, prefix: str = '') -> dict[str, Leaf]:
  """Every stored feature of a features.json tree: {'a/b': Leaf}.

  Handles the connectors MOVi uses (FeaturesDict, Sequence, Video, Image,
  Tensor, Scalar, BBoxFeature, ClassLabel, Text) in both file formats. The
  tree comes from a download: every field's type is checked (its depth is
  bounded by `read_untrusted_json`).

  Raises:
    LayoutError: an unknown connector or a node it cannot read (one line,
      naming the node).
  """
  where = shown(prefix.rstrip('/') or 'the top', 120)
  node = _object(node, where)
  name = _class_name(node, where)
  content, proto = _content(node, name, where)
  if name == 'FeaturesDict':
    children = _object(content.get('features', {}) if proto else content,
                       where)
    out: dict[str, Leaf] = {}
    for key, child in children.items():
      out.update(feature_leaves(child, f'{prefix}{key}/'))
    return out
  key = prefix.rstrip('/')
  if name == 'Sequence':
    length = _count(content.get('length'), f'features.json: {where}: the '
                    'length', most=1 << 31)
    inner = feature_leaves(content.get('feature'), prefix)
    return {k: dataclasses.replace(leaf, shape=(length,) + leaf.shape,
                                   sequence_rank=leaf.sequence_rank + 1)
            for k, leaf in inner.items()}
  if name in ('Video', 'Image'):
    shape = _dims(content.get('shape'), where)
    dtype = _dtype(content, where, 'uint8')
    if name == 'Image':
      return {key: Leaf(shape=(), dtype='bytes', image_shape=shape,
                        image_dtype=dtype)}
    if len(shape) != 4:
      raise LayoutError(f'features.json: {where}: a Video shape has 4 '
                        f'dimensions, got {shape}')
    return {key: Leaf(shape=shape[:1], dtype='bytes', sequence_rank=1,
                      image_shape=shape[1:], image_dtype=dtype)}
  if name in ('Tensor', 'Scalar'):
    encoding = content.get('encoding') or 'none'
    if not isinstance(encoding, str):
      raise LayoutError(f'features.json: {where}: the encoding is a '
                        f'{type(encoding).__name__}, not a text')
    if encoding.lower() != 'none':
      return {key: Leaf(shape=(), dtype='bytes')}
    return {key: Leaf(shape=_dims(content.get('shape'), where),
                      dtype=_dtype(content, where, None))}
  if name == 'BBoxFeature':
    return {key: Leaf(shape=(4,), dtype='float32')}
  if name == 'ClassLabel':
    return {key: Leaf(shape=(), dtype='int64')}
  if name == 'Text':
    return {key: Leaf(shape=(), dtype='bytes')}
  raise LayoutError(f'features.json: {where}: unknown feature connector '
                    f'{shown(repr(name), 80)}')


# ----------------------------------------------------------------------------
# The source folder
# ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SourceInfo:
  """What the converter needs to know of a downloaded MOVi folder.

  Attributes:
    folder: the TFDS version folder.
    name: the TFDS name, e.g. 'movi_a' (the output dataset's name).
    version: e.g. '1.0.0'.
    num_frames: T.
    resolution: (h, w) of the stored frames.
    shard_lengths: {MOVi split: records per shard}.
    leaves: (key, Leaf) of the features the parser is given: the ones read
      and every ragged one (the parser needs a spec for each of those).
    kept: the flows and depth (FLOW_DEPTH) the download has, kept.
  """

  folder: Path
  name: str
  version: str
  num_frames: int
  resolution: tuple[int, int]
  shard_lengths: Mapping[str, tuple[int, ...]]
  leaves: tuple[tuple[str, Leaf], ...]
  kept: tuple[str, ...] = ()


def layout_error(source: Path, missing: str) -> FileNotFoundError:
  return FileNotFoundError(
      f'MOVi: {missing}. Expected a TFDS version folder of MOVi under '
      f'--source={source}:\n{LAYOUT}')


def find_version_folder(source: Path) -> Path:
  """``source`` itself or the one folder up to two levels below it that
  holds dataset_info.json (e.g. ``movi_a/128x128`` -> ``.../1.0.0``)."""
  if (source / 'dataset_info.json').is_file():
    return source
  found = sorted({p.parent for pattern in ('*/dataset_info.json',
                                           '*/*/dataset_info.json')
                  for p in source.glob(pattern)})
  if len(found) == 1:
    return found[0]
  if not found:
    raise layout_error(source, f'no dataset_info.json in {source}')
  raise layout_error(source, 'several TFDS folders ('
                     + ', '.join(shown(str(p), 200) for p in found[:10])
                     + '): pass one of them')


def _load_json(path: Path) -> Any:
  try:
    return read_untrusted_json(path, what='MOVi metadata',
                               max_bytes=_MAX_JSON_BYTES,
                               max_depth=_MAX_JSON_DEPTH)
  except OSError as error:
    raise LayoutError(f'{path} cannot be read ({error.strerror or error}): '
                      'copy the MOVi folder again') from None


def dataset_name(info: Mapping[str, Any], folder: Path) -> str:
  """The download's TFDS name (movi_a ... movi_f): it names the shards read
  from ``folder`` and the folder written under ``--data_dir``, so it must
  be a plain TFDS name (see `files.confined`)."""
  name = info.get('name', '')
  confined(folder, name, what=f'{folder / "dataset_info.json"}: the name')
  if not _DATASET_NAME.fullmatch(name):
    raise LayoutError(f'{folder / "dataset_info.json"}: the name '
                      f"'{shown(name, 80)}' is not a TFDS dataset name "
                      '(lower case letters, digits and _, e.g. movi_a)')
  return name


def split_shard_lengths(info: Mapping[str, Any], path: Path
                        ) -> dict[str, tuple[int, ...]]:
  """{MOVi split: records per shard} of dataset_info.json's 'splits'."""
  splits = info.get('splits', [])
  if not isinstance(splits, list):
    raise LayoutError(f'{path}: "splits" is a {type(splits).__name__}, not '
                      'a list')
  shard_lengths = {}
  for number, split in enumerate(splits):
    where = f'{path}: split {number}'
    if not isinstance(split, Mapping) or not isinstance(split.get('name'),
                                                        str):
      raise LayoutError(f'{where} is not an object with a text "name"')
    lengths = split.get('shardLengths', split.get('shard_lengths', []))
    if not isinstance(lengths, list) or len(lengths) > _MAX_SHARDS:
      raise LayoutError(f'{where}: the shard lengths are not a list of at '
                        f'most {_MAX_SHARDS} counts')
    counts = tuple(_count(n, f'{where}: a shard length',
                          most=_MAX_SHARD_LENGTH) for n in lengths)
    if None in counts:
      raise LayoutError(f'{where}: a shard length is negative')
    shard_lengths[split['name']] = counts
  if not shard_lengths:
    raise LayoutError(f'{path} lists no splits')
  return shard_lengths


@functools.lru_cache(maxsize=8)
def read_source(source: Path) -> SourceInfo:
  """Reads and checks dataset_info.json and features.json of ``source``.

  Both come from a download: read with limits (size, depth), every field
  type-checked, the name confined to a plain TFDS name.

  Raises:
    FileNotFoundError: not a TFDS folder.
    ValueError: not MOVi (a required feature is missing), or a file that
      is not what TFDS writes (LayoutError).
  """
  folder = find_version_folder(Path(source))
  info = _load_json(folder / 'dataset_info.json')
  features_path = folder / 'features.json'
  if not features_path.is_file():
    raise layout_error(Path(source), f'{features_path} not found')
  tree = _load_json(features_path)
  if not isinstance(info, dict) or not isinstance(tree, dict):
    raise LayoutError(f'{folder}: dataset_info.json / features.json are not '
                      'JSON objects')
  name = dataset_name(info, folder)
  version = info.get('version', '')
  if not isinstance(version, str):
    raise LayoutError(f'{folder / "dataset_info.json"}: the version is a '
                      f'{type(version).__name__}, not a text')
  leaves = feature_leaves(tree)
  missing = [k for k in REQUIRED_FEATURES if k not in leaves]
  if missing:
    raise LayoutError(
        f'{features_path}: no {", ".join(missing)}: {name} is not '
        "a MOVi dataset (Kubric's challenges/movi/movi_*.py features)")
  video = leaves[_VIDEO]
  num_frames = video.shape[0]
  height, width = (video.image_shape or (None, None))[:2]
  if num_frames is None or height is None or width is None:
    raise LayoutError(f'{features_path}: video shape {video.shape} + '
                      f'{video.image_shape} is not fixed')
  channels = (video.image_shape or (None,) * 3)[2:]
  segmentation = (leaves[_SEGMENTATIONS].image_shape or (None,) * 3)[2:]
  if channels != (3,) or segmentation not in ((1,), (None,)):
    raise LayoutError(f'{features_path}: video frames of {channels} and '
                      f'segmentations of {segmentation} channels; MOVi has '
                      'RGB frames (3) and one-channel segmentations')
  if not (1 <= num_frames <= MAX_SOURCE_FRAMES
          and 1 <= min(height, width) <= max(height, width)
          <= MAX_SOURCE_SIDE):
    raise LayoutError(
        f'{features_path}: videos of {num_frames} frames of {height}x'
        f'{width}; MOVi has 24 frames of 128 to 512 pixels (this reader '
        f'takes up to {MAX_SOURCE_FRAMES} frames of up to '
        f'{MAX_SOURCE_SIDE}x{MAX_SOURCE_SIDE})')
  shard_lengths = split_shard_lengths(info, folder / 'dataset_info.json')
  kept = flow_depth_leaves(leaves, int(num_frames), int(height), int(width),
                           features_path)
  needed = set(REQUIRED_FEATURES) | {
      k for k, leaf in leaves.items() if leaf.sequence_rank >= 2} | set(
          kept) | {_range_key(k) for k in kept}
  return SourceInfo(
      folder=folder, name=name, version=version,
      num_frames=int(num_frames), resolution=(int(height), int(width)),
      shard_lengths=shard_lengths,
      leaves=tuple(sorted((k, v) for k, v in leaves.items() if k in needed)),
      kept=kept)


def flow_depth_leaves(leaves: Mapping[str, Leaf], num_frames: int,
                      height: int, width: int, where: Path
                      ) -> tuple[str, ...]:
  """The flows and depth of FLOW_DEPTH the download has (each with its
  range), checked to be what Kubric's builder declares: flows uint16
  tensors [T, h, w, 2], depth T uint16 images [h, w, 1], ranges float32 [2].

  Raises:
    LayoutError: one of them declared otherwise (or without its range).
  """
  kept = []
  for name in FLOW_DEPTH:
    if name not in leaves:
      continue
    leaf, range_leaf = leaves[name], leaves.get(_range_key(name))
    channels = flow_depth.STORED[name]
    if name == flow_depth.DEPTH:
      stated = (leaf.shape, leaf.image_shape, leaf.image_dtype)
      fine = stated == ((num_frames,), (height, width, channels), 'uint16')
    else:
      stated = (leaf.shape, leaf.dtype)
      fine = stated == ((num_frames, height, width, channels), 'uint16')
    fine = fine and leaf.sequence_rank == 1
    if not fine or range_leaf is None or (
        range_leaf.shape, range_leaf.dtype) != ((2,), 'float32'):
      raise LayoutError(
          f'{where}: {name} is declared as {shown(repr(stated), 120)} with '
          f'range {shown(repr(range_leaf), 120)}; MOVi stores it as '
          f'{num_frames} uint16 frames of {height}x{width}x{channels} with '
          f'a float32 (2,) {_range_key(name)}')
    kept.append(name)
  return tuple(kept)


def available_splits(source: Path) -> tuple[str, ...]:
  """This project's names of the splits the download has."""
  have = read_source(Path(source)).shard_lengths
  return tuple(s for s in SPLITS if SOURCE_SPLITS[s] in have)


# ----------------------------------------------------------------------------
# Options, jobs, conversion
# ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Options(base.ConversionOptions):
  """Conversion parameters.

  Attributes:
    resolution: (H, W) of the stored frames and segmentations.
    max_objects: M, rows of the per-instance arrays; None: the variant's
      most instances per video (MAX_INSTANCES).
  """

  resolution: tuple[int, int] = DEFAULT_RESOLUTION
  max_objects: int | None = None
  version = CONVERTER_VERSION

  def __post_init__(self):
    super().__post_init__()
    if self.max_objects is not None and not 1 <= self.max_objects <= 255:
      raise ValueError(f'max_objects must be in [1, 255], got '
                       f'{self.max_objects}')


def instance_rows(options: Options, source: SourceInfo) -> int:
  """M for this download."""
  if options.max_objects is not None:
    return options.max_objects
  if source.name not in MAX_INSTANCES:
    raise ValueError(f'{source.folder}: unknown MOVi variant '
                     f'{source.name!r}; pass --max_objects (rows for '
                     'instances)')
  return MAX_INSTANCES[source.name]


@dataclasses.dataclass(frozen=True)
class RecordJob:
  """One video: a record of a shard."""

  key: str  # '<shard file name>:<record index>'
  shard: Path
  span: tfrecord.RecordSpan


@dataclasses.dataclass(frozen=True)
class _Plan:
  """What a worker needs (picklable)."""

  leaves: tuple[tuple[str, Leaf], ...]
  num_frames: int
  source_resolution: tuple[int, int]
  resolution: tuple[int, int]
  rows: int
  kept: tuple[str, ...] = ()


def shard_paths(source: SourceInfo, split: str) -> list[Path]:
  """The shard files of a MOVi split, checked against dataset_info.json.

  Raises:
    FileNotFoundError: a listed shard is missing.
  """
  lengths = source.shard_lengths[split]
  count = len(lengths)
  paths = [source.folder / f'{source.name}-{split}.tfrecord-{i:05d}-of-'
           f'{count:05d}' for i in range(count)]
  missing = [p.name for p in paths if not p.is_file()]
  if missing:
    raise FileNotFoundError(
        f'{source.folder}: {len(missing)} of the {count} {split} shards '
        f'listed in dataset_info.json are missing, e.g. {missing[0]} (an '
        'incomplete download: copy the folder again, e.g. gsutil -m cp -r '
        f'gs://kubric-public/tfds/{source.name}/<resolution>/'
        f'{source.version or "1.0.0"} .)')
  return paths


def discover(source: Path, split: str, options: Options) -> list[RecordJob]:
  """Every record of ``split``, in shard order.

  Reads the record headers of every shard (their length checksums
  included): a truncated or damaged shard fails here, before any video is
  converted.

  Raises:
    FileNotFoundError: the split or a shard is missing.
    tfrecord.TFRecordError: a truncated / damaged shard, or one whose record
      count differs from dataset_info.json.
  """
  del options  # the listing does not depend on them
  info = read_source(Path(source))
  movi_split = SOURCE_SPLITS[split]
  if movi_split not in info.shard_lengths:
    raise layout_error(
        Path(source), f'{info.name} has no {movi_split!r} split (it has '
        f'{shown(", ".join(sorted(info.shard_lengths)), 200)})')
  jobs = []
  for path, expected in zip(shard_paths(info, movi_split),
                            info.shard_lengths[movi_split]):
    spans = tfrecord.index_records(path)
    if len(spans) != expected:
      raise tfrecord.TFRecordError(
          f'{path}: {len(spans)} records, dataset_info.json says {expected} '
          '(a damaged or partial file: download it again)')
    jobs += [RecordJob(key=f'{path.name}:{s.index}', shard=path, span=s)
             for s in spans]
  return jobs


def _is_int(leaf: Leaf) -> bool:
  return leaf.dtype != 'bytes' and np.dtype(leaf.dtype).kind in 'iu'


@functools.lru_cache(maxsize=4)
def _parser(leaves: tuple[tuple[str, Leaf], ...]
            ) -> tfds.core.example_parser.ExampleParserNp:
  """Integer features as the int64 the proto holds (`_declared_ints` casts
  them once checked: the parser would wrap 2**32 + 5 to 5 in int32)."""
  string = tfds.features.Text().get_serialized_info().np_dtype
  specs = {key: tfds.features.TensorInfo(
      shape=leaf.shape, dtype=string if leaf.dtype == 'bytes'
      else np.dtype(np.int64) if _is_int(leaf) else np.dtype(leaf.dtype),
      sequence_rank=leaf.sequence_rank)
           for key, leaf in leaves}
  return tfds.core.example_parser.ExampleParserNp(specs)


def _declared_ints(example: dict[str, Any], leaves: tuple[tuple[str, Leaf],
                                                          ...], where: str
                   ) -> dict[str, Any]:
  """`example` with every integer feature checked to fit the dtype
  features.json declares (uint16 instance counts, int32 frame indices)
  and cast to it.

  Raises:
    UntrustedFileError: a value outside that dtype, naming the feature.
  """
  for key, leaf in leaves:
    if key not in example or not _is_int(leaf):
      continue
    info = np.iinfo(np.dtype(leaf.dtype))
    def cast(value, key=key, leaf=leaf, info=info):
      return int_in_range(np.asarray(value, np.int64), int(info.min),
                          int(info.max), what=f'{where}: {key}'
                          ).astype(leaf.dtype)
    value = example[key]
    example[key] = ([cast(v) for v in value] if isinstance(value, list)
                    else cast(value))
  return example


def _decode_png(data: bytes, shape: Sequence[int | None], where: str,
                dtype: str = 'uint8') -> np.ndarray:
  """One frame; its size is checked from the PNG header before anything is
  decoded (a header may claim 10^6 x 10^6 pixels, a real frame may be far
  larger than features.json says), its bit depth after (`dtype`, what
  features.json declares: 'uint8', or 'uint16' for MOVi's depth)."""
  want = tuple(d for d in shape)
  stated = media.png_size(data[:24])
  if stated is None:
    raise ValueError(f'{where}: a frame that is not a PNG')
  if (stated[1], stated[0]) != tuple(want[:2]):
    raise ValueError(f'{where}: a {stated[1]}x{stated[0]} frame (its PNG '
                     f'header), features.json says {want[0]}x{want[1]}')
  with warnings.catch_warnings():
    # PIL's own bomb check warns first: an error here, the size check below
    # names it.
    warnings.simplefilter('error', Image.DecompressionBombWarning)
    try:
      image = Image.open(io.BytesIO(data), formats=['PNG'])
    except Image.DecompressionBombError as error:
      raise ValueError(f'{where}: {shown(str(error), 200)}') from None
    with image:
      width, height = image.size
      if (height, width) != tuple(want[:2]):
        raise ValueError(f'{where}: a {height}x{width} frame (its PNG '
                         f'header), features.json says {want[0]}x{want[1]}')
      image.load()
      array = np.asarray(image)
  if array.ndim == 2:
    array = array[..., None]
  array = _image_values(array, dtype, where)
  if array.shape[:2] != want[:2] or (want[2] is not None
                                     and array.shape[2] < want[2]):
    raise ValueError(f'{where}: a {array.shape} frame, features.json says '
                     f'{want}')
  return array[..., :want[2]] if want[2] is not None else array


def _image_values(array: np.ndarray, dtype: str, where: str) -> np.ndarray:
  """A decoded PNG's values as `dtype`: 8-bit PNGs for uint8; 16-bit ones
  (PIL: uint16, or int32 in older versions, range-checked) for uint16."""
  if dtype == 'uint8' and array.dtype == np.uint8:
    return array
  if dtype == 'uint16' and array.dtype.kind in 'iu' and array.dtype != np.uint8:
    return int_in_range(array, 0, 65535, what=where).astype(np.uint16)
  raise ValueError(f'{where}: a PNG of {array.dtype} values, features.json '
                   f'says {dtype}')


def _frames(example: Mapping[str, Any], key: str, leaf: Leaf, num_frames: int,
            where: str) -> np.ndarray:
  encoded = list(example[key])
  if len(encoded) != num_frames:
    raise ValueError(f'{where}: {key} has {len(encoded)} frames, '
                     f'features.json says {num_frames}')
  return np.stack([_decode_png(bytes(e), leaf.image_shape or (None,) * 3,
                               f'{where} {key}', leaf.image_dtype or 'uint8')
                   for e in encoded])


def _flow_depth(example: Mapping[str, Any], plan: _Plan, where: str
                ) -> dict[str, np.ndarray]:
  """{name: uint16 [T, h, w, C], name_range: float32 [2]} of the kept
  flows and depth of a record, checked (shape, values, range).

  Raises:
    ValueError: a field missing or not what features.json says.
  """
  leaves = dict(plan.leaves)
  out = {}
  for name in plan.kept:
    missing = [k for k in (name, _range_key(name)) if k not in example]
    if missing:
      raise ValueError(f'{where}: the Example has no {", ".join(missing)}')
    channels = flow_depth.STORED[name]
    if name == flow_depth.DEPTH:
      values = _frames(example, name, leaves[name], plan.num_frames, where)
    else:
      values = np.asarray(example[name])
    want = (plan.num_frames, *plan.source_resolution, channels)
    if values.shape != want or values.dtype != np.uint16:
      raise ValueError(f'{where}: {name} is {values.dtype} {values.shape}, '
                       f'features.json says uint16 {want}')
    out[name] = values
    out[flow_depth.range_field(name)] = flow_depth.check_range(
        example[_range_key(name)], name, what=where)
  return out


def _resized_flow_depth(fields: Mapping[str, np.ndarray],
                        resolution: Sequence[int]) -> dict[str, np.ndarray]:
  """The stored flows and depth of `_flow_depth` at `resolution`: the
  pixels `media.resize_labels` takes; flows rescaled and encoded again."""
  out = {}
  for name in flow_depth.STORED:
    if name not in fields:
      continue
    values = fields[name]
    value_range = fields[flow_depth.range_field(name)]
    source = values.shape[1:3]
    picked = np.moveaxis(media.resize_labels(np.moveaxis(values, -1, 1),
                                             resolution), 1, -1)
    if name != flow_depth.DEPTH:
      scale = (resolution[0] / source[0], resolution[1] / source[1])
      picked, value_range = flow_depth.encode(flow_depth.rescale_flow(
          flow_depth.decode(picked, value_range), scale))
    out[name] = np.ascontiguousarray(picked, np.uint16)
    out[flow_depth.range_field(name)] = value_range
  return out


def _per_instance(example: Mapping[str, Any], key: str, count: int,
                  num_frames: int, width: int, where: str) -> np.ndarray:
  """float32 [count, T, width] (an empty video gives [0, T, width])."""
  values = np.asarray(example.get(key, np.zeros((0,))), np.float32)
  if values.size != count * num_frames * width:
    raise ValueError(f'{where}: {key} holds {values.size} values, '
                     f'{count} instances x {num_frames} frames x {width} '
                     'expected')
  return values.reshape(count, num_frames, width)


def _pad_rows(values: np.ndarray, rows: int) -> np.ndarray:
  """[n, T, ...] instances -> [T, rows, ...] (zeros after n, cut at rows)."""
  out = np.zeros((values.shape[1], rows) + values.shape[2:], np.float32)
  kept = min(rows, values.shape[0])
  out[:, :kept] = np.swapaxes(values[:kept], 0, 1)
  return out


def convert_record(job: RecordJob, plan: _Plan) -> dict[str, Any]:
  """Reads, checks and converts one MOVi record.

  Raises:
    base.ConversionError: a damaged record (checksum, Example proto, PNG,
      or content that contradicts features.json), naming the file.
  """
  where = f'{job.shard} record {job.span.index}'
  try:
    data = tfrecord.read_record(job.shard, job.span)
    example = _declared_ints(_parser(plan.leaves).parse_example(data),
                             plan.leaves, where)
    missing = [k for k in REQUIRED_FEATURES
               if k not in example and k not in (_BBOXES, _BBOX_FRAMES)]
    if missing:
      raise ValueError(f'{where}: the Example has no {", ".join(missing)}')
    leaves = dict(plan.leaves)
    video = _frames(example, _VIDEO, leaves[_VIDEO], plan.num_frames, where)
    segmentations = _frames(example, _SEGMENTATIONS, leaves[_SEGMENTATIONS],
                            plan.num_frames, where)[..., 0]
    count = int(example[_NUM_INSTANCES])
    t = plan.num_frames
    positions = _per_instance(example, _POSITIONS, count, t, 3, where)
    velocities = _per_instance(example, _VELOCITIES, count, t, 3, where)
    image_positions = _per_instance(example, _IMAGE_POSITIONS, count, t, 2,
                                    where)
    # Ragged: one array per instance ([] when no instance / never visible).
    boxes_ragged = list(example.get(_BBOXES, []))
    frames_ragged = list(example.get(_BBOX_FRAMES, []))
    if len(boxes_ragged) not in (0, count) or len(frames_ragged) != len(
        boxes_ragged):
      raise ValueError(f'{where}: bboxes of {len(boxes_ragged)} and '
                       f'bbox_frames of {len(frames_ragged)} instances, '
                       f'num_instances is {count}')
    largest = int(segmentations.max(initial=0))
    if largest > count:
      raise ValueError(f'{where}: segmentation id {largest} but only '
                       f'{count} instances')
    video_name = _text(example[_VIDEO_NAME])
    stored = _flow_depth(example, plan, where)
  except tfrecord.TFRecordError as error:
    raise base.ConversionError(f'{error}: download this file again') from None
  except (Exception, DecodeError) as error:  # pylint: disable=broad-except
    # A record that passed its checksum but does not decode (protobuf, PNG,
    # shapes, a name that is not UTF-8): the file was written wrongly or is
    # not MOVi; name it. Anything the parsers raise on crafted bytes counts.
    detail = shown(str(error).splitlines()[0], 300) if str(error) else ''
    raise base.ConversionError(
        f'{where}: unreadable MOVi example ({type(error).__name__}: '
        f'{detail}); download this file again') from None

  rows = plan.rows
  boxes = np.zeros((t, rows, 4), np.float32)
  visible = np.zeros((t, rows), bool)
  for k, (frame_list, box_list) in enumerate(zip(frames_ragged,
                                                 boxes_ragged)):
    if k >= rows:
      break
    frame_list = np.asarray(frame_list, np.int64).reshape(-1)
    box_list = np.asarray(box_list, np.float32).reshape(-1, 4)
    if len(frame_list) != len(box_list) or (
        len(frame_list) and not 0 <= frame_list.min() <= frame_list.max() < t):
      raise base.ConversionError(
          f'{where}: instance {k} has {len(box_list)} boxes for frames '
          f'{frame_list.tolist()}; download this file again')
    boxes[frame_list, k] = box_list
    visible[frame_list, k] = True
  # Ids above M: background, as SAVi's sparse_to_dense_annotation.
  segmentations = np.where(segmentations <= rows, segmentations, 0)
  if tuple(plan.resolution) != tuple(video.shape[1:3]):
    video = media.resize_frames(video, plan.resolution)
    segmentations = media.resize_labels(segmentations, plan.resolution)
    stored = _resized_flow_depth(stored, plan.resolution)
  return {
      **stored,
      'video': video.astype(np.uint8),
      'segmentations': segmentations.astype(np.uint8),
      'boxes': boxes, 'visible': visible,
      'positions': _pad_rows(positions, rows),
      'velocities': _pad_rows(velocities, rows),
      'image_positions': _pad_rows(image_positions, rows),
      'num_instances': np.int32(count),
      'video_name': video_name,
  }


def _text(value: Any) -> str:
  """A text field of a record; raises UnicodeDecodeError when it is not
  UTF-8 (TFDS writes text as UTF-8)."""
  if isinstance(value, np.ndarray):
    value = value.reshape(-1)[0] if value.size else b''
  return value.decode('utf-8') if isinstance(value, bytes) else str(value)


def features(num_frames: int, resolution: Sequence[int], rows: int,
             kept: Sequence[str] = FLOW_DEPTH) -> tfds.features.FeaturesDict:
  h, w = resolution
  t = num_frames
  stored = {}
  for name in kept:
    stored[name] = base.tensor((t, h, w, flow_depth.STORED[name]), np.uint16)
    stored[flow_depth.range_field(name)] = base.tensor((2,), np.float32)
  return tfds.features.FeaturesDict({
      **stored,
      'video': base.tensor((t, h, w, 3), np.uint8),
      'segmentations': base.tensor((t, h, w), np.uint8),
      'boxes': base.tensor((t, rows, 4), np.float32),
      'visible': base.tensor((t, rows), np.bool_),
      'positions': base.tensor((t, rows, 3), np.float32),
      'velocities': base.tensor((t, rows, 3), np.float32),
      'image_positions': base.tensor((t, rows, 2), np.float32),
      'num_instances': base.tensor((), np.int32),
      'video_name': tfds.features.Text(),
  })


def conversion(options: Options, source: Path) -> base.Conversion:
  info = read_source(Path(source))
  rows = instance_rows(options, info)
  h, w = options.resolution
  params = {
      'resolution': list(options.resolution), 'max_objects': rows,
      'source': {'name': info.name, 'version': info.version,
                 'resolution': list(info.resolution),
                 'num_frames': info.num_frames},
      'kept': list(info.kept),
      'converter_version': CONVERTER_VERSION}
  plan = _Plan(leaves=info.leaves, num_frames=info.num_frames,
               source_resolution=info.resolution,
               resolution=options.resolution, rows=rows, kept=info.kept)
  sh, sw = info.resolution
  kept = (f' {", ".join(info.kept)} (uint16 + range).' if info.kept
          else '')
  return base.Conversion(
      name=info.name,
      config_name=base.digest_name(f'r{h}x{w}_t{info.num_frames}_m{rows}',
                                     params),
      description=(f'Kubric {info.name} {info.version} ({sh}x{sw} TFDS) at '
                   f'{h}x{w}: video, instance segmentations (0 background, '
                   f'k = instance k - 1, ids above {rows} dropped), boxes, '
                   f'positions, velocities.{kept}'),
      params=params,
      features_fn=functools.partial(features, info.num_frames,
                                    options.resolution, rows, info.kept),
      convert_fn=functools.partial(convert_record, plan=plan))


def _convert_again(dataset: base.Converted,
                   data_config: Any) -> str:
  return (f'the converted {data_config.name} videos have no flow and depth '
          '(converted before the converter kept them, version '
          f'{CONVERTER_VERSION}, or from a download without them): convert '
          f'the download again, {dataset.conversion_command(data_config)} '
          '(a folder of its own next to the old one: delete the old one, or '
          'set data.prepared_config to the new one)')


# One name per variant: `data.name='movi_a'` reads what --dataset=movi made of
# a MOVi-A download.
DATASET = base.register(base.Converted(
    names=tuple(MAX_INSTANCES), label='MOVi', command=NAME, splits=SPLITS,
    layout=LAYOUT,
    # The paper's version: SAVi's 24 frames at 64x64, MOVi-A/B/C's rows.
    features=functools.partial(features, 24, DEFAULT_RESOLUTION,
                               MAX_INSTANCES['movi_a']),
    options=Options, discover=discover, conversion=conversion,
    available_splits=available_splits,
    download='/path/to/{name}/128x128/1.0.0',
    field_fixes={field: _convert_again for field in (
        targets.FLOW.field, targets.DEPTH.field, flow_depth.BACKWARD_FLOW,
        flow_depth.FORWARD_FLOW)}))
