"""The object-contact (OCP) embedded dataset ('synthetic_contact') as its
reader sees it: the generation parameters (:class:`ContactConfig`, named by a
run's ``config.data``) and the folder they name. The generator is
``data/convert/contact.py``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any

from slotformer_jax.data.embedded import folders
from slotformer_jax.data.embedded.synthetic import (
    GENERATOR_VERSION as SYNTHETIC_VERSION)

GENERATOR_VERSION = 1

NAME = 'synthetic_contact'
SPLITS: tuple[str, ...] = ('train', 'readout_train', 'readout_val',
                           'readout_test')
# Where the agent starts: the front (along the camera's view) or the side.
LAUNCH_SIDES = ('front', 'side')
# 'direct': the agent is aimed at (or beside) the patient, so its heading in
# the observed frames decides the label. 'bank': it is aimed at a *bumper*
# (object row 1) that stands off the line to the patient, and reaches the
# patient (or not) only after bouncing off it, after the observed frames:
# the observed motion alone no longer answers, the collision decides.
SCENARIOS = ('direct', 'bank')


@dataclasses.dataclass(frozen=True)
class ContactConfig:
  """Generation parameters; together they identify a cached dataset.

  Attributes:
    resolution: (H, W) of the output frames.
    num_frames: T, frames per video (20 per simulated second).
    observed_frames: frames a model observes; contacts start after them.
    min_distractors, max_distractors: other static objects per video.
    seed: base seed; video ``i`` of split ``s`` uses ``(seed, s, i)``.
    num_train, num_readout_train, num_readout_val, num_readout_test: videos
      per split.
    supersample: anti-aliasing factor (see synthetic.py).
    object_scale: multiplies every object's size.
    launch_side: where the agent starts: 'front' (the camera's side, moving
      along the view direction) or 'side' (the left / right edge, moving
      across it).
  """

  resolution: tuple[int, int] = (64, 64)
  num_frames: int = 24
  observed_frames: int = 8
  min_distractors: int = 1
  max_distractors: int = 2
  seed: int = 0
  num_train: int = 1000
  num_readout_train: int = 400
  num_readout_val: int = 100
  num_readout_test: int = 200
  supersample: int = 2
  object_scale: float = 1.0
  launch_side: str = 'front'
  scenario: str = 'direct'

  def __post_init__(self):
    object.__setattr__(self, 'resolution',
                       tuple(int(r) for r in self.resolution))
    if len(self.resolution) != 2 or min(self.resolution) < 8:
      raise ValueError(f'resolution must be (H, W) >= 8, got {self.resolution}')
    if not 1 <= self.observed_frames < self.num_frames:
      raise ValueError('need 1 <= observed_frames < num_frames, got '
                       f'{self.observed_frames}, {self.num_frames}')
    if not 0 <= self.min_distractors <= self.max_distractors <= 4:
      raise ValueError('need 0 <= min_distractors <= max_distractors <= 4')
    if min(self.num_videos(s) for s in SPLITS) < 0 or self.seed < 0:
      raise ValueError('split sizes and seed must be >= 0')
    if self.launch_side not in LAUNCH_SIDES:
      raise ValueError(f'launch_side must be one of {LAUNCH_SIDES}, got '
                       f'{self.launch_side!r}')
    if self.scenario not in SCENARIOS:
      raise ValueError(f'scenario must be one of {SCENARIOS}, got '
                       f'{self.scenario!r}')
    if self.scenario == 'bank' and (self.launch_side != 'side'
                                    or self.min_distractors < 1):
      raise ValueError("scenario='bank' needs launch_side='side' and "
                       'min_distractors >= 1 (the bumper is a distractor)')

  @property
  def max_objects_total(self) -> int:
    """O: rows of the per-object arrays (patient + distractors + agent)."""
    return self.max_distractors + 2

  def num_videos(self, split: str) -> int:
    return {'train': self.num_train, 'readout_train': self.num_readout_train,
            'readout_val': self.num_readout_val,
            'readout_test': self.num_readout_test}[split]

  @property
  def slug(self) -> str:
    h, w = self.resolution
    fields = dataclasses.asdict(self)
    if fields['launch_side'] == 'front':  # the datasets made before the option
      del fields['launch_side']
    if fields['scenario'] == 'direct':  # ... and before this one
      del fields['scenario']
    payload = json.dumps(
        {**fields, 'generator_version': GENERATOR_VERSION,
         'synthetic_version': SYNTHETIC_VERSION}, sort_keys=True)
    digest = hashlib.sha256(payload.encode()).hexdigest()[:8]
    return (f'r{h}x{w}_t{self.num_frames}_obs{self.observed_frames}'
            f'_d{self.min_distractors}-{self.max_distractors}_s{self.seed}'
            f'_n{self.num_train}-{self.num_readout_train}-'
            f'{self.num_readout_val}-{self.num_readout_test}_{digest}')



def config_from_data_config(data_config: Any) -> ContactConfig:
  """The generation parameters named in a run's ``config.data``."""
  fields = {f.name for f in dataclasses.fields(ContactConfig)}
  return ContactConfig(**{key: data_config[key] for key in fields
                          if key in data_config})


def dataset_dir(config: ContactConfig,
                data_dir: str | os.PathLike[str]) -> Path:
  """The TFDS version folder of ``config`` under cache root ``data_dir``."""
  return folders.tfds_dir(data_dir, NAME, config.slug)
