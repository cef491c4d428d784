"""Where an embedded dataset lives, whether it is complete, and what to run
when it is not.

The TFDS families ('synthetic', 'synthetic_contact', 'synthetic_phyre')
share one layout, ``<data_dir>/<name>/<slug>/<version>``; the slug encodes
every generation parameter and the generator's version, so a changed recipe
never reuses a stale folder. tfds writes into a temporary folder and
renames it when complete, so ``dataset_info.json`` exists for finished
builds only.
"""

from __future__ import annotations

import os
from pathlib import Path

from slotformer_jax.errors import MissingInputError

# The TFDS version folder of every embedded TFDS family: 2.0.0 is the
# chunked layout (data/chunked.py TFDS_VERSION); a 1.0.0 folder of an older
# checkout (whole-video records) is left alone and a 2.0.0 one generated.
TFDS_VERSION = '2.0.0'
DATASET_INFO = 'dataset_info.json'
# The command that makes the embedded data (stages/data.py); every --mode
# runs it first, so readers only meet a missing dataset outside main.
PREPARE_COMMAND = ('python -m slotformer_jax.main --config=<config> '
                   '--workdir=<workdir> --mode=prepare_data')


def tfds_dir(data_dir: str | os.PathLike[str], name: str, slug: str) -> Path:
  """The TFDS version folder of family ``name`` with parameters ``slug``."""
  return Path(data_dir) / name / slug / TFDS_VERSION


def is_complete(dataset_dir: str | os.PathLike[str]) -> bool:
  """Whether a TFDS build finished in ``dataset_dir`` (a stat, no read)."""
  return (Path(dataset_dir) / DATASET_INFO).is_file()


def not_generated(what: str, path: str | os.PathLike[str]
                  ) -> MissingInputError:
  """The one-line error of a reader that finds no generated ``what``."""
  return MissingInputError(
      f'{what} is not generated yet (no {os.fspath(path)}); generate it with '
      f'{PREPARE_COMMAND} (every --mode runs that stage first)')
