"""Checksums of a dataset cache: verified when opened (reading only).

`checksums.json` in a TFDS version folder holds, per array_record file (and
the TFDS metadata and the chunk index, `video_chunks.json`), its
size, modification time and crc32. Opening a split compares sizes (always)
and, when a file's modification time changed, its crc32: a truncated or
rewritten file is found before any step reads it, at the cost of one stat
per file on a healthy cache. The writers record the file
(`data/write/records.py`), so a reader never writes.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any
import zlib

from slotformer_jax.files import read_json

CHECKSUMS_FILE = 'checksums.json'
# The chunked layout's per-split index (data/chunked.py INDEX_FILE).
CHUNK_INDEX_FILE = 'video_chunks.json'


class DamagedDataset(Exception):
  """A cache file differs from what was written (the message names it)."""


def file_crc32(path: str | os.PathLike[str], chunk: int = 1 << 24) -> str:
  """crc32 of a file, read in 16 MiB pieces (about 1 GB/s)."""
  value = 0
  with open(path, 'rb') as f:
    while block := f.read(chunk):
      value = zlib.crc32(block, value)
  return f'{value:08x}'


def checksummed_files(dataset_dir: Path) -> list[Path]:
  """The files checksums.json covers: records and TFDS metadata."""
  return sorted(p for p in dataset_dir.iterdir()
                if '.array_record' in p.name or p.name in (
                    'dataset_info.json', 'features.json', CHUNK_INDEX_FILE))


def file_entry(path: Path) -> dict[str, Any]:
  """What checksums.json holds of one file."""
  stat = path.stat()
  return {'size': stat.st_size, 'mtime_ns': stat.st_mtime_ns,
          'crc32': file_crc32(path)}


def verify_checksums(dataset_dir: str | os.PathLike[str],
                     split: str | None = None) -> bool:
  """Checks the files of `split` (default: all) against checksums.json.

  Returns False when the folder has no checksums.json (an older cache).

  Raises:
    DamagedDataset: a file is missing, has another size, or other bytes.
  """
  dataset_dir = Path(dataset_dir)
  path = dataset_dir / CHECKSUMS_FILE
  if not path.is_file():
    return False
  recorded = read_json(path, fix=f'Delete {path}: it is recomputed.')
  for name, entry in sorted(recorded.items()):
    if split is not None and '.array_record' in name and (
        f'-{split}.array_record' not in name):
      continue
    file = dataset_dir / name
    if not file.is_file():
      raise DamagedDataset(f'{file} is missing')
    stat = file.stat()
    if stat.st_size != entry['size']:
      raise DamagedDataset(f'{file} has {stat.st_size} bytes, '
                           f'{entry["size"]} were written')
    if stat.st_mtime_ns != entry['mtime_ns']:
      crc = file_crc32(file)
      if crc != entry['crc32']:
        raise DamagedDataset(f'{file} was changed after it was written '
                             f'(crc32 {crc}, written {entry["crc32"]})')
  return True
