"""The per-step curves of a run's eval/metrics.json, as the explorer page
shows them, read as a file from elsewhere: a run folder someone shares may
hold anything there. Every field is type-checked and bounded (names up to
`MAX_NAME` characters, curves up to `MAX_STEPS` steps, `MAX_CURVES` curves);
a file that is not what --mode=evaluate writes leaves the curves out, with a
note saying why. No jax: the page's reader of this file is cheap to test on
hostile inputs (tests/reader_fuzz.py).
"""

from __future__ import annotations

from collections.abc import Mapping
import logging
import math
import os
from typing import Any

from slotformer_jax.files import UntrustedFileError
from slotformer_jax.files import int_in_range
from slotformer_jax.files import read_untrusted_json

logger = logging.getLogger(__name__)

MAX_NAME = 100
MAX_STEPS = 10_000
MAX_CURVES = 1_000

_UNREADABLE = ('eval/metrics.json is not what --mode=evaluate writes: re-run '
               '--mode=evaluate for the run\'s curves')


def clean(values) -> list[float | None]:
  """Per-step values for the page: 4 decimals, non-finite as None (and so
  an int too large for a float, such as 10**400 in a JSON file)."""
  try:
    return [None if v is None or not math.isfinite(v) else round(float(v), 4)
            for v in values]
  except OverflowError:
    return [_finite(v) for v in values]


def _finite(value) -> float | None:
  try:
    value = None if value is None else float(value)
  except OverflowError:
    return None
  return None if value is None or not math.isfinite(value) else round(
      value, 4)


def _curve(value: Any) -> list[float | None] | None:
  """A per-step curve of metrics.json (numbers or nulls), else None."""
  if not isinstance(value, list) or len(value) > MAX_STEPS or not all(
      v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))
      for v in value):
    return None
  return clean(value)


def _name(value: Any) -> bool:
  return isinstance(value, str) and 0 < len(value) <= MAX_NAME


def read_curves(path: str, identity: dict[str, Any],
                labels: Mapping[str, str]
                ) -> tuple[dict[str, Any] | None, str]:
  """({metric: {method label: per-step values}}, note) of the metrics file
  at `path`, or (None, why not) when it is missing, from other models
  (`identity` differs), or not what --mode=evaluate writes. `labels`: the
  page's label of each method."""
  if not os.path.exists(path):
    return None, ('no eval/metrics.json: run --mode=evaluate for the run\'s '
                  'curves')
  try:
    results = read_untrusted_json(path, what='metrics file')
  except UntrustedFileError as error:
    logger.warning('explore: %s', error)
    return None, _UNREADABLE
  if not isinstance(results, dict):
    return None, _UNREADABLE
  if results.get('identity') != identity:
    return None, ('eval/metrics.json is from other models than these: '
                  're-run --mode=evaluate for the run\'s curves')
  rollout = results.get('rollout', {})
  if not isinstance(rollout, dict):
    return None, _UNREADABLE
  curves: dict[str, dict[str, list]] = {}
  count = 0
  for method, per_metric in rollout.items():
    if not (_name(method) and isinstance(per_metric, dict)):
      return None, _UNREADABLE
    for name, value in per_metric.items():
      if isinstance(value, dict) and 'per_step' in value:
        curve = _curve(value['per_step'])
        count += 1
        if curve is None or not _name(name) or count > MAX_CURVES:
          return None, _UNREADABLE
        curves.setdefault(name, {})[labels.get(method, method)] = curve
  protocol = results.get('protocol', {})
  protocol = protocol if isinstance(protocol, dict) else {}
  videos, split = protocol.get('num_videos', 'the'), protocol.get('split', '')
  try:
    videos = int_in_range(videos, 0, 10**12, what='num_videos')
  except UntrustedFileError:
    videos = 'the'
  return curves, (f'the run: eval/metrics.json, mean over {videos} '
                  f'{split if _name(split) else ""} videos')
