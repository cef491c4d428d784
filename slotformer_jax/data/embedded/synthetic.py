"""The OBJ3D-like embedded dataset ('synthetic') as its reader sees it.

Its generation parameters (:class:`SyntheticConfig`, named by a run's
``config.data``), the folder they name, and the labels of the stored
``shapes`` / ``colors`` / ``sizes`` ids. The generator is
``data/convert/synthetic.py``; the CLEVRER-like and contact families reuse
its objects, hence these names.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any

from slotformer_jax.data.embedded import folders

# Bump whenever the generator's output changes for identical parameters: it is
# part of the cache folder name, so stale caches are never reused.
GENERATOR_VERSION = 1

# The TFDS builder's name: the family's folder under the data dir.
NAME = 'synthetic_obj3d'
SPLITS: tuple[str, ...] = ('train', 'val', 'test')

# What the stored ids mean: shapes[k], colors[k], sizes[k] index these.
SHAPES: tuple[str, ...] = ('cube', 'sphere', 'cylinder')
COLORS: tuple[str, ...] = (
    'gray', 'red', 'blue', 'green', 'brown', 'purple', 'cyan', 'yellow')
SIZES: tuple[str, ...] = ('small', 'large')


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
  """Generation parameters; together they identify a cached dataset.

  Attributes:
    resolution: (H, W) of the output frames.
    num_frames: T, frames per video.
    min_objects: minimum number of static objects per video.
    max_objects: maximum number of static objects (the launched sphere comes on
      top, so per-object arrays have ``max_objects + 1`` rows). Up to 7 fit
      the layout region comfortably; 8 is slow to place, 10 does not fit.
    seed: base seed; video ``i`` of split ``s`` uses ``(seed, s, i)``.
    num_train, num_val, num_test: videos per split (0 skips a split).
    supersample: render at ``supersample`` x the resolution and area-average
      (anti-aliasing); masks are downsampled by majority vote.
    object_scale: multiplies every object's size (larger objects cover more
      pixels, which matters at low resolution).
    distinct_colors: no two objects of a video share a colour (at most
      len(COLORS) objects).
  """

  resolution: tuple[int, int] = (64, 64)
  num_frames: int = 40
  min_objects: int = 3
  max_objects: int = 5
  seed: int = 0
  num_train: int = 1000
  num_val: int = 100
  num_test: int = 100
  supersample: int = 2
  object_scale: float = 1.0
  distinct_colors: bool = False

  def __post_init__(self):
    # Accept lists (e.g. from ml_collections) but store a hashable tuple.
    object.__setattr__(self, 'resolution', tuple(int(r) for r in self.resolution))
    if len(self.resolution) != 2 or min(self.resolution) < 8:
      raise ValueError(f'resolution must be (H, W) >= 8, got {self.resolution}')
    if self.num_frames < 1:
      raise ValueError(f'num_frames must be >= 1, got {self.num_frames}')
    if not 1 <= self.min_objects <= self.max_objects:
      raise ValueError('need 1 <= min_objects <= max_objects, got '
                       f'{self.min_objects}..{self.max_objects}')
    if self.max_objects + 1 > 254:
      raise ValueError('uint8 masks hold at most 254 objects')
    if min(self.num_train, self.num_val, self.num_test) < 0:
      raise ValueError('split sizes must be >= 0')
    if self.seed < 0:
      raise ValueError(f'seed must be >= 0, got {self.seed}')
    if self.supersample < 1:
      raise ValueError(f'supersample must be >= 1, got {self.supersample}')
    if self.distinct_colors and self.max_objects + 1 > len(COLORS):
      raise ValueError(f'distinct_colors allows at most {len(COLORS) - 1} '
                       f'static objects, got max_objects={self.max_objects}')
    if not 0.25 <= self.object_scale <= 2.0:
      raise ValueError(
          f'object_scale must be in [0.25, 2], got {self.object_scale}')

  @property
  def max_objects_total(self) -> int:
    """O: rows of the per-object arrays (static objects + launched sphere)."""
    return self.max_objects + 1

  def num_videos(self, split: str) -> int:
    return {'train': self.num_train, 'val': self.num_val,
            'test': self.num_test}[split]

  @property
  def slug(self) -> str:
    """A readable, unique folder name for these parameters (+ code version)."""
    h, w = self.resolution
    payload = json.dumps(
        {**dataclasses.asdict(self), 'generator_version': GENERATOR_VERSION},
        sort_keys=True)
    digest = hashlib.sha256(payload.encode()).hexdigest()[:8]
    return (f'r{h}x{w}_t{self.num_frames}_o{self.min_objects}-{self.max_objects}'
            f'_s{self.seed}_n{self.num_train}-{self.num_val}-{self.num_test}'
            f'_aa{self.supersample}_{digest}')



def config_from_data_config(data_config: Any) -> SyntheticConfig:
  """The generation parameters named by a data config (the dataclass's
  defaults for those it does not name)."""
  defaults = SyntheticConfig()
  values = {}
  for field in dataclasses.fields(SyntheticConfig):
    if field.name in data_config:
      # As the default's type (an int given for object_scale is a float):
      # the dataset's folder name hashes these values.
      kind = type(getattr(defaults, field.name))
      values[field.name] = kind(data_config[field.name])
  return SyntheticConfig(**values)


def dataset_dir(config: SyntheticConfig,
                data_dir: str | os.PathLike[str]) -> Path:
  """The TFDS version folder of ``config`` under cache root ``data_dir``."""
  return folders.tfds_dir(data_dir, NAME, config.slug)
