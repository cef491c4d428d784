"""Fitting a readout head through the shared trainer (train/trainer.py),
with the epoch chosen on validation only.

The official protocol: epochs over the training set in an order drawn anew
each epoch, Adam on the official schedule (tasks/readout.py), dropout keys
per step; after every epoch `select` scores the head on validation, and the
first epoch with the best score is kept. The head trains on the first
device of each process (it is tiny); it resumes like any stage.

`directory` holds the trainer's checkpoints/ and train_log.jsonl (one line
per epoch), `epochs.jsonl` (each epoch's score and mean training loss) and
`params.msgpack` (the best epoch's parameters so far). A resumed fit picks
as an uninterrupted one; an epoch resumed after a preemption in its middle
averages the losses of its steps since the resume.
"""

from __future__ import annotations

from collections.abc import Callable
import functools
import json
import os
from typing import Any

from flax import serialization
import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax.errors import MissingInputError
from slotformer_jax.files import append_line_atomic
from slotformer_jax.files import write_atomic
from slotformer_jax.runtime import sharding
from slotformer_jax.tasks import readout as readout_lib
from slotformer_jax.train import trainer

EPOCHS_FILE = 'epochs.jsonl'
PARAMS_FILE = 'params.msgpack'
# The step RNG's own stream of the seed (dropout): fold_in(key(seed), 1).
DROPOUT_STREAM = 1


def fit_readout(directory: str, name: str, model: nn.Module,
                train: tuple[np.ndarray, np.ndarray],
                select: Callable[[Any], float],
                fit_config: readout_lib.FitConfig, seed: int
                ) -> tuple[Any, dict[str, Any]]:
  """Trains head `model` on `train` (features [N, ...], labels [N]) in
  `directory`, keeping the epoch `select` (params -> validation score,
  higher is better) likes best; `seed` draws its initialisation, its
  training order and its dropout.

  Returns:
    (the best epoch's params (numpy), log) with log = {'best_epoch',
    'best_score', 'scores' (per epoch), 'losses' (mean training loss per
    epoch)}.
  """
  features, labels = train
  if len(features) != len(labels) or not len(features):
    raise ValueError(f'{len(features)} feature rows vs {len(labels)} labels')
  batch_size = min(fit_config.batch_size, len(features))
  steps_per_epoch = len(features) // batch_size
  mesh = sharding.one_device_per_process()
  sharding.per_host_batch_size(batch_size, mesh)  # splits evenly
  # Drawn outside the trainer's jitted initialisation, as an eager init
  # draws them (bit for bit).
  initial = model.init(jax.random.key(seed),
                       jnp.asarray(features[:1]))['params']
  selection = _Selection(directory, steps_per_epoch, fit_config.epochs,
                         select)
  stage = trainer.Stage(
      name=name, directory=directory,
      config=ml_collections.ConfigDict(dict(
          batch_size=batch_size,
          num_train_steps=steps_per_epoch * fit_config.epochs,
          log_every=steps_per_epoch, checkpoint_every=steps_per_epoch,
          stop_check_every=1)),
      loss_fn=functools.partial(readout_lib.readout_loss, model=model),
      init_params=lambda rng: initial,
      batches=lambda start_step: readout_lib.training_batches(
          features, labels, batch_size, seed, start_step,
          jax.process_index(), jax.process_count()),
      optimizer=readout_lib.make_optimizer(fit_config, steps_per_epoch),
      rng_stream=DROPOUT_STREAM, after_update=selection.after_update)
  trainer.fit(stage, mesh=mesh, seed=seed)
  return selection.result()


class _Selection:
  """The epochs' scores and the best epoch's parameters, on disk (the lead
  process writes) so that a resumed fit goes on where it stopped."""

  def __init__(self, directory: str, steps_per_epoch: int, num_epochs: int,
               select: Callable[[Any], float]):
    self.steps_per_epoch = steps_per_epoch
    self.num_epochs = num_epochs
    self.select = select
    self.epochs_path = os.path.join(directory, EPOCHS_FILE)
    self.params_path = os.path.join(directory, PARAMS_FILE)
    self.is_lead = jax.process_index() == 0
    self.records: dict[int, dict[str, Any]] | None = None
    self.best_params: Any = None
    self.losses: list[float] = []  # of this epoch's updates

  def _load(self) -> None:
    """The epochs already scored (by this or an interrupted fit: a resumed
    epoch is trained again to the same state) and the best one's params."""
    self.records = {}
    if os.path.exists(self.epochs_path):
      with open(self.epochs_path) as f:
        for line in f:
          record = json.loads(line)
          self.records[record['epoch']] = record
    if self.records and os.path.exists(self.params_path):
      with open(self.params_path, 'rb') as f:
        self.best_params = serialization.msgpack_restore(f.read())

  def after_update(self, step: int, params: Any,
                   metrics: dict[str, jax.Array]) -> None:
    """`Stage.after_update`: at the end of an epoch, its score and mean
    loss; its params when it is the best epoch so far."""
    if self.records is None:
      self._load()
    loss = metrics['loss'].addressable_data(0)  # no collective
    self.losses.append(float(np.asarray(loss)))
    if step % self.steps_per_epoch:
      return
    epoch = step // self.steps_per_epoch - 1
    params = trainer.host_copy(params)
    record = {'epoch': epoch, 'score': float(self.select(params)),
              'loss': float(np.mean(self.losses))}
    self.losses = []
    self.records[epoch] = record
    if self.is_lead:
      append_line_atomic(self.epochs_path, json.dumps(record))
    if _best_epoch(self.records, epoch) == epoch:
      self.best_params = params
      if self.is_lead:
        write_atomic(self.params_path, serialization.msgpack_serialize(
            params))

  def result(self) -> tuple[Any, dict[str, Any]]:
    if self.records is None:  # trained before: nothing ran in this process
      self._load()
    epochs = [e for e in range(self.num_epochs) if e in self.records]
    best = _best_epoch(self.records, self.num_epochs - 1)
    return self.best_params, {
        'scores': [self.records[e]['score'] for e in epochs],
        'losses': [self.records[e]['loss'] for e in epochs],
        'best_score': (self.records[best]['score'] if best >= 0
                       else -np.inf),
        'best_epoch': best}


def _best_epoch(records: dict[int, dict[str, Any]], last: int) -> int:
  """The first epoch up to `last` with the highest score (-1: none)."""
  best, best_score = -1, -np.inf
  for epoch in range(last + 1):
    if epoch in records and records[epoch]['score'] > best_score:
      best, best_score = epoch, records[epoch]['score']
  return best


def load_params(directory: str, what: str, marker: str = PARAMS_FILE) -> Any:
  """The chosen epoch's parameters of the head `fit_readout` trained in
  `directory` (`what` names it in the message).

  Raises:
    MissingInputError: `marker` is not in `directory` (not trained).
  """
  if not os.path.exists(os.path.join(directory, marker)):
    raise MissingInputError(
        f'no trained {what} in {directory}; run --mode=train_readout')
  with open(os.path.join(directory, PARAMS_FILE), 'rb') as f:
    return serialization.msgpack_restore(f.read())
