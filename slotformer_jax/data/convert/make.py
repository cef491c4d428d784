"""Makes the embedded dataset a run's ``config.data`` names, unless it is
there: the one entry point of the data stage (stages/data.py), and of a
script or test that needs the data without a run.

Each family's generator writes into the folder its parameters name
(data/embedded/), which is where the readers look.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from slotformer_jax.data.convert import clevrer_like
from slotformer_jax.data.convert import contact
from slotformer_jax.data.convert import phyre_like
from slotformer_jax.data.convert import synthetic
from slotformer_jax.data.data_dir import resolve_data_dir
from slotformer_jax.data.embedded import families


def make_dataset(data_config: Any) -> Path:
  """Generates the embedded dataset of ``data_config`` unless it is there.

  Deterministic (a pure function of the generation parameters; the worker
  count, ``data.num_workers``, does not matter). The OBJ3D-like family is
  generated under a lock, so processes sharing a data dir make it once.

  Returns:
    The folder the reader opens: a TFDS version folder, or the CLEVRER-like
    dataset folder.

  Raises:
    ValueError: ``data_config.name`` is not an embedded family.
  """
  name = data_config.name
  root = resolve_data_dir(data_config.data_dir)
  workers = data_config.num_workers
  if name not in families.NAMES:
    raise ValueError(f'{name!r} is not an embedded family '
                     f'({families.NAMES}); real datasets are converted')
  parameters = families.generation_config(data_config)
  if name == 'synthetic':
    return synthetic.build_synthetic_dataset(parameters, root,
                                             num_workers=workers)
  if name == 'synthetic_contact':
    return contact.build_contact_dataset(parameters, root,
                                         num_workers=workers)
  if name == 'synthetic_phyre':
    return phyre_like.build_video_dataset(data_config, root)
  return clevrer_like.build_dataset(parameters, root, num_workers=workers)


def discard_dataset(path: str | Path) -> None:
  """Removes a (damaged) generated dataset folder so it is built again."""
  shutil.rmtree(path, ignore_errors=True)
