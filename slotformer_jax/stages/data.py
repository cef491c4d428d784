"""The data stage: makes and checks what the other stages read.

Reading never writes (`data/sources.py` only opens data), so whatever a run
reads is made here, first for every `--mode`; when the data are there it
costs a stat per file. A generated dataset (`datasets/base.py:Generated`)
is made when missing, with what a task reads besides the videos
(`Generated.task_data`) and the CLEVRER-like questions. Every split the run
reads (:func:`splits_read`) is checked against its recorded checksums: a
folder without them gets them; a damaged embedded cache is set aside and
generated again; a damaged converted dataset is refused with one line
naming the conversion command; a converted folder from before
``video_names.json`` gets it from its conversion's progress files. A
converted dataset that is not there is left to the stage that reads it,
which names the conversion command, unless ``config.data`` names its
download (a folder of videos, ``data.source``): that is converted here.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import ml_collections

from slotformer_jax import datasets
from slotformer_jax.data import integrity
from slotformer_jax.data.sources import resolve_data_dir
from slotformer_jax.data.video_names import NAMES_FILE
from slotformer_jax.data.write import convert as writer
from slotformer_jax.data.write import generate
from slotformer_jax.data.write.records import record_checksums
from slotformer_jax.datasets.base import ConversionError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.errors import shown
from slotformer_jax.run import Run
from slotformer_jax.stages import task as task_lib

logger = logging.getLogger(__name__)


def splits_read(config: ml_collections.ConfigDict) -> tuple[str, ...]:
  """The data splits the stages of `config` open, in first-use order: stage
  1 trains on 'train', extraction reads `extraction.splits`, the task the
  splits it declares (`Task.reads`: video prediction its evaluated split,
  a readout its `readout.splits`)."""
  splits = ['train', *config.extraction.splits]
  splits += [split for _, split in task_lib.get(config.task).reads(config)]
  return tuple(dict.fromkeys(splits))


def prepare_data(run: Run) -> None:
  """Makes and checks the data of the run (see the module docstring); the
  data belong to the data dir, not to one workdir."""
  config = run.config
  prepare_dataset(config.data, splits_read(config))
  dataset = datasets.get(config.data.name)
  task_data = dataset.task_data.get(config.task)
  if task_data is not None:
    task_data(config.data, generate.output(config.data))


def prepare_dataset(data_config: ml_collections.ConfigDict,
                    splits: Sequence[str] | None = None) -> None:
  """Makes (an embedded family) and checks the dataset `data_config` names.

  Args:
    data_config: a run's `config.data`.
    splits: the splits to check; None: all of them.

  Raises:
    UserError: a converted dataset is damaged (names the conversion
      command), or the name is unknown.
  """
  dataset = datasets.get(data_config.name)
  if isinstance(dataset, datasets.Generated):
    folder = generate.make_dataset(dataset, data_config)
    if dataset.checksummed:
      _check_generated(dataset, data_config, folder, splits)
  else:
    _check_converted(dataset, data_config, splits)


def _check_generated(dataset: datasets.Generated,
                     data_config: ml_collections.ConfigDict, folder: Path,
                     splits: Sequence[str] | None) -> None:
  for split in splits or (None,):
    try:
      if not integrity.verify_checksums(folder, split):
        record_checksums(folder)  # built by an older version
    except integrity.DamagedDataset as error:
      # A cache is regenerable: say so, set it aside, build it again.
      logger.warning('the %s dataset cache is damaged (%s); regenerating it',
                     data_config.name, error)
      generate.discard_dataset(folder)
      folder = generate.make_dataset(dataset, data_config)


def convert_source(dataset: datasets.Converted,
                   data_config: ml_collections.ConfigDict,
                   source: Path) -> writer.ConversionResult:
  """Converts the download ``config.data`` names (a folder of videos:
  ``data.source``) into its folder unless it is there: every split, with
  the prepare command's machinery (resumable, parallel, skipped videos
  reported one line each).

  Raises:
    UserError: the source is not a folder, holds no video for a split, or
      too many of its videos cannot be read (one line, or the lines of the
      skipped videos).
  """
  if not source.is_dir():
    raise MissingInputError(f'data.source={shown(source)} is not a folder')
  try:
    options = dataset.options_of(data_config)
    spec = dataset.spec(options, source)
    jobs = {split: dataset.discover(source, split, options)
            for split in dataset.splits}
    result = writer.convert(
        spec, jobs, resolve_data_dir(data_config.data_dir),
        num_workers=data_config.num_workers,
        max_skip_fraction=data_config.get('max_skip_fraction', 0.05))
  except (FileNotFoundError, ValueError, ConversionError) as error:
    raise UserError(f'data.source: {error}') from None
  if result.videos_processed:
    logger.info('%s', writer.summary(result))
  return result


def _check_converted(dataset: datasets.Converted,
                     data_config: ml_collections.ConfigDict,
                     splits: Sequence[str] | None) -> None:
  source = dataset.source_of(data_config)
  if source is not None:
    convert_source(dataset, data_config, source)
  try:
    folder = dataset.dataset_dir(data_config)
  except MissingInputError:
    logger.info('the %s dataset is not converted; a stage that reads it '
                'says how', data_config.name)
    return
  for split in splits or (None,):
    try:
      if not integrity.verify_checksums(folder, split):
        # Converted by an older version: trust it once, check from now on.
        logger.info('recording checksums of %s', folder)
        record_checksums(folder)
    except integrity.DamagedDataset as error:
      raise dataset.damaged(data_config, error) from None
  if not (folder / NAMES_FILE).is_file() and writer.record_video_names(
      folder):
    logger.info('recorded the video names of %s (converted before they '
                'were)', folder)
