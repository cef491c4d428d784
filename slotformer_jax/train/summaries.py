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

import os
from collections.abc import Mapping

import ml_collections
import numpy as np
from slotformer_jax.errors import UserError

DIRECTORY = 'tensorboard'
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
    if enabled:
      try:
        import tensorboardX  # pylint: disable=import-outside-toplevel
      except ImportError:
        raise UserError(
            'logging.tensorboard=True needs tensorboardX: pip install '
            'tensorboardX, or pass --config.logging.tensorboard=False'
        ) from None
      self._writer = tensorboardX.SummaryWriter(self.directory,
                                                flush_secs=30)

  @property
  def enabled(self) -> bool:
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
    if self._writer is not None:
      self._writer.close()
      self._writer = None
