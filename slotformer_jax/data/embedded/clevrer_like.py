"""The CLEVRER-like VQA dataset ('clevrer_like') as its readers see it.

The generation parameters (:class:`ClevrerLikeConfig`, named by a run's
``config.data``), the folder they name, and the reader of its frames
(:class:`NpyVideoSource`). The simulator and the question generator that
write it are ``data/convert/clevrer_like.py`` and
``data/convert/questions.py``. Layout::

  <data_dir>/clevrer_like/<slug>/
    <split>/{video,segmentations,boxes,visible,num_objects}.npy
    <split>/events.jsonl          one EventLog per video, in index order
    questions/{train,validation,test}.json   (CLEVRER's file names)
    vocab.json                    {'q_vocab', 'a_vocab'}
    complete.json                 written last: the build finished, and by
                                  which question generator
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from slotformer_jax.data.embedded import folders
from slotformer_jax.data.embedded.synthetic import COLORS
from slotformer_jax.errors import MissingInputError

# The videos and event logs (the questions have their own version,
# QUESTIONS_VERSION; the event-log types are in data/events.py).
# 2: future_collision_fraction.
GENERATOR_VERSION = 2
# The questions generated from the event logs (data/convert/questions.py).
# Not part of the folder name: a dataset whose complete.json names an older
# version gets new questions from its stored event logs (its videos do not
# change), so the readers refuse it until the data stage has done that.
# 1: the first generator; 2: explanatory labels by re-simulation, balanced
# per choice kind, count templates over objects in view, up to 2
# predictive / explanatory questions per video.
QUESTIONS_VERSION = 2

# predictive_design: 'direct', objects aimed roughly at each other (most
# future collisions are objects already heading at each other: extrapolating
# the observed end answers ~85% of the predictive options, experiments/
# vqa_state_extrapolation.py); 'deflected', bank-shot scenes drawn
# until the future has an event that extrapolation gets wrong, and every
# pair in view at the end carries the extrapolation's verdict
# (EventLog.extrapolated) so that the questions balance the labels within
# each verdict (docs/vqa.md, "Issue 12, round 4"); see
# data/convert/clevrer_like.py.
PREDICTIVE_DESIGNS = ('direct', 'deflected')

DATASET_NAME = 'clevrer_like'
ARRAY_FIELDS = ('video', 'segmentations', 'boxes', 'visible', 'num_objects')
# scene_index = offset + video index, as CLEVRER numbers its splits.
SCENE_OFFSETS = {'train': 0, 'val': 10000, 'test': 15000}
COMPLETE = 'complete.json'


@dataclasses.dataclass(frozen=True)
class ClevrerLikeConfig:
  """Generation parameters; together they identify a generated dataset.

  Attributes:
    resolution: (H, W) of rendered frames.
    observed_frames: frames of the video shown to models.
    predicted_frames: frames simulated after the video (predictive questions
      ask about them; a dynamics model has to roll out to see them).
    min_objects, max_objects: objects present from frame 0.
    max_entering: objects entering later (0..max_entering per video).
    moving_fraction: probability that an object present at frame 0 moves.
    future_collision_fraction: probability that a video is drawn among
      scenes where two objects in view at the last observed frame collide
      after it (rejection sampling over physics-only simulations): without
      it only ~1/3 of the videos have anything to predict. With the
      'deflected' design: among scenes with a predictive question balanced
      within the extrapolation's verdict (:func:`has_deflected_question`).
    seed: base seed; video ``i`` of split ``s`` uses ``(seed, s, i)``.
    num_train, num_val, num_test: videos per split.
    supersample, object_scale: as in
      :class:`slotformer_jax.data.embedded.synthetic.SyntheticConfig`.
    predictive_design: one of PREDICTIVE_DESIGNS ('direct' is the generator
      of version 2; the field enters the slug only when not 'direct', so the
      datasets built before it keep their slugs and contents).
  """

  resolution: tuple[int, int] = (32, 32)
  observed_frames: int = 24
  predicted_frames: int = 16
  min_objects: int = 2
  max_objects: int = 4
  max_entering: int = 1
  moving_fraction: float = 0.5
  future_collision_fraction: float = 0.0
  seed: int = 0
  num_train: int = 1000
  num_val: int = 100
  num_test: int = 200
  supersample: int = 2
  object_scale: float = 1.0
  predictive_design: str = 'direct'

  def __post_init__(self):
    object.__setattr__(self, 'resolution', tuple(int(r) for r in self.resolution))
    if self.observed_frames < 2 or self.predicted_frames < 0:
      raise ValueError('need observed_frames >= 2 and predicted_frames >= 0')
    if not 1 <= self.min_objects <= self.max_objects:
      raise ValueError('need 1 <= min_objects <= max_objects')
    if self.max_objects + self.max_entering > len(COLORS):
      # Objects are named by colour in questions: colours must be distinct.
      raise ValueError(f'at most {len(COLORS)} objects per video')
    if self.max_entering < 0:
      raise ValueError('max_entering must be >= 0')
    if not 0.0 <= self.future_collision_fraction <= 1.0:
      raise ValueError('future_collision_fraction must be in [0, 1]')
    if self.predictive_design == 'deflected' and (
        self.max_objects < 3 or self.predicted_frames < 2):
      # A bank shot needs three objects, a verdict a few future frames.
      raise ValueError("predictive_design='deflected' needs max_objects >= 3 "
                       'and predicted_frames >= 2')
    if self.predictive_design not in PREDICTIVE_DESIGNS:
      raise ValueError(f'predictive_design must be one of '
                       f'{PREDICTIVE_DESIGNS}, got {self.predictive_design!r}')

  @property
  def num_frames(self) -> int:
    return self.observed_frames + self.predicted_frames

  @property
  def max_objects_total(self) -> int:
    return self.max_objects + self.max_entering

  def num_videos(self, split: str) -> int:
    return {'train': self.num_train, 'val': self.num_val,
            'test': self.num_test}[split]

  def identity(self) -> dict[str, Any]:
    """The fields that identify the dataset: all of them, except
    ``predictive_design`` when it is 'direct' (as before the field)."""
    fields = dataclasses.asdict(self)
    if fields['predictive_design'] == 'direct':
      del fields['predictive_design']
    return fields

  @property
  def slug(self) -> str:
    h, w = self.resolution
    payload = json.dumps({**self.identity(),
                          'generator_version': GENERATOR_VERSION},
                         sort_keys=True)
    digest = hashlib.sha256(payload.encode()).hexdigest()[:8]
    return (f'r{h}x{w}_t{self.observed_frames}+{self.predicted_frames}'
            f'_o{self.min_objects}-{self.max_objects}+{self.max_entering}'
            f'_s{self.seed}_{digest}')


def video_filename(split: str, index: int) -> str:
  return f'video_{SCENE_OFFSETS[split] + index:05d}.mp4'


def dataset_dir(config: ClevrerLikeConfig, data_dir: str | os.PathLike[str]
                ) -> Path:
  return Path(data_dir) / DATASET_NAME / config.slug


def completion(config: ClevrerLikeConfig) -> dict[str, Any]:
  """What complete.json of a finished, current dataset holds."""
  return {**config.identity(), 'questions_version': QUESTIONS_VERSION}


def is_complete(root: str | os.PathLike[str]) -> bool:
  """Whether the dataset folder ``root`` is finished and its questions are
  the current generator's (one small read)."""
  path = Path(root) / COMPLETE
  if not path.is_file():
    return False
  with open(path) as f:
    return json.load(f).get('questions_version') == QUESTIONS_VERSION


def complete_dataset_dir(data_config: Any, data_dir: str | os.PathLike[str]
                         ) -> Path:
  """The folder of the dataset ``config.data`` names.

  Raises:
    MissingInputError: it is not generated, or its questions are older
      than the generator's (names the command that makes them).
  """
  root = dataset_dir(config_from_data_config(data_config), data_dir)
  if not (root / COMPLETE).is_file():
    raise folders.not_generated('the CLEVRER-like dataset', root / COMPLETE)
  if not is_complete(root):
    raise MissingInputError(
        f'the CLEVRER-like dataset {root} holds questions of an older '
        f'generator; {folders.PREPARE_COMMAND} writes new ones from its '
        'event logs (every --mode runs that stage first)')
  return root


class NpyVideoSource:
  """The videos of one split of a built dataset (frames memory-mapped).

  Items: video uint8 [T, H, W, 3], segmentations uint8 [T, H, W], boxes
  float32 [T, O, 4], visible bool [T, O], num_objects int32 [], index.
  """

  def __init__(self, root: str | os.PathLike[str], split: str):
    folder = Path(root) / split
    self._arrays = {field: np.load(folder / f'{field}.npy', mmap_mode='r')
                    for field in ARRAY_FIELDS}

  def __len__(self) -> int:
    return len(self._arrays['video'])

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    if not 0 <= index < len(self):
      raise IndexError(index)
    item = {k: np.asarray(v[index]) for k, v in self._arrays.items()}
    item['index'] = np.array(index, np.int32)
    return item


def config_from_data_config(data_config: Any) -> ClevrerLikeConfig:
  """The generation parameters named by a data config (defaults filled in)."""
  fields = {f.name for f in dataclasses.fields(ClevrerLikeConfig)}
  values = {k: data_config[k] for k in fields if k in data_config}
  if 'resolution' in values:
    values['resolution'] = tuple(values['resolution'])
  return ClevrerLikeConfig(**values)
