"""The settings a workdir was run with: config.json and its history.

A run on an existing workdir must use the settings it was made with, or say
so (`--allow_config_change`): the changed fields are listed, the old
settings go to config_history.jsonl, and the stages they affect are set
aside and rebuilt (their identities no longer match, see identity.py).

A new workdir whose first run stops before making anything (a missing
input, a wrong path) keeps no config.json (`withdraw_unused_config`): the
corrected command is a first run again, not a change of settings.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

import jax

from slotformer_jax.errors import UserError
from slotformer_jax.files import append_line_atomic
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic
from slotformer_jax.workdir.identity import NOT_SHAPING
from slotformer_jax.workdir.identity import flat_differences
from slotformer_jax.workdir.identity import plain
from slotformer_jax.workdir.paths import Paths

# Settings that pick a variant with its own folder (vqa/<inputs>_s<seed>/):
# one workdir holds every Aloe input and seed of a comparison.
VARIANT_SELECTORS = ('vqa.inputs', 'vqa.seed', 'vqa.eval_split')
# What a stage accepts as input, not what it makes: changing one is no
# change of settings.
INPUT_THRESHOLDS = ('vqa.max_missing_video_fraction',)


def accept_config(settings: dict[str, Any], paths: Paths, *,
                  allow_change: bool = False) -> list[str]:
  """Checks `settings` (the resolved config as a dict) against the ones the
  workdir was run with; records them in config.json (the old ones go to
  config_history.jsonl).

  Returns the changed fields (empty for a new workdir or the same settings).

  Raises:
    UserError: settings changed and `allow_change` is False.
  """
  path = paths.config_file
  current = plain(settings)
  changes = []
  if os.path.exists(path):
    saved = read_json(path, fix=f'Restore it from {paths.config_history} or '
                      'delete it to accept the current settings.')
    changes = [c for c in flat_differences(saved, current)
               if not _only_observation(c)]
    if changes and not allow_change:
      raise UserError(
          f'{paths.root} was run with other settings: {"; ".join(changes)}. '
          'Use a new --workdir for new settings, or pass '
          '--allow_config_change to accept them here (stages they affect '
          'are then retrained or re-extracted; old checkpoints are kept as '
          '<stage>.stale-<run id>).')
  if jax.process_index() == 0 and (changes or not os.path.exists(path)):
    if changes:
      append_line_atomic(paths.config_history, json.dumps(
          {'replaced': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
           'changes': changes, 'config': saved}))
    write_json_atomic(path, current)
  return changes


# What a workdir holds besides the work of its stages: its settings and
# the bookkeeping of whoever runs in it (paths.py).
_BOOKKEEPING = ('config.json', '.lock', '.processes')


def holds_no_work(paths: Paths) -> bool:
  """True when the workdir holds no file but its settings and bookkeeping
  (config.json, .lock, .processes/); empty folders do not count."""
  for folder, subfolders, names in os.walk(paths.root):
    if folder == paths.root:
      subfolders[:] = [d for d in subfolders if d not in _BOOKKEEPING]
      names = [n for n in names if n not in _BOOKKEEPING]
    if names:
      return False
  return True


def withdraw_unused_config(paths: Paths) -> bool:
  """Removes config.json from a workdir whose first run stopped before it
  made anything (`holds_no_work`), so that the corrected command is not
  refused as a change of settings. Call it only when that run wrote
  config.json itself (the workdir had none); returns whether it removed
  it."""
  if jax.process_index() != 0 or not os.path.exists(paths.config_file):
    return False
  if not holds_no_work(paths):
    return False
  os.remove(paths.config_file)
  return True


def _only_observation(change: str) -> bool:
  name = change.split(':', 1)[0]
  last = name.rsplit('.', 1)[-1]
  # The pictures', the explorer's and the logging settings (a whole section
  # too: a workdir from before the explorer has no `explore` section).
  return (last in NOT_SHAPING or name in ('render', 'explore', 'logging')
          or name.startswith(('render.', 'explore.', 'logging.'))
          or name in VARIANT_SELECTORS or name in INPUT_THRESHOLDS)
