"""Recording a dataset folder's checksums, after it is written (the readers
verify them: data/integrity.py)."""

from __future__ import annotations

import os
from pathlib import Path

from slotformer_jax.data.integrity import CHECKSUMS_FILE
from slotformer_jax.data.integrity import checksummed_files
from slotformer_jax.data.integrity import file_entry
from slotformer_jax.files import write_json_atomic


def record_checksums(dataset_dir: str | os.PathLike[str]) -> None:
  """Writes checksums.json for every record / metadata file of the folder."""
  dataset_dir = Path(dataset_dir)
  write_json_atomic(dataset_dir / CHECKSUMS_FILE, {
      p.name: file_entry(p) for p in checksummed_files(dataset_dir)})
