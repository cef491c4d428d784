"""The contact-prediction stages (`task='contact'`): `train_readout`,
`evaluate_readout`.

They read the slot model's extracted slots of the readout splits, roll
SlotFormer out after the observed frames, and fit / evaluate the Physion
readout on each condition (tasks/contact.py has the protocol and the pure
parts). Every file is written atomically; a readout seed whose
`selection.json` exists is not refitted.

Seeds (`Run.readout_chains`): a one-seed run fits `readout.seeds` readouts on
its one chain (slot model -> SlotFormer), the official Physion protocol; a
several-seed run (config.seeds, docs/seeds.md) fits one readout per chain,
chain s's with seed s, so the spread covers the whole chain. Either way
results.json reports each readout's test accuracy, their mean and std.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax import inference
from slotformer_jax.config import defaults
from slotformer_jax.config.sections import primary_dynamics
from slotformer_jax.data import video_names
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import visualize
from slotformer_jax.files import read_json
from slotformer_jax.files import write_atomic
from slotformer_jax.files import write_json_atomic
from slotformer_jax.frames import to_uint8
from slotformer_jax.run import Run
from slotformer_jax.runtime import progress
from slotformer_jax.stages import readout_fit
from slotformer_jax.stages.task import Task
from slotformer_jax.stages.task import register
from slotformer_jax.tasks import contact
from slotformer_jax.tasks import readout as readout_lib

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Readout:
  """A trained contact readout of a run.

  Attributes:
    module: the readout (`tasks.contact.build_readout`).
    params: its parameters at the epoch chosen on validation.
    threshold: the decision threshold chosen on validation.
    selection: everything `train_readout` recorded (selection.json).
  """

  module: Any
  params: Any
  threshold: float
  selection: dict[str, Any]


def load_readout(run: Run, condition: str, seed: int) -> Readout:
  """The readout of `condition` ('observed', 'rollout', ...) and `seed`.

  Raises:
    MissingInputError: not trained (the message names the stage).
  """
  directory = run.paths.readout(condition, seed)
  params = readout_fit.load_params(directory, 'readout',
                                   marker='selection.json')
  selection = read_json(os.path.join(directory, 'selection.json'),
                        fix=f'Delete {directory} and re-run '
                        '--mode=train_readout.')
  module = contact.build_readout(run.config.readout,
                                 run.slot_model.slot_shape[1])
  return Readout(module=module, params=params,
                 threshold=selection['threshold'], selection=selection)


def load_split(run: Run, split: str) -> tuple[np.ndarray, np.ndarray]:
  """(slots float32 [V, T, N, D], labels float32 [V]) of a readout split.

  T is cut to ``readout.video_len`` when set (the official Physion readout
  reads the first 75 frames). Videos whose label is negative (unlabelled)
  are an error.
  """
  readout = run.config.readout
  source = SlotSource(run.paths.slots(split))  # names extract_slots if missing
  video_len = readout.video_len or None
  slots = np.stack([source[i]['slots'][:video_len]
                    for i in range(len(source))])
  videos = run.videos(split)
  field = readout.label_field
  if field not in videos[0]:
    raise ConfigError(f'readout.label_field={field!r}: the {split} videos '
                      f'of {run.config.data.name!r} have no such labels')
  labels = np.array([videos[i][field] for i in range(len(videos))],
                    np.float32)
  if (labels < 0).any():
    raise ConfigError(f'{int((labels < 0).sum())} videos of {split} have no '
                     f'{field!r} label; the readout splits must be labelled')
  return slots, labels


def rollout_fn(run: Run):
  """observed slots [V, O, N, D], steps -> SlotFormer's rollout [V, K, N, D]
  at the slots' frame rate (interleaved when SlotFormer was trained on
  every ``slotformer.frame_stride``-th frame)."""
  slotformer = run.dynamics(primary_dynamics(run.config))
  logger.info('rollouts from SlotFormer step %d', slotformer.step)
  batch = run.config.readout.rollout_batch_size
  section = run.dynamics_section(primary_dynamics(run.config))

  def predict(context: np.ndarray, num_steps: int) -> np.ndarray:
    roll = jax.jit(functools.partial(inference.rollout_slots,
                                     model=slotformer.module,
                                     num_steps=num_steps))
    return np.concatenate([
        np.asarray(roll(slotformer.params, context[i:i + batch]))
        for i in range(0, len(context), batch)])

  def rollout(observed: np.ndarray, num_steps: int) -> np.ndarray:
    return contact.interleaved_rollout(
        observed, num_steps, section.burn_in, section.frame_stride, predict)
  return rollout


def _features_by_condition(run: Run, split: str, conditions):
  slots, labels = load_split(run, split)
  rollout = rollout_fn(run) if contact.ROLLOUT in conditions else None
  return {c: contact.condition_features(
      slots, c, run.config.readout.observed_frames, rollout)
          for c in conditions}, labels


def _trained(run: Run, condition: str, seed: int) -> bool:
  return os.path.exists(os.path.join(run.paths.readout(condition, seed),
                                     'selection.json'))


def train_readout(run: Run) -> None:
  """Fits the readout per chain, condition and seed (`Run.readout_chains`);
  selection on validation."""
  readout = run.config.readout
  conditions = tuple(readout.conditions)
  train_split, val_split, _ = contact.readout_splits(readout)
  model = contact.build_readout(readout, run.slot_model.slot_shape[1])
  if run.seeds is not None:
    logger.info('seeds %s: one readout per chain, seed s on chain s '
                '(readout.seeds is not used)', run.seeds)
  for chain, seeds in run.readout_chains(readout.seeds):
    if all(_trained(chain, c, seed) for c in conditions for seed in seeds):
      logger.info('readouts of seeds %s already trained', seeds)
      continue
    train, train_labels = _features_by_condition(chain, train_split,
                                                 conditions)
    val, val_labels = _features_by_condition(chain, val_split, conditions)
    for condition in conditions:
      for seed in seeds:
        _fit_one(chain, model, condition, seed, (train[condition],
                                                 train_labels),
                 (val[condition], val_labels))


def _fit_one(run: Run, model: Any, condition: str, seed: int,
             train: tuple[np.ndarray, np.ndarray],
             val: tuple[np.ndarray, np.ndarray]) -> None:
  """Fits and writes the readout of `condition` and `seed` on `run`'s
  features, unless it is trained."""
  directory = run.paths.readout(condition, seed)
  if _trained(run, condition, seed):
    logger.info('readout %s seed %d already trained', condition, seed)
    return
  val_features, val_labels = val

  def val_accuracy(params):
    probs = readout_lib.predict(model, params, val_features)
    return readout_lib.best_threshold(probs, val_labels)[1]

  params, log = readout_fit.fit_readout(
      directory, f'readout {condition} seed {seed}', model, train,
      val_accuracy, contact.fit_config(run.config.readout), seed)
  probs = readout_lib.predict(model, params, val_features)
  threshold, accuracy = readout_lib.best_threshold(probs, val_labels)
  # params.msgpack holds the chosen epoch's parameters (`fit_readout`); a
  # seed counts as trained once selection.json exists.
  write_json_atomic(os.path.join(directory, 'selection.json'), {
      'threshold': threshold, 'val_accuracy': accuracy,
      'best_epoch': log['best_epoch'], 'val_scores': log['scores'],
      'train_losses': log['losses']}, sort_keys=False)
  logger.info('readout %s seed %d: val accuracy %.3f (epoch %d, '
              'threshold %.1f)', condition, seed, accuracy,
              log['best_epoch'], threshold)


def evaluate_readout(run: Run) -> dict[str, Any]:
  """Test accuracy at the validation-chosen checkpoint and threshold, per
  readout of `Run.readout_chains`; mean and std over them."""
  readout = run.config.readout
  conditions = tuple(readout.conditions)
  test_split = contact.readout_splits(readout)[2]
  accuracies = {c: [] for c in conditions}
  val_accuracies = {c: [] for c in conditions}
  seeds_evaluated, picture = [], None
  for chain, seeds in run.readout_chains(readout.seeds):
    test, labels = _features_by_condition(chain, test_split, conditions)
    for seed in seeds:
      seeds_evaluated.append(seed)
      for condition in conditions:
        trained = load_readout(chain, condition, seed)
        probs = readout_lib.predict(trained.module, trained.params,
                                    test[condition])
        accuracies[condition].append(readout_lib.accuracy_at(
            probs, labels, trained.threshold))
        val_accuracies[condition].append(trained.selection['val_accuracy'])
        if picture is None and condition == contact.ROLLOUT:
          # The first readout's: its chain's rollouts and decisions.
          picture = (chain, test[condition], probs, trained.threshold, seed)
  results: dict[str, Any] = {}
  for condition in conditions:
    # A converted official readout has no validation accuracy (None).
    measured = [v for v in val_accuracies[condition] if v is not None]
    results[condition] = {
        'test_accuracy': accuracies[condition],
        'mean': float(np.mean(accuracies[condition])),
        'std': float(np.std(accuracies[condition])),
        'val_accuracy_mean': (float(np.mean(measured))
                              if len(measured) == len(val_accuracies[
                                  condition]) else None)}
  positive = float(labels.mean())
  results['chance'] = {'mean': max(positive, 1.0 - positive), 'std': 0.0}
  results['num_test_videos'] = len(labels)
  # Which seed each test_accuracy entry is; 'per_seed': each its own chain
  # (config.seeds), 'one': readout seeds on one chain.
  results['seeds'] = seeds_evaluated
  results['chains'] = 'one' if run.seeds is None else 'per_seed'
  directory = run.paths.readouts
  write_json_atomic(os.path.join(directory, 'results.json'), results,
                    sort_keys=False)
  table = contact.format_table(results, conditions)
  write_atomic(os.path.join(directory, 'results.md'), table + '\n')
  logger.info('contact prediction, test accuracy (%d seeds%s):\n%s',
              len(seeds_evaluated),
              '' if run.seeds is None else ', one chain each', table)
  if picture is not None and readout.num_pictures:
    chain, rollout_features, probs, threshold, seed = picture
    write_pictures(chain, rollout_features, probs, threshold, labels, seed,
                   directory)
  return results


# A contact picture shows at most about this many frames per row.
MAX_PICTURE_COLUMNS = 12


def picture_frames(num_frames: int, observed: int,
                   max_columns: int = MAX_PICTURE_COLUMNS) -> list[int]:
  """The frames a contact picture draws (and so the only ones it decodes):
  every k-th observed frame from 0 and every k-th rolled-out frame from
  `observed`, k chosen so that about `max_columns` are drawn."""
  stride = max(1, -(-num_frames // max_columns))
  return [*range(0, min(observed, num_frames), stride),
          *range(observed, num_frames, stride)]


def _video_names(source: Any, split: str, count: int) -> list[str]:
  """The first `count` videos' converted names ('video_01234 (test video
  0)'), else 'test video i' (embedded data, no or a damaged names file)."""
  names = None
  dataset_dir = getattr(source, 'dataset_dir', None)
  if dataset_dir is not None:
    try:
      names = video_names.read_recorded_names(dataset_dir, split)
    except UserError:
      names = None
  return [f'{names[i]} ({split} video {i})' if names and i < len(names)
          else f'{split} video {i}' for i in range(count)]


def picture_title(name: str, probability: float, threshold: float,
                  label: float, onset: int, observed: int, seed: int
                  ) -> list[str]:
  """The lines above a contact picture: which video, what the readout (on
  observed + rollout slots) said at its threshold, the truth, the legend."""
  predicts = probability > threshold  # as readout.accuracy_at decides
  return [
      name,
      f'readout on observed + rollout (seed {seed}): p(contact) = '
      f'{probability:.2f}, threshold {threshold:.2f} -> '
      f'{"contact" if predicts else "no contact"}; truth: '
      f'{"contact" if label else "no contact"}'
      + (f' (onset frame {onset})' if onset >= 0 else '')
      + ('; right' if predicts == bool(label) else '; wrong'),
      f'green border: observed frames 0-{observed - 1}; red: SlotFormer '
      'rollout',
  ]


def write_pictures(run: Run, rollout_slots: np.ndarray,
                   probabilities: np.ndarray, threshold: float,
                   labels: np.ndarray, seed: int, directory: str) -> None:
  """<directory>/test_<i>.png for the first `readout.num_pictures` test
  videos: the real frames over `run`'s slot model's decoding of [observed,
  SlotFormer rollout] slots (green border: observed, red: rolled out), frame
  numbers above, and a title (`picture_title`) with the video's name, the
  probability and `threshold` of readout `seed`, its decision and the truth.

  Only the drawn frames are decoded (STEVE generates each token by token:
  `progress.announce_decoding` says what that costs before it starts)."""
  readout = run.config.readout
  slot_model = run.slot_model
  if not slot_model.decodes_pixels:
    logger.info('contact pictures skipped: %s decodes no pixels',
                slot_model.label)
    return
  count = min(readout.num_pictures, len(labels))
  observed = readout.observed_frames
  drawn = picture_frames(rollout_slots.shape[1], observed)
  progress.announce_decoding(
      'contact pictures', slot_model, count * len(drawn),
      '--config.readout.num_pictures (now %d)' % readout.num_pictures)
  params = run.stage1.params
  decode = jax.jit(lambda slots: slot_model.decode(params, slots).recon)
  split = contact.readout_splits(readout)[2]
  videos = run.videos(split)
  names = _video_names(videos, split, count)
  scale = max(1, round(96 / videos[0]['video'].shape[1]))
  colour = lambda t: (visualize.OBSERVED_COLOUR if t < observed
                      else visualize.ROLLOUT_COLOUR)
  for i in progress.bar(range(count), desc='contact pictures',
                        unit='picture'):
    video = videos[i]
    truth = video['video'][drawn]
    predicted = to_uint8(decode(jnp.asarray(rollout_slots[i][drawn])))
    grid = visualize.labelled_tile_grid(
        {'real frames': [visualize.framed_tile(f, colour(t), scale)
                         for f, t in zip(truth, drawn)],
         f'{slot_model.label} decoding': [
             visualize.framed_tile(f, colour(t), scale)
             for f, t in zip(predicted, drawn)]},
        [f't={t}' for t in drawn])
    title = picture_title(
        names[i], float(probabilities[i]), threshold,
        float(labels[i]), int(video.get('contact_frame', -1)), observed,
        seed)
    visualize.write_png(os.path.join(directory, f'test_{i}.png'),
                        visualize.titled(grid, title))


TASK = register(Task(
    name='contact', config='configs/synthetic_contact.py',
    stages={'train_readout': train_readout,
            'evaluate_readout': evaluate_readout},
    seeded=('train_readout', 'evaluate_readout'),
    section='readout', defaults=defaults.contact_readout_config,
    reads=lambda config: tuple(
        (f'readout.splits.{k}', v)
        for k, v in sorted(config.readout.splits.items()))))
