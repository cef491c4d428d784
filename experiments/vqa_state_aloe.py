r"""Can Aloe learn the embedded predictive questions from perfect object states?
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_state_aloe.py [--config=configs/synthetic_vqa.py]
      [--num_train=600] [--inputs=future,observed] [--binding=words,given]
      [--seeds=0,1,2] [--steps=3000] [--dropout=0] [--choice_batch_size=32]
      [--split=test] [--out=result.json]

The slot model and the dynamics model taken out of the question: the first
`num_train` / `num_val` / `num_test` videos of the config's CLEVRER-like
family are simulated (physics and counterfactual worlds, no rendering), with
the event logs and questions a built dataset would have (the same
generator), and every frame's simulator state becomes one "slot" per object
(:func:`state_slots`: colour and shape one-hot, ground position, ground
velocity, in-view flag). The config's Aloe (`config.vqa`: layers, width,
frames, stride, batch sizes, learning rate, dropout) is trained on the
descriptive questions and on every predictive option, each as a one-choice
question (so per-option accuracy means what it means in `evaluate_vqa`),
with the pipeline's batches, window sampling and loss (`tasks/vqa.py`):

* `future`: the observed frames + the simulated frames after the video, read
  by predictive questions as SlotFormer's rollout is (what a perfect slot
  model and a perfect dynamics model would give Aloe);
* `observed`: the video only (predictive questions read its end).

`--binding`: 'words' gives Aloe every slot (it must find the two objects an
option names from its words, as in the pipeline); 'given' zeroes, for each
predictive option, every slot but those of the two objects it names, so the
binding of words to slots is given and what is left is reading (or
extrapolating) the pair's motion. Prints, per binding, input and seed,
per-option predictive and descriptive accuracy on `--split`, and the mean
+- std (numpy's population std) over seeds.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib.util
import json
import re
import time
from collections.abc import Mapping, Sequence
from typing import Any

from slotformer_jax.runtime import xla_flags

xla_flags.apply_fast_cpu_flags()

# pylint: disable=g-import-not-at-top,wrong-import-position
import jax
import numpy as np

from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.datasets import clevrer_like
from slotformer_jax.datasets import clevrer_like_questions as question_generator
from slotformer_jax.data.write.pool import ordered_map
from slotformer_jax.datasets.synthetic import COLORS, SHAPES
from slotformer_jax.data.events import EventLog
from slotformer_jax.tasks import vqa as task
from slotformer_jax.train import optim

PREDICTIVE = question_generator.QUESTION_TYPES.index('predictive')
STATE_FEATURES = len(COLORS) + len(SHAPES) + 5  # + x, y, vx, vy, in view
_CHOICE = re.compile(r'the (.+) collides with the (.+)')


def state_slots(positions: np.ndarray, in_view: np.ndarray,
                objects: Sequence[Mapping[str, str]], num_slots: int,
                slot_size: int) -> np.ndarray:
  """Simulator states as slots, float32 [T, num_slots, slot_size].

  Slot i is object i (later slots zero): colour one-hot, shape one-hot,
  ground position / 3 m, ground velocity per frame x 5 (finite difference,
  0 at frame 0), 1, all zero while the object is out of view.

  Args:
    positions: float [T, O, 3] object centres (clevrer_like.simulate).
    in_view: bool [T, O].
    objects: per object {'color', 'shape'} (the event log's objects).
  """
  if len(objects) > num_slots or slot_size < STATE_FEATURES:
    raise ValueError(f'{len(objects)} objects / {STATE_FEATURES} features do '
                     f'not fit {num_slots} slots of {slot_size}')
  ground = np.asarray(positions, np.float64)[..., :2]
  velocity = np.diff(ground, axis=0, prepend=ground[:1])
  out = np.zeros((len(ground), num_slots, slot_size), np.float32)
  c = len(COLORS)
  s = c + len(SHAPES)
  for i, obj in enumerate(objects):
    out[:, i, COLORS.index(obj['color'])] = 1.0
    out[:, i, c + SHAPES.index(obj['shape'])] = 1.0
    out[:, i, s:s + 2] = ground[:, i] / 3.0
    out[:, i, s + 2:s + 4] = velocity[:, i] * 5.0
    out[:, i, s + 4] = 1.0
    out[:, i] *= np.asarray(in_view[:, i], np.float32)[:, None]
  return out


def keep_slots(slots: np.ndarray, keep: Sequence[int]) -> np.ndarray:
  """``slots`` [T, N, D] with every slot not in ``keep`` zeroed."""
  mask = np.zeros(slots.shape[1], np.float32)
  mask[list(keep)] = 1.0
  return slots * mask[None, :, None]


def choice_objects(choice: str, objects: Sequence[Mapping[str, str]]
                   ) -> tuple[int, int]:
  """The two object indices a predictive choice "the X collides with the Y"
  names (objects are named "<colour> <shape>", distinct in a video)."""
  match = _CHOICE.fullmatch(choice)
  if match is None:
    raise ValueError(f'not a predictive choice: {choice!r}')
  names = {f"{o['color']} {o['shape']}": i for i, o in enumerate(objects)}
  return names[match.group(1)], names[match.group(2)]


def one_choice_questions(question: vqa_data.EncodedQuestion,
                         choices: Sequence[str], key: str,
                         objects: Sequence[Mapping[str, str]]
                         ) -> list[tuple[vqa_data.EncodedQuestion,
                                         tuple[int, int]]]:
  """A predictive question as one one-choice question per option, each with
  the objects it names; its ``video_filename`` becomes ``key#k``."""
  out = []
  for k, text in enumerate(choices):
    out.append((dataclasses.replace(
        question, video_filename=f'{key}#{k}',
        tokens=question.tokens[k:k + 1], pad_mask=question.pad_mask[k:k + 1],
        choice_ids=question.choice_ids[k:k + 1],
        choice_labels=question.choice_labels[k:k + 1]),
                choice_objects(text, objects)))
  return out


def _simulated(config: clevrer_like.ClevrerLikeConfig, num_slots: int,
               slot_size: int, split: str, index: int
               ) -> tuple[dict[str, Any], np.ndarray]:
  video = clevrer_like.generate_video(config, split, index, render=False)
  log = video['events']
  slots = state_slots(video['positions'], video['in_view'], log.objects,
                      num_slots, slot_size)
  return log.to_dict(), slots


def simulate_split(config: clevrer_like.ClevrerLikeConfig, split: str,
                   num_slots: int, slot_size: int, num_workers: int | None
                   ) -> tuple[list[dict[str, Any]], np.ndarray]:
  """(event logs, state slots [V, T, num_slots, slot_size]) of a split."""
  make = functools.partial(_simulated, config, num_slots, slot_size, split)
  results = list(ordered_map(make, config.num_videos(split), num_workers))
  return [r[0] for r in results], np.stack([r[1] for r in results])


class SplitData:
  """Encoded questions of one split and the slots each one reads."""

  def __init__(self, config: clevrer_like.ClevrerLikeConfig, split: str,
               logs: list[dict[str, Any]], slots: np.ndarray,
               vocab: vqa_data.Vocabulary, vqa: Any, *, observed_only: bool,
               named_only: bool):
    scenes = question_generator.generate_split(
        [EventLog.from_dict(d) for d in logs], config.seed,
        split, video_filenames=[clevrer_like.video_filename(split, i)
                                for i in range(len(logs))],
        scene_offset=clevrer_like.SCENE_OFFSETS[split])
    if observed_only:
      slots = slots[:, :config.observed_frames]
    self.slots = slots
    self.questions: list[vqa_data.EncodedQuestion] = []
    self._keep: dict[str, tuple[int, int] | None] = {}
    for v, scene in enumerate(scenes):
      for q in scene['questions']:
        encoded = vqa_data.encode_question(scene, q, vocab,
                                           vqa.max_question_len,
                                           vqa.max_choice_len)
        key = f'{v}:{q["question_id"]}'
        if encoded.is_descriptive:
          self.questions.append(dataclasses.replace(encoded,
                                                    video_filename=key))
          self._keep[key] = None
        elif encoded.question_type == PREDICTIVE:
          for one, named in one_choice_questions(
              encoded, [c['choice'] for c in q['choices']], key,
              logs[v]['objects']):
            self.questions.append(one)
            self._keep[one.video_filename] = named if named_only else None

  def slots_of(self, key: str) -> np.ndarray:
    video = int(key.split(':')[0])
    keep = self._keep[key]
    return (self.slots[video] if keep is None
            else keep_slots(self.slots[video], keep))

  def batches(self, vqa: Any) -> task.QuestionBatches:
    return task.QuestionBatches(
        self.questions, self.slots_of,
        video_length=vqa.video_length, num_frames=vqa.num_frames,
        stride=vqa.frame_stride, max_choices=1)


def train_and_evaluate(config: Any, train: SplitData, evaluation: SplitData,
                       vocab: vqa_data.Vocabulary, seed: int
                       ) -> dict[str, float]:
  """Trains Aloe for ``config.vqa.num_train_steps`` and scores it."""
  vqa = config.vqa
  model = task.build_aloe(config.vqa, len(vocab.questions),
                        len(vocab.answers), num_slots=config.savi.num_slots)
  train_batches = train.batches(vqa)
  stream = train_batches.train_batches(vqa.open_batch_size,
                                       vqa.choice_batch_size, seed=seed)
  first = next(stream)
  params = model.init(
      {'params': jax.random.key(seed), 'dropout': jax.random.key(seed + 1)},
      first['open_slots'], first['open_tokens'], first['open_pad'],
      first['choice_slots'], first['choice_tokens'], first['choice_pad'])
  optimizer, _ = optim.make_optimizer(vqa)
  opt_state = optimizer.init(params)

  @jax.jit
  def update(params, opt_state, batch, rng):
    grads, metrics = jax.grad(
        functools.partial(task.vqa_loss, model=model), has_aux=True)(
            params, batch, None, rng)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return jax.tree.map(lambda p, u: p + u, params, updates), opt_state, \
        metrics

  rng = jax.random.key(seed + 2)
  batch = first
  for step in range(vqa.num_train_steps):
    params, opt_state, metrics = update(params, opt_state, batch,
                                        jax.random.fold_in(rng, step))
    batch = next(stream)
  predict = jax.jit(functools.partial(task.predict, model=model))
  metrics = task.VqaMetrics()
  size = vqa.eval_batch_size
  for batch, open_ids, choice_ids in evaluation.batches(vqa).eval_batches(
      size, size):
    answers, logits = predict(params, batch)
    n_open, n_choice = len(open_ids), len(choice_ids)
    metrics.add_open(np.asarray(answers)[:n_open],
                     batch['open_label'][:n_open])
    metrics.add_choices(np.asarray(logits)[:n_choice] > 0,
                        batch['choice_label'][:n_choice],
                        batch['choice_valid'][:n_choice],
                        batch['choice_type'][:n_choice])
  results = metrics.results()
  return {'predictive_per_option': results['predictive']['per_option'],
          'predictive_options': results['predictive']['questions'],
          'descriptive': results['descriptive']['accuracy'],
          'descriptive_questions': results['descriptive']['questions']}


def _load_config(spec: str) -> Any:
  path, _, variant = spec.partition(':')
  module_spec = importlib.util.spec_from_file_location('vqa_config', path)
  module = importlib.util.module_from_spec(module_spec)
  module_spec.loader.exec_module(module)
  return module.get_config(variant)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--config', default='configs/synthetic_vqa.py')
  parser.add_argument('--num_train', type=int, default=None,
                      help="training videos (default: the config's)")
  parser.add_argument('--inputs', default='future,observed')
  parser.add_argument('--binding', default='words,given')
  parser.add_argument('--seeds', default='0,1,2')
  parser.add_argument('--steps', type=int, default=None,
                      help="Aloe steps (default: the config's)")
  parser.add_argument('--dropout', type=float, default=None)
  parser.add_argument('--choice_batch_size', type=int, default=None,
                      help="predictive options per step (default: the "
                      "config's choice_batch_size)")
  parser.add_argument('--split', default='val', choices=('val', 'test'))
  parser.add_argument('--num_workers', type=int, default=None)
  parser.add_argument('--out', default=None, help='write the results here')
  args = parser.parse_args()

  config = _load_config(args.config)
  if args.num_train is not None:
    config.data.num_train = args.num_train
  if args.steps is not None:
    config.vqa.num_train_steps = args.steps
  if args.dropout is not None:
    config.vqa.dropout_rate = args.dropout
  if args.choice_batch_size is not None:
    config.vqa.choice_batch_size = args.choice_batch_size
  family = clevrer_like.config_from_data_config(config.data)
  vocab = vqa_data.Vocabulary(
      vqa_data.make_vocabulary(question_generator.template_words()),
      vqa_data.make_vocabulary(question_generator.template_answers()))
  start = time.time()
  simulated = {split: simulate_split(family, split, config.savi.num_slots,
                                     config.savi.slot_size, args.num_workers)
               for split in ('train', args.split)}
  print(f'simulated {family.num_train} + {family.num_videos(args.split)} '
        f'videos in {time.time() - start:.0f} s', flush=True)
  results: dict[str, list[dict[str, float]]] = {}
  for binding in args.binding.split(','):
    if binding not in ('words', 'given'):
      raise SystemExit(f'--binding: words or given, not {binding!r}')
    for inputs in args.inputs.split(','):
      if inputs not in ('future', 'observed'):
        raise SystemExit(f'--inputs: future or observed, not {inputs!r}')
      data = {split: SplitData(family, split, *simulated[split], vocab,
                               config.vqa,
                               observed_only=inputs == 'observed',
                               named_only=binding == 'given')
              for split in simulated}
      for seed in (int(s) for s in args.seeds.split(',')):
        t0 = time.time()
        row = train_and_evaluate(config, data['train'], data[args.split],
                                 vocab, seed)
        row['seconds'] = time.time() - t0
        results.setdefault(f'{binding}/{inputs}', []).append(row)
        print(f'binding {binding}, {inputs}, seed {seed}: predictive per '
              f'option {100 * row["predictive_per_option"]:.1f} '
              f'({row["predictive_options"]} options), descriptive '
              f'{100 * row["descriptive"]:.1f}, {row["seconds"]:.0f} s',
              flush=True)
  print(f'\n{args.split}, {family.num_train} training videos, '
        f'{config.vqa.num_train_steps} Aloe steps, dropout '
        f'{config.vqa.dropout_rate}, {config.vqa.choice_batch_size} options '
        'per step: mean +- std over seeds')
  for name, rows in results.items():
    pred = 100 * np.array([r['predictive_per_option'] for r in rows])
    desc = 100 * np.array([r['descriptive'] for r in rows])
    print(f'  {name:16s} predictive per option {pred.mean():.1f} +- '
          f'{pred.std():.1f}   descriptive {desc.mean():.1f} +- '
          f'{desc.std():.1f}   ({len(rows)} seeds)')
  if args.out:
    with open(args.out, 'w') as f:
      json.dump({'args': vars(args), 'results': results}, f, indent=1)


if __name__ == '__main__':
  main()
