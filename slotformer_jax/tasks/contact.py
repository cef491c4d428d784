"""Physion-style object contact prediction (OCP): the pure parts.

Protocol (SlotFormer Section 4.3, with the selection fixed):

1. SAVi and SlotFormer are trained on the dynamics split ('train'); slots of
   every readout split are extracted (``--mode=extract_slots``).
2. Every readout video is observed for its first ``observed_frames`` frames;
   the readout then sees one of these slot sequences (``CONDITIONS``):
   'observed' (the observed frames only), 'rollout' (+ SlotFormer's rollout
   of the rest, from the last ``burn_in`` observed frames), 'copy_last'
   (+ the last observed slots repeated), 'ground_truth' (+ SAVi's slots of
   the real future frames: the ceiling).
3. ``train_readout``: per condition and seed, the Physion readout is fitted
   on 'readout_train'; the epoch and the threshold are chosen on
   'readout_val' (the official script picks both on test).
4. ``evaluate_readout``: accuracy on 'readout_test' at the chosen threshold,
   mean +- std over seeds, next to chance (the majority class).

Workdir: ``readout/<condition>/seed_<s>/{params.msgpack, selection.json}``,
``readout/results.json``, ``readout/results.md``. The stages that read slots
and models and write those files are in ``stages/contact.py``.
"""

from __future__ import annotations

from typing import Any

import ml_collections
import numpy as np

from slotformer_jax.modules import readouts
from slotformer_jax.tasks import readout as readout_lib

OBSERVED, ROLLOUT, COPY_LAST, GROUND_TRUTH = (
    'observed', 'rollout', 'copy_last', 'ground_truth')
CONDITIONS = (OBSERVED, ROLLOUT, COPY_LAST, GROUND_TRUTH)


def readout_splits(readout: ml_collections.ConfigDict
                   ) -> tuple[str, str, str]:
  """(train, val, test) data splits of the readout section `readout`
  (Physion's converter writes the Testing videos as 'test', the embedded
  family 'readout_test')."""
  splits = readout.splits
  return splits.train, splits.val, splits.test


def build_readout(readout: ml_collections.ConfigDict, slot_size: int
                  ) -> readouts.PhysionReadout:
  """The readout over slots of `slot_size` (`readout.features` overrides)."""
  return readouts.PhysionReadout(features=readout.features or slot_size,
                                 pairs=readout.pairs)


def fit_config(r: ml_collections.ConfigDict) -> readout_lib.FitConfig:
  """The readout section's training settings."""
  return readout_lib.FitConfig(epochs=r.epochs, batch_size=r.batch_size,
                               learning_rate=r.learning_rate,
                               warmup_fraction=r.warmup_fraction)


def interleaved_rollout(observed: np.ndarray, num_steps: int, burn_in: int,
                        frame_stride: int, predict) -> np.ndarray:
  """Full-frame-rate future slots from a model trained on every
  ``frame_stride``-th frame (the official Physion rollout script).

  Offset ``o`` rolls out frames ``o, o + stride, ...`` after the observed
  ones from the ``burn_in`` observed frames spaced ``stride`` apart that end
  just before them; the offsets are interleaved back into frame order.

  Args:
    observed: [V, O, N, D] observed slots at the full frame rate.
    num_steps: future frames wanted (full rate).
    burn_in: the model's context length (in its own, strided frames).
    frame_stride: the model's temporal subsampling.
    predict: (context [V, burn_in, N, D], steps) -> [V, steps, N, D].

  Returns:
    [V, num_steps, N, D].
  """
  num_observed = observed.shape[1]
  if num_observed < burn_in * frame_stride:
    raise ValueError(f'{num_observed} observed frames < burn_in {burn_in} x '
                     f'frame_stride {frame_stride}')
  per_offset = []
  for offset in range(frame_stride):
    start = num_observed - burn_in * frame_stride + offset
    context = observed[:, start::frame_stride][:, :burn_in]
    steps_needed = len(range(offset, num_steps, frame_stride))
    per_offset.append(predict(context, steps_needed) if steps_needed else None)
  return np.stack([per_offset[i % frame_stride][:, i // frame_stride]
                   for i in range(num_steps)], axis=1)


def condition_features(slots: np.ndarray, condition: str,
                       observed_frames: int, rollout=None) -> np.ndarray:
  """The slot sequence the readout sees, [V, T', N, D].

  Args:
    slots: SAVi's slots of the whole videos [V, T, N, D].
    condition: one of CONDITIONS.
    observed_frames: how many leading frames are observed.
    rollout: (observed [V, O, N, D], steps) -> [V, steps, N, D]; needed for
      'rollout'.
  """
  observed = slots[:, :observed_frames]
  future = slots.shape[1] - observed_frames
  if condition == OBSERVED:
    return observed
  if condition == GROUND_TRUTH:
    return slots
  if condition == COPY_LAST:
    copied = np.repeat(observed[:, -1:], future, axis=1)
    return np.concatenate([observed, copied], axis=1)
  if condition == ROLLOUT:
    if rollout is None:
      raise ValueError('the rollout condition needs a rollout function')
    return np.concatenate([observed, rollout(observed, future)], axis=1)
  raise ValueError(f'unknown condition {condition!r}; one of {CONDITIONS}')


_ROW_NAMES = {
    OBSERVED: 'observed slots only',
    ROLLOUT: 'observed + SlotFormer rollout',
    COPY_LAST: 'observed + copy-last',
    GROUND_TRUTH: 'observed + ground-truth future slots (ceiling)',
    'chance': 'chance (majority class)',
}


def format_table(results: dict[str, Any], conditions: tuple[str, ...]) -> str:
  lines = ['| readout input | test accuracy (%) | val accuracy (%) |',
           '|---|---|---|']
  for name in conditions + ('chance',):
    row = results[name]
    val = row.get('val_accuracy_mean')
    lines.append(f'| {_ROW_NAMES[name]} | {100 * row["mean"]:.1f} +- '
                 f'{100 * row["std"]:.1f} | '
                 f'{"" if val is None else f"{100 * val:.1f}"} |')
  return '\n'.join(lines)
