"""One run of the pipeline: what every stage receives.

`main` checks the config once and builds one `Run`: the config (its
sections are what the stages and their helpers read), every path of the
workdir (`workdir.paths.Paths`), the device mesh, this process's place among
the run's processes, the slot model, and the trained models of the workdir,
loaded (and checked against each other) the first time a stage asks::

    run = Run.create(config, '/path/to/workdir')    # or Run.open(workdir)
    run.slot_model.encode(run.stage1.params, video, rng, None)
    slotformer = run.dynamics('slotformer')          # dynamics.Loaded

With several seeds (config.seeds) `run.for_seed(k)` is the view of seed
k: the one-seed run of that seed on its share of the stacked checkpoints,
in its `seed_<s>/` folders; the stages after stage 1 run it seed by seed.

A stage is `(run) -> None | results` (stages/__init__.py). Nothing below the
stages builds its own view of the run: a helper gets the section it needs.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Sequence
from typing import Any

import jax
from jax.sharding import Mesh
import ml_collections

from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax import slot_models
from slotformer_jax.config import checks as config_checks
from slotformer_jax.config.sections import DYNAMICS
from slotformer_jax.config.sections import dynamics_section
from slotformer_jax.config.sections import several_seeds
from slotformer_jax import datasets
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.sources import VideoSource
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.files import read_json
from slotformer_jax.inference import StackedSeed
from slotformer_jax.runtime import sharding
from slotformer_jax.slot_models import chain
from slotformer_jax.slot_models.base import Loaded
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import Paths


@dataclasses.dataclass(frozen=True, eq=False)
class Run:
  """A run: its settings, its folders, its devices and its models.

  Attributes:
    config: the checked settings (read-only). Stages pass sections of it to
      the code they call.
    paths: every path of the workdir (and of a read-only stage 1).
    mesh: the devices, batches split on its 'data' axis.
    slot_model: the configured slot model (`config.slot_model`).
    seed_index: None, or this is the view of seed `config.seeds[k]` of a
      several-seed run (`for_seed`): its paths are that seed's, its trained
      models that seed's share of the stacked checkpoints, and it draws
      with that seed where a one-seed run draws with `config.seed`.
  """

  config: ml_collections.ConfigDict
  paths: Paths
  mesh: Mesh
  slot_model: SlotModel
  seed_index: int | None = None
  _loaded: dict[str, Any] = dataclasses.field(default_factory=dict,
                                              repr=False)

  @classmethod
  def create(cls, config: ml_collections.ConfigDict, workdir: str,
             mesh: Mesh | None = None) -> Run:
    """The run of `config` in `workdir` (on every device by default).

    Raises:
      ConfigError: a field holds a value outside its declared choices, or
        a tuple of the wrong shape (before anything is built from it: the
        slot model reads its (H, W) fields as it is made).
    """
    problems = (config_checks.choice_problems(config)
                + config_checks.check_field_shapes(config))
    if problems:
      raise ConfigError('config: ' + '; '.join(problems))
    slot_model = slot_models.get(config)
    if config.compute_dtype not in slot_model.compute_dtypes:
      raise ConfigError(
          f'compute_dtype={config.compute_dtype!r} is not implemented for '
          f'slot_model={slot_model.name!r}; use --config.compute_dtype='
          f'{slot_model.compute_dtypes[0]}')
    return cls(config=config,
               paths=Paths.of(workdir, config.stage1_workdir),
               mesh=mesh if mesh is not None else sharding.make_mesh(),
               slot_model=slot_model)

  @classmethod
  def open(cls, workdir: str, mesh: Mesh | None = None) -> Run:
    """The run a workdir was made by, with the settings its config.json
    records: for loading its trained models outside the pipeline."""
    path = os.path.join(workdir, 'config.json')
    if not os.path.exists(path):
      raise MissingInputError(f'{workdir} has no config.json: not a run')
    settings = read_json(path)
    # A workdir from before a field was added: the value its absence
    # stands for (identity.ADDED_FIELDS), so the code reads every field.
    for name, value in identity_lib.ADDED_FIELDS.items():
      *sections, field = name.split('.')
      if sections[:1] and sections[0] in DYNAMICS and DYNAMICS[
          sections[0]].inherits is not None:
        continue  # overrides only: a field it lacks is the inherited one's
      section = settings
      for key in sections:
        section = section.get(key) if isinstance(section, dict) else None
      if isinstance(section, dict) and field not in section:
        section[field] = value
    return cls.create(ml_collections.ConfigDict(settings), workdir, mesh)

  # ---- who this process is ------------------------------------------------

  @property
  def process_index(self) -> int:
    return jax.process_index()

  @property
  def process_count(self) -> int:
    return jax.process_count()

  @property
  def is_lead(self) -> bool:
    """The process that writes the run's shared files."""
    return jax.process_index() == 0

  # ---- several seeds (config.seeds, docs/seeds.md) --------------------------

  @property
  def seeds(self) -> tuple[int, ...] | None:
    """The seeds trained in one program (config.seeds, several), or None
    for a one-seed run. A seed view has them too (`seed_index`)."""
    return several_seeds(self.config)

  @property
  def seed(self) -> int:
    """What this run draws with: `config.seed`, or a seed view's seed."""
    if self.seed_index is None:
      return self.config.seed
    return self.seeds[self.seed_index]

  @property
  def stacked(self) -> StackedSeed | None:
    """A seed view's place in the stacked checkpoints, or None."""
    if self.seed_index is None:
      return None
    return StackedSeed(self.seeds, self.seed_index,
                       self.config.seed_data_order)

  def for_seed(self, index: int) -> Run:
    """The view of seed `config.seeds[index]`: the one-seed run of that seed
    on its share of the stacked stages, in its `seed_<s>/` folders."""
    seeds = self.seeds
    if seeds is None or not 0 <= index < len(seeds):
      raise ValueError(f'no seed index {index} in seeds {seeds}')
    return dataclasses.replace(self, paths=self.paths.for_seed(seeds[index]),
                               seed_index=index, _loaded={})

  def seed_views(self) -> list[Run]:
    """`for_seed` of every seed, in config.seeds order."""
    return [self.for_seed(index) for index in range(len(self.seeds))]

  def chains(self) -> list[Run]:
    """The runs a per-seed stage goes through: a one-seed run or a seed
    view itself; a several-seed run every seed view (chain s: stage-1
    seed s and what follows)."""
    if self.seeds is None or self.seed_index is not None:
      return [self]
    return self.seed_views()

  def readout_chains(self, readout_seeds: Sequence[int]
                     ) -> list[tuple[Run, tuple[int, ...]]]:
    """(chain, the seeds of the task models fitted on it): a one-seed
    run's one chain with `readout_seeds` (a task's own seeds, e.g.
    readout.seeds); with several seeds each seed view with its own seed,
    task model s on chain s (`readout_seeds` not used)."""
    if self.seeds is None:
      return [(self, tuple(readout_seeds))]
    return [(view, (view.seed,)) for view in self.chains()]

  # ---- what the config asks for ----------------------------------------------

  @property
  def task(self) -> str | None:
    """The downstream task ('contact', 'planning', 'vqa'), or None for
    video prediction."""
    return self.config.task

  def dynamics_section(self, name: str) -> ml_collections.ConfigDict:
    """The resolved settings of dynamics model `name` (Slot-LSTM's over
    SlotFormer's, see config/sections.py)."""
    return dynamics_section(self.config, name)

  @functools.cached_property
  def slots_fields(self) -> dict[str, Any]:
    """What shapes the extracted slots besides the slot model."""
    return identity_lib.slots_fields(self.seed,
                                     self.config.extraction.to_dict())

  # ---- data ------------------------------------------------------------------

  def videos(self, split: str) -> VideoSource:
    """The videos of `split` (opened, never made: see stages/data.py)."""
    return datasets.get_video_source(self.config.data, split)

  def slots(self, split: str, video_fields: tuple[str, ...] = (), *,
            video_from: int = 0) -> SlotSource:
    """The extracted slots of `split`, served with `video_fields` of its
    videos (e.g. ('video',) for the image loss), a training clip's from its
    `video_from`-th frame on (`SlotSource`)."""
    videos = self.videos(split) if video_fields else None
    return SlotSource(self.paths.slots(split), videos, video_fields,
                      video_from=video_from)

  # ---- trained models, loaded once and checked ---------------------------------

  @property
  def stage1(self) -> Loaded:
    """The trained slot model (every part of its chain), checked; a seed
    view's: that seed's share of the stacked stage 1."""
    if 'stage1' not in self._loaded:
      self._loaded['stage1'] = chain.load(self.slot_model, self.paths,
                                          self.mesh, self.stacked)
    return self._loaded['stage1']

  def dynamics(self, name: str) -> dynamics_lib.Loaded:
    """Trained dynamics model `name` (registered: dynamics/base.py)."""
    key = f'dynamics/{name}'
    if key not in self._loaded:
      self._loaded[key] = dynamics_lib.load(
          self.paths, self.mesh, name, self.dynamics_section(name),
          self.slot_model.slot_shape, self.stacked)
    return self._loaded[key]

  def forget(self) -> None:
    """Drops the loaded models (a later stage that retrained one reads it
    again)."""
    self._loaded.clear()
