"""Physion-style object contact prediction (OCP) with SlotFormer rollouts.

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
``readout/results.json``, ``readout/results.md``.
"""

from __future__ import annotations

import functools
import json
import logging
import os
from typing import Any

from flax import serialization
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
from PIL import Image
from PIL import ImageDraw

from slotformer_jax import models
from slotformer_jax import inference
from slotformer_jax import steve_inference
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.modules import readouts
from slotformer_jax.tasks import readout as readout_lib

logger = logging.getLogger(__name__)

OBSERVED, ROLLOUT, COPY_LAST, GROUND_TRUTH = (
    'observed', 'rollout', 'copy_last', 'ground_truth')
CONDITIONS = (OBSERVED, ROLLOUT, COPY_LAST, GROUND_TRUTH)

def readout_splits(config: ml_collections.ConfigDict) -> tuple[str, str, str]:
  """(train, val, test) data splits of the readout (Physion's converter
  writes the Testing videos as 'test', the embedded family 'readout_test')."""
  splits = config.readout.splits
  return splits.train, splits.val, splits.test


def readout_dir(workdir: str) -> str:
  return os.path.join(workdir, 'readout')


def slot_size(config: ml_collections.ConfigDict) -> int:
  """The size of the slots the readout reads: STEVE's on the paper's
  Physion pipeline (``slot_model='steve'``), else SAVi's."""
  if config.get('slot_model', 'savi') == 'steve':
    return config.steve.slot_size
  return config.savi.slot_size


def build_readout(config: ml_collections.ConfigDict) -> readouts.PhysionReadout:
  return readouts.PhysionReadout(
      features=config.readout.features or slot_size(config),
      pairs=config.readout.pairs)


def load_split(config: ml_collections.ConfigDict, workdir: str, split: str
               ) -> tuple[np.ndarray, np.ndarray]:
  """(slots float32 [V, T, N, D], labels float32 [V]) of a readout split.

  T is cut to ``readout.video_len`` when set (the official Physion readout
  reads the first 75 frames). Videos whose label is negative (unlabelled)
  are an error.
  """
  directory = workdir_lib.slots_dir(workdir_lib.stage1_workdir(config, workdir), split)
  source = SlotSource(directory)  # names --mode=extract_slots when missing
  video_len = config.readout.get('video_len') or None
  slots = np.stack([source[i]['slots'][:video_len]
                    for i in range(len(source))])
  videos = get_video_source(config.data, split)
  field = config.readout.label_field
  if field not in videos[0]:
    raise KeyError(f'the {split} videos of {config.data.name!r} have no '
                   f'{field!r} labels')
  labels = np.array([videos[i][field] for i in range(len(videos))],
                    np.float32)
  if (labels < 0).any():
    raise ValueError(f'{int((labels < 0).sum())} videos of {split} have no '
                     f'{field!r} label; the readout splits must be labelled')
  return slots, labels


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


def rollout_fn(config: ml_collections.ConfigDict, workdir: str, mesh: Mesh):
  """observed slots [V, O, N, D], steps -> SlotFormer's rollout [V, K, N, D]
  at the slots' frame rate (interleaved when SlotFormer was trained on
  every ``slotformer.frame_stride``-th frame)."""
  if config.get('slot_model', 'savi') == 'steve':  # trained on STEVE's slots
    params, step = steve_inference.load_dynamics_params(config, workdir, mesh)
  else:
    params, step = inference.load_dynamics_params(config, workdir, mesh)
  logger.info('rollouts from SlotFormer step %d', step)
  model = models.build_slotformer(config)
  batch = config.readout.rollout_batch_size

  def predict(context: np.ndarray, num_steps: int) -> np.ndarray:
    run = jax.jit(functools.partial(inference.rollout_slots, model=model,
                                    num_steps=num_steps))
    return np.concatenate([np.asarray(run(params, context[i:i + batch]))
                           for i in range(0, len(context), batch)])

  def rollout(observed: np.ndarray, num_steps: int) -> np.ndarray:
    return interleaved_rollout(observed, num_steps, config.slotformer.burn_in,
                               config.slotformer.frame_stride, predict)
  return rollout


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


def _features_by_condition(config, workdir, mesh, split, conditions):
  slots, labels = load_split(config, workdir, split)
  rollout = rollout_fn(config, workdir, mesh) if ROLLOUT in conditions else None
  return {c: condition_features(slots, c, config.readout.observed_frames,
                                rollout) for c in conditions}, labels


def _fit_config(config: ml_collections.ConfigDict) -> readout_lib.FitConfig:
  r = config.readout
  return readout_lib.FitConfig(epochs=r.epochs, batch_size=r.batch_size,
                               learning_rate=r.learning_rate,
                               warmup_fraction=r.warmup_fraction)


def _run_dir(workdir: str, condition: str, seed: int) -> str:
  return os.path.join(readout_dir(workdir), condition, f'seed_{seed}')


def train_readout(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh) -> None:
  """Fits the readout per condition and seed; selection on validation."""
  conditions = tuple(config.readout.conditions)
  train_split, val_split, _ = readout_splits(config)
  train, train_labels = _features_by_condition(config, workdir, mesh,
                                               train_split, conditions)
  val, val_labels = _features_by_condition(config, workdir, mesh, val_split,
                                           conditions)
  model = build_readout(config)
  for condition in conditions:
    for seed in config.readout.seeds:
      directory = _run_dir(workdir, condition, seed)
      if os.path.exists(os.path.join(directory, 'selection.json')):
        logger.info('readout %s seed %d already trained', condition, seed)
        continue

      def val_accuracy(params, condition=condition):
        probs = readout_lib.predict(model, params, val[condition])
        return readout_lib.best_threshold(probs, val_labels)[1]

      params, log = readout_lib.fit(
          model, (train[condition], train_labels), val_accuracy,
          _fit_config(config), seed=seed)
      probs = readout_lib.predict(model, params, val[condition])
      threshold, accuracy = readout_lib.best_threshold(probs, val_labels)
      os.makedirs(directory, exist_ok=True)
      with open(os.path.join(directory, 'params.msgpack'), 'wb') as f:
        f.write(serialization.msgpack_serialize(params))
      with open(os.path.join(directory, 'selection.json'), 'w') as f:
        json.dump({'threshold': threshold, 'val_accuracy': accuracy,
                   'best_epoch': log['best_epoch'],
                   'val_scores': log['scores'],
                   'train_losses': log['losses']}, f, indent=1)
      logger.info('readout %s seed %d: val accuracy %.3f (epoch %d, '
                  'threshold %.1f)', condition, seed, accuracy,
                  log['best_epoch'], threshold)


def evaluate_readout(config: ml_collections.ConfigDict, workdir: str,
                     mesh: Mesh) -> dict[str, Any]:
  """Test accuracy at the validation-chosen checkpoint and threshold."""
  conditions = tuple(config.readout.conditions)
  test_split = readout_splits(config)[2]
  test, labels = _features_by_condition(config, workdir, mesh, test_split,
                                        conditions)
  model = build_readout(config)
  results: dict[str, Any] = {}
  first_seed_probs = {}
  for condition in conditions:
    accuracies, val_accuracies = [], []
    for seed in config.readout.seeds:
      directory = _run_dir(workdir, condition, seed)
      selection_path = os.path.join(directory, 'selection.json')
      if not os.path.exists(selection_path):
        raise FileNotFoundError(
            f'no trained readout in {directory}; run --mode=train_readout')
      with open(selection_path) as f:
        selection = json.load(f)
      with open(os.path.join(directory, 'params.msgpack'), 'rb') as f:
        params = serialization.msgpack_restore(f.read())
      probs = readout_lib.predict(model, params, test[condition])
      first_seed_probs.setdefault(condition, probs)
      accuracies.append(readout_lib.accuracy_at(probs, labels,
                                                selection['threshold']))
      val_accuracies.append(selection['val_accuracy'])
    # A converted official readout has no validation accuracy (None).
    measured = [v for v in val_accuracies if v is not None]
    results[condition] = {
        'test_accuracy': accuracies,
        'mean': float(np.mean(accuracies)), 'std': float(np.std(accuracies)),
        'val_accuracy_mean': (float(np.mean(measured))
                              if len(measured) == len(val_accuracies)
                              else None)}
  positive = float(labels.mean())
  results['chance'] = {'mean': max(positive, 1.0 - positive), 'std': 0.0}
  results['num_test_videos'] = len(labels)
  os.makedirs(readout_dir(workdir), exist_ok=True)
  with open(os.path.join(readout_dir(workdir), 'results.json'), 'w') as f:
    json.dump(results, f, indent=1)
  table = format_table(results, conditions)
  with open(os.path.join(readout_dir(workdir), 'results.md'), 'w') as f:
    f.write(table + '\n')
  logger.info('contact prediction, test accuracy (%d seeds):\n%s',
              len(config.readout.seeds), table)
  if ROLLOUT in conditions and config.readout.get('num_pictures', 0):
    write_pictures(config, workdir, mesh, test[ROLLOUT],
                   first_seed_probs[ROLLOUT], labels)
  return results


def write_pictures(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh, rollout_slots: np.ndarray,
                   probabilities: np.ndarray, labels: np.ndarray) -> None:
  """readout/test_<i>.png: real frames over the slot model's decoding of
  [observed, SlotFormer rollout] slots (green border: observed, red: rolled
  out), with the readout's contact probability (first seed) and the truth.
  STEVE's frames are generated token by token (steve_evaluate)."""
  decode = _frame_decoder(config, workdir, mesh)
  videos = get_video_source(config.data, readout_splits(config)[2])
  observed = config.readout.observed_frames
  scale, every = 3, 2
  for i in range(min(config.readout.num_pictures, len(labels))):
    video = videos[i]
    truth = video['video'][:len(rollout_slots[i])]
    predicted = np.asarray(decode(jnp.asarray(rollout_slots[i])))
    predicted = (np.clip(predicted, 0, 1) * 255 + 0.5).astype(np.uint8)
    rows = []
    for frames in (truth, predicted):
      tiles = []
      for t in range(0, len(frames), every):
        tile = np.repeat(np.repeat(frames[t], scale, 0), scale, 1)
        colour = (40, 160, 40) if t < observed else (200, 40, 40)
        framed = np.empty((tile.shape[0] + 4, tile.shape[1] + 4, 3),
                          np.uint8)
        framed[:] = colour
        framed[2:-2, 2:-2] = tile
        tiles.append(framed)
      rows.append(np.concatenate(tiles, axis=1))
    grid = np.concatenate(rows, axis=0)
    canvas = Image.new('RGB', (grid.shape[1], grid.shape[0] + 16),
                       (255, 255, 255))
    canvas.paste(Image.fromarray(grid), (0, 16))
    onset = int(video.get('contact_frame', -1))
    ImageDraw.Draw(canvas).text(
        (3, 2), f'test video {i}: p(contact | observed + rollout) = '
        f'{probabilities[i]:.2f}; truth: {"contact" if labels[i] else "none"}'
        + (f' (onset frame {onset})' if onset >= 0 else ''), fill=(0, 0, 0))
    canvas.save(os.path.join(readout_dir(workdir), f'test_{i}.png'))


def _frame_decoder(config: ml_collections.ConfigDict, workdir: str,
                   mesh: Mesh):
  """Jitted slots [T, N, D] -> frames [T, H, W, 3] in [0, 1]."""
  if config.get('slot_model', 'savi') == 'steve':
    # pylint: disable=g-import-not-at-top
    from slotformer_jax.evaluation import steve_evaluate
    steve_params, _ = steve_inference.load_steve_params(config, workdir, mesh)
    dvae_params, _ = steve_inference.load_dvae_params(config, workdir, mesh)
    generate = steve_evaluate.make_generator(config)
    return jax.jit(lambda slots: generate(steve_params, dvae_params,
                                          slots).recon)
  savi_params, _ = inference.load_savi_params(config, workdir, mesh)
  decoder = models.build_decoder(config)
  return jax.jit(lambda slots: inference.decode_slots(
      savi_params['decoder'], slots, decoder=decoder).recon)


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
