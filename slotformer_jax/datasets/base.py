"""One dataset behind one small interface, and the registry of them by name.

A dataset module (``datasets/<name>.py``, or a file of your own) describes
one dataset and registers it at import (:func:`register`); everything else
finds it by ``config.data.name`` (:func:`get`). What it says of itself:

* its spec: the ``data.name`` values it answers, the features a video holds
  at its paper's version (frames, resolution, fields and dtypes), the channel
  order the official models saw, its evaluation clips beyond 'first';
* where it lives and how it is opened (:meth:`Dataset.open`);
* how it is made: a :class:`Converted` dataset lists the videos of its
  published download and converts one video into one example, which
  ``data/write/convert.py`` writes (``python -m slotformer_jax.data.prepare
  --dataset=<command>``); a :class:`Generated` one makes its folder from the
  generation parameters of ``config.data``, writing through the
  :class:`Output` the data stage hands it.

Reading never writes: a dataset module imports no writer (``data/write/``)
and writes no file itself (tests/test_layout.py), so opening a dataset can
never make one.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Protocol, TypeVar

import ml_collections
import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import chunked
from slotformer_jax.data import flow_depth
from slotformer_jax.data import integrity
from slotformer_jax.data import sources
from slotformer_jax.data.video_names import read_recorded_names
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.files import confined

T = TypeVar('T')

# `evaluation.clips` of every dataset: each video from its first frame.
FIRST_CLIPS = 'first'
# (videos, num_videos, burn_in, rollout, frame_stride) -> (video, start) of
# every evaluated clip of the first `num_videos` videos; frames are
# `start + i * frame_stride` for i < burn_in + rollout.
ClipRule = Callable[[Any, int, int, int, int], list[tuple[int, int]]]
# Stored tensors as raw bytes: the fastest numpy round trip (measured:
# docs/datasets.md, "Record layout").
TENSOR_ENCODING = tfds.features.Encoding.BYTES


def tensor(shape: Sequence[int | None], dtype: Any) -> tfds.features.Tensor:
  """A raw-bytes tensor feature (None in ``shape``: variable length)."""
  return tfds.features.Tensor(shape=tuple(shape), dtype=dtype,
                              encoding=TENSOR_ENCODING)


def digest_name(readable: str, params: Mapping[str, Any]) -> str:
  """``<readable>_<8 hex digits of a hash of params>``: a folder name that
  shows the main parameters and changes with any of them."""
  payload = json.dumps(dict(params), sort_keys=True, default=str)
  return f'{readable}_{hashlib.sha256(payload.encode()).hexdigest()[:8]}'


@dataclasses.dataclass(frozen=True)
class Dataset:
  """What every dataset says of itself, and how it is opened.

  Attributes:
    names: the ``config.data.name`` values it answers (MOVi: one per
      variant).
    label: its name in messages ('CLEVRER').
    features: ``() -> FeaturesDict``, what one video holds at the paper's
      version (field names, shapes with T first, dtypes).
    splits: the splits it has (or can have: a conversion may leave some
      out); every split a config names must be one of them.
    official_channel_order: 'rgb' / 'bgr', the channel order of the frames
      the official SlotFormer models of this dataset saw (a converted
      checkpoint must be read with it); None: no official model.
    clip_rules: the ``evaluation.clips`` it offers beyond 'first', by name.
    task_data: {task: ``(data_config, Output) -> None``}: what a task reads
      besides the videos, made by the data stage with them.
    field_fixes: {served field: ``(dataset, data_config) -> str``}, how
      to get a field its videos can have but those of ``data_config`` may
      lack (MOVi's flow: convert again; the OBJ3D-like family's: generate
      with ``data.with_flow_depth``), named when a run needs it.
  """

  names: tuple[str, ...]
  label: str
  features: Callable[[], tfds.features.FeaturesDict]
  splits: tuple[str, ...] = ()
  official_channel_order: str | None = None
  clip_rules: Mapping[str, ClipRule] = dataclasses.field(
      default_factory=dict)
  task_data: Mapping[str, Callable[[ml_collections.ConfigDict, Output], Any]
                     ] = dataclasses.field(default_factory=dict)
  field_fixes: Mapping[str, Callable[[Any, ml_collections.ConfigDict], str]
                       ] = dataclasses.field(default_factory=dict)

  @property
  def frames(self) -> int | None:
    """T of the paper's version (None: it varies per video)."""
    return self.features()['video'].shape[0]

  @property
  def resolution(self) -> tuple[int, int]:
    """(H, W) of the paper's version."""
    return tuple(self.features()['video'].shape[1:3])

  def open(self, data_config: ml_collections.ConfigDict, split: str
           ) -> sources.VideoSource:
    """The videos of ``split`` (never makes them).

    Raises:
      MissingInputError: they are not there (names the command).
      UserError: their recorded checksums say they are damaged.
    """
    raise NotImplementedError

  def num_frames(self, data_config: ml_collections.ConfigDict) -> int | None:
    """Frames per video known without the data (None: read them)."""
    del data_config
    return None

  def served_fields(self, data_config: ml_collections.ConfigDict
                    ) -> tuple[str, ...] | None:
    """The fields ``open`` serves a video with, when known without the
    data (a generated dataset's, from its parameters); None: read them."""
    del data_config
    return None

  def config_problems(self, data_config: ml_collections.ConfigDict
                      ) -> list[str]:
    """The problems of ``config.data`` that it knows, one line each,
    before any work (a generated dataset's are its parameters')."""
    del data_config
    return []

  def field_fix(self, data_config: ml_collections.ConfigDict, field: str
                ) -> str | None:
    """How to get a video field a run needs that the videos of
    ``data_config`` lack (``field_fixes``); None: it has no such field."""
    fix = self.field_fixes.get(field)
    return None if fix is None else fix(self, data_config)

  def video_names(self, data_config: ml_collections.ConfigDict, split: str
                  ) -> list[str]:
    """The name of every video of ``split``, in record (= slot row) order:
    what joins question files to the videos (``data/video_names.py``)."""
    del data_config, split
    raise ConfigError(f'the {self.label} videos have no names to join '
                      'questions to')

  def questions_root(self, data_config: ml_collections.ConfigDict
                     ) -> Path | None:
    """The folder holding its VQA ``questions/`` (and ``vocab.json``);
    None: not the dataset's (``vqa.questions_root`` names it)."""
    del data_config
    return None


def clips_problem(name: str, clips: str) -> str | None:
  """The config line of an ``evaluation.clips`` that dataset ``name`` does
  not offer, or None."""
  offered = (FIRST_CLIPS, *get(name).clip_rules)
  if clips in offered:
    return None
  return (f'evaluation.clips must be one of {", ".join(map(repr, offered))} '
          f'for data.name={name!r}, got {clips!r}')


# ----------------------------------------------------------------------------
# Converted datasets
# ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ConversionOptions:
  """What every conversion is given (a converter's ``Options`` extends it):
  the stored resolution, checked, and the parameters that name the folder.

  ``version`` (the converter's) is part of the folder name: bump it when
  the stored content changes for identical options.
  """

  resolution: tuple[int, int] = (64, 64)
  version: ClassVar[int] = 1

  def __post_init__(self):
    object.__setattr__(self, 'resolution',
                       tuple(int(r) for r in self.resolution))
    if len(self.resolution) != 2 or min(self.resolution) < 8:
      raise ValueError(f'resolution must be (H, W) >= 8, got {self.resolution}')
    # A dataset whose length comes from the download (MOVi) has no option.
    num_frames = getattr(self, 'num_frames', None)
    if num_frames is not None and num_frames < 1:
      raise ValueError(f'num_frames must be >= 1, got {num_frames}')

  @property
  def params(self) -> dict[str, Any]:
    """Everything the stored content depends on (JSON-serialisable)."""
    return {**dataclasses.asdict(self), 'converter_version': self.version}

  @property
  def config_name(self) -> str:
    """The conversion folder: ``r<H>x<W>_t<T>_<hash of params>``."""
    h, w = self.resolution
    return digest_name(f'r{h}x{w}_t{getattr(self, "num_frames")}',
                       self.params)


@dataclasses.dataclass(frozen=True)
class Conversion:
  """What to write and how to make one example (``data/write/convert.py``).

  Attributes:
    name: dataset name; the top folder and the shard-file prefix.
    config_name: sub-folder encoding the conversion parameters.
    description: free text stored in ``dataset_info.json``.
    params: JSON-serialisable conversion parameters; recorded in the
      manifest (a resumed run must use the same) and in the report.
    features_fn: picklable ``() -> tfds.features.FeaturesDict``.
    convert_fn: picklable ``job -> example dict`` (numpy arrays / scalars /
      str matching the features); raises ``media.SkipVideo``.
  """

  name: str
  config_name: str
  description: str
  params: Mapping[str, Any]
  features_fn: Callable[[], tfds.features.FeaturesDict]
  convert_fn: Callable[[Any], dict[str, Any]]

  def dataset_dir(self, data_dir: str | os.PathLike[str]) -> Path:
    """``<data_dir>/<name>/<config_name>/<version>``.

    Raises:
      OutsideFolderError: a name (made from a downloaded file's fields:
        MOVi's dataset name, PHYRE's eval setup) that would lead out of
        ``data_dir``.
    """
    top = confined(data_dir, self.name, what='the dataset name')
    return confined(top, self.config_name,
                    what='the conversion folder name') / chunked.TFDS_VERSION


class ConversionError(RuntimeError):
  """The conversion cannot (yet) produce a trustworthy dataset (a damaged
  download, an unfinished conversion with other inputs, too many skipped
  videos): one line naming the file and the fix."""


def layout_error(label: str, layout: str, source: Path, missing: Path,
                 detail: str = '', *, what: str = 'the published layout'
                 ) -> FileNotFoundError:
  """The error for a missing part of a download's layout."""
  return FileNotFoundError(
      f'{label}: {missing} not found{detail}. Expected {what} under '
      f'--source={source}:\n{layout}')


@dataclasses.dataclass(frozen=True)
class Converted(Dataset):
  """A dataset converted from its published download.

  Attributes:
    command: its ``prepare --dataset`` value (MOVi: 'movi' for every
      variant: the download names the variant).
    layout: the download's layout, shown when a part is missing.
    options: its conversion parameters (a :class:`ConversionOptions`); the
      prepare flags set the fields of the same names.
    discover: ``(source, split, options) -> jobs`` of the split, in record
      order (each with a unique, stable ``key``).
    convert: ``(job, options) -> example``: one video (picklable).
    stored: ``options -> FeaturesDict`` of the converted videos.
    describe: ``options -> str``, stored in ``dataset_info.json``.
    conversion: ``(options, source) -> Conversion``, where the output
      depends on the download (replaces ``convert``, ``stored`` and
      ``describe``).
    available_splits: ``source -> splits`` the download has (None: all).
    download: the download in the commands of the error lines ('{name}':
      the dataset name).
  """

  command: str = ''
  layout: str = ''
  options: type[ConversionOptions] = ConversionOptions
  discover: Callable[[Path, str, Any], Sequence[Any]] | None = None
  convert: Callable[..., dict[str, Any]] | None = None
  stored: Callable[[Any], tfds.features.FeaturesDict] | None = None
  describe: Callable[[Any], str] | None = None
  conversion: Callable[[Any, Path], Conversion] | None = None
  available_splits: Callable[[Path], tuple[str, ...]] | None = None
  download: str = '/path/to/download'

  def spec(self, options: ConversionOptions, source: Path) -> Conversion:
    """What converting ``source`` with ``options`` writes."""
    if self.conversion is not None:
      return self.conversion(options, source)
    return Conversion(
        name=self.names[0], config_name=options.config_name,
        description=self.describe(options), params=options.params,
        features_fn=functools.partial(self.stored, options),
        convert_fn=functools.partial(self.convert, options=options))

  def source_of(self, data_config: ml_collections.ConfigDict
                ) -> Path | None:
    """The download the data stage converts itself, from ``config.data``
    (a folder of videos: ``data.source``); None: converted by the prepare
    command only."""
    del data_config
    return None

  def options_of(self, data_config: ml_collections.ConfigDict
                 ) -> ConversionOptions:
    """The conversion options of ``config.data`` (with ``source_of``)."""
    raise NotImplementedError

  # -- reading ---------------------------------------------------------------

  def conversion_command(self, data_config: ml_collections.ConfigDict) -> str:
    """The prepare command that makes the dataset ``data_config`` names."""
    data_dir = sources.resolve_data_dir(data_config.data_dir)
    download = self.download.format(name=data_config.name)
    return (f'python -m slotformer_jax.data.prepare --dataset={self.command} '
            f'--source={download} --data_dir={data_dir}')

  def reconversion_command(self, data_config: ml_collections.ConfigDict
                           ) -> str:
    """What converts a damaged dataset again."""
    return (f'{self.conversion_command(data_config)} --overwrite (with the '
            'options it was converted with)')

  def dataset_dir(self, data_config: ml_collections.ConfigDict) -> Path:
    """The TFDS version folder ``data_config`` names (``prepared_config``
    and ``resolution`` pick among several conversions).

    Raises:
      MissingInputError: it is not converted (names the command).
      FileNotFoundError, ValueError: see ``sources.find_prepared_dataset``.
    """
    name = data_config.name
    path = sources.resolve_data_dir(data_config.data_dir) / name
    if not path.is_dir() or not sources.find_dataset_dirs(path):
      raise MissingInputError(
          f'Dataset {name!r} is not prepared: expected an array_record TFDS '
          f'folder under {path}. Convert it first with\n'
          f'  {self.conversion_command(data_config)}')
    if data_config.prepared_config:
      path = path / data_config.prepared_config
    return sources.find_prepared_dataset(path,
                                         resolution=data_config.resolution)

  def damaged(self, data_config: ml_collections.ConfigDict,
              error: integrity.DamagedDataset) -> UserError:
    """The error of a conversion whose checksums say it is damaged."""
    return UserError(f'the converted {data_config.name} dataset is damaged: '
                     f'{error}. Convert it again: '
                     f'{self.reconversion_command(data_config)}')

  def open(self, data_config: ml_collections.ConfigDict, split: str
           ) -> sources.VideoSource:
    source = sources.TfdsVideoSource(
        self.dataset_dir(data_config), split,
        fix=f'Convert it again: {self.reconversion_command(data_config)}')
    try:
      integrity.verify_checksums(source.dataset_dir, split)
    except integrity.DamagedDataset as error:
      raise self.damaged(data_config, error) from None
    return flow_depth.serve(
        sources.with_channel_order(source, data_config.channel_order),
        source.info.features)

  def video_names(self, data_config: ml_collections.ConfigDict, split: str
                  ) -> list[str]:
    """The keys the conversion recorded (``video_names.json``).

    Raises:
      UserError: the folder records none (names the command that converts
        it again).
    """
    dataset_dir = self.dataset_dir(data_config)
    names = read_recorded_names(dataset_dir, split)
    if names is None:
      raise UserError(
          f'{dataset_dir} records no video names for split {split!r} '
          '(converted by an older version, and its _progress/ files are '
          'gone), so questions cannot be joined to its videos by name; '
          f'convert it again: {self.reconversion_command(data_config)}')
    return names


# ----------------------------------------------------------------------------
# Generated (embedded) datasets
# ----------------------------------------------------------------------------


class Output(Protocol):
  """What a generator writes with: the data stage makes one per dataset
  (``data/write/generate.py``). Paths are absolute; every file appears
  whole (written to a temporary name, then renamed)."""

  data_dir: Path

  def map(self, make: Callable[[int], T], count: int) -> Iterator[T]:
    """``make(0), ..., make(count - 1)`` in order, in the data config's
    ``num_workers`` processes (``make`` picklable, a function of its index
    alone)."""

  def tfds_folder(self, path: Path, *, name: str,
                  features: tfds.features.FeaturesDict, description: str,
                  split_sizes: Mapping[str, int],
                  make: Callable[[str, int], dict[str, Any]],
                  metadata: Mapping[str, Any] | None = None,
                  lock: str | None = None) -> Path:
    """The TFDS version folder ``path`` (chunked layout, checksums), unless
    it is complete: split ``s`` holds ``make(s, 0), make(s, 1), ...``
    (picklable); ``lock``: made under a lock file named in its errors as
    ``lock``, so processes sharing the data dir make it once."""

  def save_array(self, path: Path, array: np.ndarray) -> None:
    """``np.save``."""

  def save_arrays(self, path: Path, arrays: Mapping[str, np.ndarray]
                  ) -> None:
    """``np.savez``."""

  def write_text(self, path: Path, text: str) -> None:
    """A text file."""


@dataclasses.dataclass(frozen=True)
class Generated(Dataset):
  """A dataset the data stage generates from ``config.data``.

  Attributes:
    what: how messages name it ('the synthetic dataset').
    parameters: ``data_config -> parameters`` of the generation (they name
      its folder; ``.num_frames``: frames per video).
    stored: ``parameters -> FeaturesDict`` of what it stores (None: its
      ``features``, whatever the parameters).
    folder: ``(parameters, data_dir) -> Path`` where it lives (the folder
      :meth:`open` reads and :attr:`generate` makes).
    generate: ``(parameters, Output) -> folder``: makes it unless it is
      there; deterministic (the worker count does not matter).
    split_sizes: ``parameters -> {split: videos}``; a split outside them,
      or empty, is refused by :meth:`open`.
    checksummed: whether the folder records checksums (TFDS folders) that
      the data stage verifies, regenerating a damaged one.
  """

  what: str = ''
  parameters: Callable[[ml_collections.ConfigDict], Any] | None = None
  folder: Callable[[Any, Path], Path] | None = None
  generate: Callable[[Any, Output], Path] | None = None
  split_sizes: Callable[[Any], Mapping[str, int]] | None = None
  checksummed: bool = True
  stored: Callable[[Any], tfds.features.FeaturesDict] | None = None

  def dataset_dir(self, data_config: ml_collections.ConfigDict) -> Path:
    """The folder of the dataset ``data_config`` names."""
    return self.folder(self.parameters(data_config),
                       sources.resolve_data_dir(data_config.data_dir))

  def num_frames(self, data_config: ml_collections.ConfigDict) -> int:
    return int(self.parameters(data_config).num_frames)

  def served_fields(self, data_config: ml_collections.ConfigDict
                    ) -> tuple[str, ...]:
    features = (self.features() if self.stored is None
                else self.stored(self.parameters(data_config)))
    return flow_depth.served_fields(features.keys())

  def open(self, data_config: ml_collections.ConfigDict, split: str
           ) -> sources.VideoSource:
    parameters = self.parameters(data_config)
    if self.split_sizes is not None:
      sizes = self.split_sizes(parameters)
      if not sizes.get(split):
        raise ValueError(
            f'{data_config.name} split {split!r} is empty or unknown; splits '
            f'are {tuple(sizes)} with sizes {list(sizes.values())}')
    source = sources.open_generated(self.what,
                                    self.dataset_dir(data_config), split)
    return flow_depth.serve(source, source.info.features)


# ----------------------------------------------------------------------------
# The registry
# ----------------------------------------------------------------------------

DATASETS: dict[str, Dataset] = {}


def register(dataset: Dataset) -> Dataset:
  """Makes ``dataset`` selectable as ``config.data.name = <one of its
  names>``, at the import of its module (the same dataset again is a
  no-op; another under a taken name an error). Returns it."""
  for name in dataset.names:
    taken = DATASETS.get(name)
    if taken is not None and taken != dataset and (
        type(taken).__qualname__, taken.label) != (
            type(dataset).__qualname__, dataset.label):
      raise ValueError(f'dataset name {name!r} is taken by {taken.label}')
  for name in dataset.names:
    DATASETS[name] = dataset
  return dataset


def unknown(name: Any) -> ConfigError:
  """The error of a ``data.name`` no dataset answers."""
  return ConfigError(
      f'Unknown dataset name {name!r} (data.name); expected one of '
      f'{", ".join(sorted(DATASETS))} (a dataset of your own registers with '
      'slotformer_jax.datasets.register)')


def get(name: str) -> Dataset:
  """The dataset answering ``config.data.name``.

  Raises:
    ConfigError: none does (names the known ones).
  """
  if name not in DATASETS:
    raise unknown(name)
  return DATASETS[name]
