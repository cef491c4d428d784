"""Where a training loop's metrics go, written once per logged step: one
line each in `<stage dir>/train_log.jsonl` (the lead host's) and in the log,
TensorBoard scalars (and pictures, train/summaries.py), and the progress bar.

A logged step has one or more lines, each `(fields, metrics)`: `fields`
names whose metrics they are ({} for one model; {'seed': s} when several
train at once) and goes into the JSONL line, the log line (' seed s') and
the TensorBoard tag ('loss/seed_s').
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import json
import logging
import os
import time

import jax
import ml_collections
import numpy as np
import tqdm

from slotformer_jax.files import append_line_atomic
from slotformer_jax.train.summaries import Summaries

logger = logging.getLogger(__name__)

LOG_FILE = 'train_log.jsonl'
Line = tuple[Mapping[str, int], dict[str, float]]


class MetricsWriter:
  """The metrics of stage `name` training from `start_step` to `num_steps`
  (its directory holds the JSONL log and tensorboard/); a context manager."""

  def __init__(self, name: str, directory: str,
               logging_config: ml_collections.ConfigDict | None, *,
               start_step: int, num_steps: int):
    self.name = name
    self._is_lead = jax.process_index() == 0
    self._path = os.path.join(directory, LOG_FILE)
    self._summaries = Summaries(directory, logging_config, self._is_lead)
    self._progress = tqdm.tqdm(total=num_steps, initial=start_step,
                               desc=name, disable=not self._is_lead,
                               dynamic_ncols=True)
    self._last_time, self._last_step = time.time(), start_step

  def __enter__(self) -> MetricsWriter:
    return self

  def __exit__(self, *exc) -> None:
    self.close()

  def advance(self) -> None:
    """One more update done (the progress bar)."""
    self._progress.update(1)

  def write(self, step: int, lines: Sequence[Line],
            learning_rate: float) -> None:
    """The metrics of update `step`, with the learning rate it used and the
    steps per second since the last write."""
    now = time.time()
    shared = {'learning_rate': learning_rate,
              'steps_per_second': (step - self._last_step) / max(
                  now - self._last_time, 1e-9)}
    self._last_time, self._last_step = now, step
    for fields, metrics in lines:
      metrics = {**metrics, **shared}
      label = ''.join(f' {key} {value}' for key, value in fields.items())
      self._progress.set_postfix(loss=f'{metrics["loss"]:.4g}')
      logger.info('%s%s step %d: %s', self.name, label, step,
                  ', '.join(f'{k}={v:.4g}' for k, v in sorted(
                      metrics.items())))
      if self._is_lead:
        append_line_atomic(self._path, json.dumps(
            {'step': step, **fields, **metrics}))
      suffix = ''.join(f'/{key}_{value}' for key, value in fields.items())
      self._summaries.scalars(step, {f'{k}{suffix}': v
                                     for k, v in metrics.items()})

  def wants_images(self, step: int) -> bool:
    return self._summaries.wants_images(step)

  def images(self, step: int, grids: Mapping[str, np.ndarray]) -> None:
    self._summaries.images(step, grids)

  def close(self) -> None:
    self._progress.close()
    self._summaries.close()
