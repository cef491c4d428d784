"""TensorBoard summaries of a training stage, beside its JSONL log.

`<stage dir>/tensorboard/` gets, at every logged step, the scalars of the
JSONL line (losses, learning rate, grad / param norms, steps per second and
seconds per step) under `train/<name>`, and every `logging.image_every`
steps the stage's pictures (`Stage.images`: a reconstruction, its slot
masks, a rollout strip) as labelled grids under `images/<name>`. Written
with tensorboardX (it needs no TensorFlow); `logging.tensorboard = False`
writes nothing. Only the lead host writes.

    tensorboard --logdir <workdir>
"""

from __future__ import annotations

from collections.abc import Mapping
import logging
import os
import threading

import ml_collections
import numpy as np
from slotformer_jax.errors import UserError

DIRECTORY = 'tensorboard'
logger = logging.getLogger(__name__)


# Writer threads of tensorboardX that died of an OSError (a full disk).
_FAILED_WRITERS: list[threading.Thread] = []
# Events a writer may queue: after its thread died, a full queue would block
# the training loop forever (tensorboardX's default holds 10).
_MAX_QUEUE = 1000


def _quiet_writer_thread_errors() -> None:
  """tensorboardX writes from a thread of its own: an OSError there (a full
  disk, a quota) would print a traceback over the trainer's own line, and
  leave a writer whose queue nobody empties. It becomes one warning and a
  mark that `Summaries` checks; other threads' errors are left to the
  previous hook. Installed once per process."""
  previous = threading.excepthook
  if getattr(previous, 'slotformer_summaries', False):
    return

  def hook(args) -> None:
    if (type(args.thread).__name__ == '_EventLoggerThread'
        and isinstance(args.exc_value, OSError)):
      _FAILED_WRITERS.append(args.thread)
      logger.warning('TensorBoard summaries stopped: %s',
                     args.exc_value.strerror or args.exc_value)
      return
    previous(args)
  hook.slotformer_summaries = True
  threading.excepthook = hook


class Summaries:
  """The TensorBoard writer of one stage (a no-op when disabled)."""

  def __init__(self, stage_directory: str,
               logging_config: ml_collections.ConfigDict | None,
               is_lead_host: bool = True):
    enabled = bool(logging_config is not None and logging_config.tensorboard
                   and is_lead_host)
    self.image_every = int(logging_config.image_every
                           if logging_config is not None else 0)
    self.directory = os.path.join(stage_directory, DIRECTORY)
    self._writer = None
    self._failures_seen = 0
    if enabled:
      try:
        import tensorboardX  # pylint: disable=import-outside-toplevel
      except ImportError:
        raise UserError(
            'logging.tensorboard=True needs tensorboardX: pip install '
            'tensorboardX, or pass --config.logging.tensorboard=False'
        ) from None
      _quiet_writer_thread_errors()
      self._failures_seen = len(_FAILED_WRITERS)
      try:
        self._writer = tensorboardX.SummaryWriter(
            self.directory, flush_secs=30, max_queue=_MAX_QUEUE)
      except OSError as error:  # a full disk, a quota: the run goes on
        logger.warning('TensorBoard summaries are off: cannot write %s (%s)',
                       self.directory, error.strerror or error)

  @property
  def enabled(self) -> bool:
    if self._writer is not None and len(_FAILED_WRITERS) > self._failures_seen:
      # Its thread died (a full disk): dropped, not closed, since closing
      # would wait for that thread.
      self._writer = None
    return self._writer is not None

  def wants_images(self, step: int) -> bool:
    return (self.enabled and self.image_every > 0
            and step % self.image_every == 0)

  def scalars(self, step: int, metrics: Mapping[str, float]) -> None:
    """One logged step's metrics (+ seconds per step)."""
    if not self.enabled:
      return
    for name, value in sorted(metrics.items()):
      self._writer.add_scalar(f'train/{name}', float(value), step)
    rate = metrics.get('steps_per_second')
    if rate:
      self._writer.add_scalar('train/seconds_per_step', 1.0 / rate, step)

  def images(self, step: int, grids: Mapping[str, np.ndarray]) -> None:
    """{name: uint8 [H, W, 3]} pictures (see `labelled_grid`)."""
    if not self.enabled:
      return
    for name, image in grids.items():
      self._writer.add_image(f'images/{name}', np.asarray(image), step,
                             dataformats='HWC')

  def close(self) -> None:
    """Flushes and closes; a write that fails (a full disk) is one warning,
    never an error that would hide the trainer's own (the summaries are an
    extra: the checkpoints and train_log.jsonl say what a run did)."""
    if self.enabled:
      writer, self._writer = self._writer, None
      try:
        writer.close()
      except OSError as error:
        logger.warning('TensorBoard summaries in %s are incomplete: %s',
                       self.directory, error.strerror or error)
