"""The name of every video of a split, in record order: what joins files
that name videos (CLEVRER's questions) to the rows of the converted split.

A question file names its video ('video_10800.mp4'); a converted split holds
the videos that converted, in index order, so rank and row differ as soon as
one video is skipped (CLEVRER's converter always leaves out video 10800).
Joining by name is right whatever was skipped.

* A converted (real) dataset records its names in ``video_names.json``
  (``{split: [name, ...]}``, the converter's key of each record, e.g.
  'video_10000'), written with its metadata (``convert/writer.py``); the
  data stage adds the file to a folder converted before it (from the
  converter's progress files), so reading only reads it. A folder without
  it is refused with the command that converts it again
  (``vqa_questions.split_video_names``).
* The embedded CLEVRER-like family names video ``i`` of a split by its
  index (``clevrer_like.video_filename``), as its questions do.

Names are compared without folder and extension (:func:`name_key`). This
module only reads files: the writers import it too.
"""

from __future__ import annotations

import os
from pathlib import Path

from slotformer_jax.errors import UserError
from slotformer_jax.files import read_json

NAMES_FILE = 'video_names.json'


def name_key(name: str) -> str:
  """'videos/val/video_10000.mp4' and 'video_10000' -> 'video_10000'."""
  return os.path.splitext(os.path.basename(str(name)))[0]


def read_recorded_names(dataset_dir: str | os.PathLike[str], split: str
                        ) -> list[str] | None:
  """The names ``video_names.json`` records for ``split``; None when the
  folder has no such file (converted before it) or no entry for the
  split."""
  path = Path(dataset_dir) / NAMES_FILE
  if not path.is_file():
    return None
  fix = ('Delete it: the data stage (run by every --mode) writes it again '
         "from the conversion's _progress/ files.")
  recorded = read_json(path, fix=fix)
  names = recorded.get(split) if isinstance(recorded, dict) else []
  if names is None:
    return None
  if not (isinstance(names, list) and all(isinstance(n, str)
                                          for n in names)):
    raise UserError(f'{path} is not a {{split: [video name, ...]}} '
                    f'mapping. {fix}')
  return names
