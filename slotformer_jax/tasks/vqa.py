"""CLEVRER-style VQA with Aloe over slots: frames, batches, loss, metrics.

Pure pieces (no training imports): which slot frames a question sees, how
questions become fixed-shape batches, the loss, the metrics per question
type, the answer-prior baseline and the test-split prediction file.

Frames: as the official code, ``num_frames`` slot frames with stride
``stride`` from a random start (uniform over the starts that fit in the
``video_length`` observed frames). For a predictive question, when the slots
continue past the video (a SlotFormer rollout appended), the window is
shifted by the number of appended frames, onto the rollout.

Batches (fixed shapes for jit; open and multiple-choice questions in two
sub-batches, both always present):
  open_slots [Bo, T, N, D], open_tokens int32 [Bo, L], open_pad bool [Bo, L],
  open_label int32 [Bo], open_valid bool [Bo];
  choice_slots [Bc, T, N, D], choice_tokens int32 [Bc, C, L], choice_pad bool
  [Bc, C, L], choice_label int32 [Bc, C], choice_valid bool [Bc, C] (padded
  choices and padding questions are invalid), choice_type int32 [Bc].
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax

from slotformer_jax.data.pipeline import host_rows
from slotformer_jax.data.vqa import QUESTION_TYPES
from slotformer_jax.data.vqa import EncodedQuestion
from slotformer_jax.modules.aloe import Aloe

PREDICTIVE = QUESTION_TYPES.index('predictive')


# ----------------------------------------------------------------------------
# Frames
# ----------------------------------------------------------------------------


def frame_indices(start: int, num_frames: int, stride: int) -> np.ndarray:
  return start + stride * np.arange(num_frames)


def num_starts(video_length: int, num_frames: int, stride: int) -> int:
  """How many window starts fit in the observed video (official: 128 frames,
  25 samples, stride 5 -> starts 0..7)."""
  count = video_length - (num_frames - 1) * stride
  if count < 1:
    raise ValueError(f'{num_frames} frames with stride {stride} do not fit '
                     f'in {video_length} frames')
  return count


def question_frames(start: int, *, video_length: int, available: int,
                    num_frames: int, stride: int, predictive: bool
                    ) -> np.ndarray:
  """Slot frames a question reads, int [num_frames].

  ``available`` frames of slots exist: the observed ``video_length``, plus
  any rollout appended after them. Predictive questions look
  ``available - video_length`` frames later, i.e. onto the rollout.
  """
  if predictive:
    start += available - video_length
  indices = frame_indices(start, num_frames, stride)
  if indices[-1] >= available:
    raise ValueError(f'frame {indices[-1]} asked for, {available} available')
  return indices


def rollout_after_video(rollout: Callable[[np.ndarray, int], np.ndarray],
                        observed: np.ndarray, *, burn_in: int, stride: int,
                        num_frames: int) -> np.ndarray:
  """The ``num_frames`` slot frames after the video, from a dynamics model.

  A model trained on every ``stride``-th frame predicts every
  ``stride``-th frame: as the official CLEVRER rollout, run it ``stride``
  times, from the histories ending at the last ``stride`` observed frames
  (offsets 0..stride-1), and interleave the predictions.

  Args:
    rollout: (history [B, burn_in, N, D], steps) -> [B, steps, N, D].
    observed: [B, T, N, D] slots of the video (T >= burn_in * stride).

  Returns:
    [B, num_frames, N, D]; frame k is video frame T + k.
  """
  t = observed.shape[1]
  if t < burn_in * stride:
    raise ValueError(f'{t} observed frames < burn_in {burn_in} x stride '
                     f'{stride}')
  steps = -(-num_frames // stride)
  per_offset = []
  for offset in range(stride):
    history = observed[:, t - burn_in * stride + offset::stride][:, :burn_in]
    per_offset.append(np.asarray(rollout(history, steps)))
  frames = [per_offset[k % stride][:, k // stride] for k in range(num_frames)]
  return np.stack(frames, axis=1)


# ----------------------------------------------------------------------------
# Batches
# ----------------------------------------------------------------------------


class QuestionBatches:
  """Fixed-shape batches of encoded questions with their videos' slots.

  Args:
    questions: encoded questions of one split.
    slots_of: video filename -> float32 [available, N, D] slots (observed,
      then rollout if any).
    video_length: observed frames of every video.
    num_frames, stride: the frame window (see :func:`question_frames`).
    max_choices: C; questions with more choices are rejected.
    blind: zero slots (the question-only baseline).
    choice_weights: question type name -> weight of its multiple-choice
      questions in the training draws (missing types weigh 1); None draws
      them uniformly (as do equal weights of every type).
  """

  def __init__(self, questions: Sequence[EncodedQuestion],
               slots_of: Callable[[str], np.ndarray], *, video_length: int,
               num_frames: int, stride: int, max_choices: int,
               blind: bool = False,
               choice_weights: Mapping[str, float] | None = None):
    self.open = [q for q in questions if q.is_descriptive]
    self.choice = [q for q in questions if not q.is_descriptive]
    too_many = [q for q in self.choice if len(q.choice_ids) > max_choices]
    if too_many:
      raise ValueError(f'{len(too_many)} questions have more than '
                       f'{max_choices} choices (raise max_choices)')
    self.slots_of = slots_of
    self.video_length = video_length
    self.num_frames = num_frames
    self.stride = stride
    self.max_choices = max_choices
    self.blind = blind
    self.num_starts = num_starts(video_length, num_frames, stride)
    self.choice_p = None  # None: uniform draws
    weights = dict(choice_weights or {})
    unknown = set(weights) - set(QUESTION_TYPES[1:])
    if unknown:
      raise ValueError(f'choice_weights names {sorted(unknown)}, not '
                       f'multiple-choice types {QUESTION_TYPES[1:]}')
    per_type = [float(weights.get(t, 1.0)) for t in QUESTION_TYPES[1:]]
    if min(per_type) < 0 or max(per_type) <= 0:
      raise ValueError(f'choice_weights must be >= 0, some > 0: {weights}')
    if self.choice and len(set(per_type)) > 1:
      w = np.array([per_type[q.question_type - 1] for q in self.choice])
      if w.sum() <= 0:
        raise ValueError(f'choice_weights {weights} leave no question')
      self.choice_p = w / w.sum()

  def _slots(self, q: EncodedQuestion, start: int) -> np.ndarray:
    slots = self.slots_of(q.video_filename)
    idx = question_frames(start, video_length=self.video_length,
                          available=len(slots), num_frames=self.num_frames,
                          stride=self.stride,
                          predictive=q.question_type == PREDICTIVE)
    out = np.asarray(slots[idx], np.float32)
    return np.zeros_like(out) if self.blind else out

  def batch(self, open_ids: Sequence[int], choice_ids: Sequence[int],
            starts: np.ndarray, open_size: int, choice_size: int
            ) -> dict[str, np.ndarray]:
    """Questions ``self.open[open_ids]`` and ``self.choice[choice_ids]``,
    padded to ``open_size`` / ``choice_size`` with invalid rows;
    ``starts`` [len(open_ids) + len(choice_ids)] window starts."""
    def pad_rows(rows: list[np.ndarray], size: int) -> np.ndarray:
      # [size, ...]; size 0 (a kind not drawn) keeps the row shape.
      rows = rows + [np.zeros_like(rows[0])] * (size - len(rows))
      return np.stack(rows)[:size]

    template = self.open[0] if self.open else self.choice[0]
    slot_shape = self._slots(template, 0).shape
    text_length = template.tokens.shape[-1]
    c = self.max_choices
    o_slots, o_tokens, o_pad, o_label = [], [], [], []
    for k, i in enumerate(open_ids):
      q = self.open[i]
      o_slots.append(self._slots(q, int(starts[k])))
      o_tokens.append(q.tokens[0])
      o_pad.append(q.pad_mask[0])
      o_label.append(np.int32(max(q.answer, 0)))
    c_slots, c_tokens, c_pad, c_label, c_valid, c_type = [], [], [], [], [], []
    for k, i in enumerate(choice_ids):
      q = self.choice[i]
      n = len(q.choice_ids)
      c_slots.append(self._slots(q, int(starts[len(open_ids) + k])))
      tokens = np.zeros((c, text_length), np.int32)
      pad = np.ones((c, text_length), bool)
      tokens[:n], pad[:n] = q.tokens, q.pad_mask
      c_tokens.append(tokens)
      c_pad.append(pad)
      label = np.zeros((c,), np.int32)
      label[:n] = np.maximum(q.choice_labels, 0)
      c_label.append(label)
      c_valid.append(np.arange(c) < n)
      c_type.append(np.int32(q.question_type))
    empty_slots = [np.zeros(slot_shape, np.float32)]
    return {
        'open_slots': pad_rows(o_slots or empty_slots, open_size),
        'open_tokens': pad_rows(o_tokens or [np.zeros(text_length, np.int32)],
                                open_size),
        'open_pad': pad_rows(o_pad or [np.ones(text_length, bool)], open_size),
        'open_label': pad_rows(o_label or [np.int32(0)], open_size),
        'open_valid': np.arange(open_size) < len(open_ids),
        'choice_slots': pad_rows(c_slots or empty_slots, choice_size),
        'choice_tokens': pad_rows(c_tokens or [np.zeros((c, text_length),
                                                        np.int32)],
                                  choice_size),
        'choice_pad': pad_rows(c_pad or [np.ones((c, text_length), bool)],
                               choice_size),
        'choice_label': pad_rows(c_label or [np.zeros(c, np.int32)],
                                 choice_size),
        'choice_valid': (pad_rows(c_valid or [np.zeros(c, bool)], choice_size)
                         & (np.arange(choice_size) < len(choice_ids))[:, None]),
        'choice_type': pad_rows(c_type or [np.int32(0)], choice_size),
    }

  def train_batches(self, open_size: int, choice_size: int, seed: int,
                    start_step: int = 0, process_index: int = 0,
                    process_count: int = 1
                    ) -> Iterator[dict[str, np.ndarray]]:
    """Random questions and window starts, this host's rows of the global
    batch. ``open_size`` / ``choice_size`` are per host; every host draws the
    same global batch of ``P * open_size`` / ``P * choice_size`` questions and
    keeps rows ``[p * size, (p + 1) * size)`` of each, so batch ``s`` depends
    only on (seed, s, the global sizes): a resumed run sees the same stream,
    and so does the same run on another number of hosts.

    A kind with no question (an open-only or choice-only set) or a size of
    0 is not drawn: its ``size`` rows are padding (``*_valid`` False)."""
    open_drawn = open_size if self.open else 0
    choice_drawn = choice_size if self.choice else 0
    open_rows = host_rows(open_drawn, process_index)
    choice_rows = host_rows(choice_drawn, process_index)
    open_total = process_count * open_drawn
    choice_total = process_count * choice_drawn
    nothing = np.zeros((0,), np.int64)
    step = start_step
    while True:
      rng = np.random.default_rng([seed, step])
      open_ids = (rng.integers(0, len(self.open), open_total) if open_total
                  else nothing)
      if not choice_total:
        choice_ids = nothing
      elif self.choice_p is None:
        choice_ids = rng.integers(0, len(self.choice), choice_total)
      else:  # e.g. more predictive questions per step
        choice_ids = rng.choice(len(self.choice), choice_total,
                                p=self.choice_p)
      starts = rng.integers(0, self.num_starts, open_total + choice_total)
      starts = np.concatenate([starts[:open_total][open_rows],
                               starts[open_total:][choice_rows]])
      yield self.batch(list(open_ids[open_rows]),
                       list(choice_ids[choice_rows]), starts, open_size,
                       choice_size)
      step += 1

  def eval_batches(self, open_size: int, choice_size: int
                   ) -> Iterator[tuple[dict[str, np.ndarray], list[int],
                                       list[int]]]:
    """Every question once, with the middle window start (deterministic);
    yields (batch, open ids, choice ids)."""
    start = self.num_starts // 2
    num = max(-(-len(self.open) // open_size),
              -(-len(self.choice) // choice_size))
    for b in range(num):
      open_ids = list(range(b * open_size,
                            min(len(self.open), (b + 1) * open_size)))
      choice_ids = list(range(b * choice_size,
                              min(len(self.choice), (b + 1) * choice_size)))
      starts = np.full(len(open_ids) + len(choice_ids), start)
      yield (self.batch(open_ids, choice_ids, starts, open_size, choice_size),
             open_ids, choice_ids)


# ----------------------------------------------------------------------------
# Loss (pure; jitted by the caller)
# ----------------------------------------------------------------------------


def vqa_loss(params: Any, batch: Mapping[str, jax.Array], frozen_params: Any,
             rng: jax.Array, *, model: Aloe) -> tuple[jax.Array, dict]:
  """Cross-entropy of open answers + binary cross-entropy per choice
  (both weighted 1, as the official code), over valid rows only."""
  del frozen_params
  open_logits, choice_logits = model.apply(
      params, batch['open_slots'], batch['open_tokens'], batch['open_pad'],
      batch['choice_slots'], batch['choice_tokens'], batch['choice_pad'],
      deterministic=False, rngs={'dropout': rng})
  open_valid = batch['open_valid'].astype(jnp.float32)
  ce = optax.softmax_cross_entropy_with_integer_labels(
      open_logits, batch['open_label'])
  open_loss = (ce * open_valid).sum() / jnp.maximum(open_valid.sum(), 1.0)
  choice_valid = batch['choice_valid'].astype(jnp.float32)
  bce = optax.sigmoid_binary_cross_entropy(
      choice_logits, batch['choice_label'].astype(jnp.float32))
  choice_loss = (bce * choice_valid).sum() / jnp.maximum(
      choice_valid.sum(), 1.0)
  open_acc = ((open_logits.argmax(-1) == batch['open_label']) * open_valid
              ).sum() / jnp.maximum(open_valid.sum(), 1.0)
  option_acc = (((choice_logits > 0) == (batch['choice_label'] > 0))
                * choice_valid).sum() / jnp.maximum(choice_valid.sum(), 1.0)
  return open_loss + choice_loss, {
      'open_loss': open_loss, 'choice_loss': choice_loss,
      'open_accuracy': open_acc, 'option_accuracy': option_acc}


def predict(params: Any, batch: Mapping[str, jax.Array], *, model: Aloe
            ) -> tuple[jax.Array, jax.Array]:
  """(open answer ids [Bo], choice logits [Bc, C]), dropout off."""
  open_logits, choice_logits = model.apply(
      params, batch['open_slots'], batch['open_tokens'], batch['open_pad'],
      batch['choice_slots'], batch['choice_tokens'], batch['choice_pad'])
  return open_logits.argmax(-1), choice_logits


# ----------------------------------------------------------------------------
# Metrics
# ----------------------------------------------------------------------------


def score_choices(correct_option: np.ndarray, valid: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
  """Per question: (options right, question right), [B] each.

  Args:
    correct_option: bool [B, C], prediction == label per option.
    valid: bool [B, C], real options.
  A question is right only if every one of its options is.
  """
  options_right = (correct_option & valid).sum(-1)
  question_right = np.all(correct_option | ~valid, axis=-1)
  return options_right, question_right


class VqaMetrics:
  """Accumulates per question type: descriptive accuracy; per-option and
  per-question accuracy of multiple-choice types."""

  def __init__(self):
    self.open_right = 0
    self.open_count = 0
    self.options = collections.Counter()
    self.option_right = collections.Counter()
    self.questions = collections.Counter()
    self.question_right = collections.Counter()

  def add_open(self, predicted: np.ndarray, labels: np.ndarray) -> None:
    self.open_right += int((np.asarray(predicted) == labels).sum())
    self.open_count += int(len(labels))

  def add_choices(self, predicted: np.ndarray, labels: np.ndarray,
                  valid: np.ndarray, question_types: np.ndarray) -> None:
    """predicted, labels: bool/int [B, C]; valid [B, C]; types [B]."""
    correct = np.asarray(predicted).astype(bool) == np.asarray(labels).astype(
        bool)
    options_right, question_right = score_choices(correct, valid)
    for t, n, o, q in zip(question_types, valid.sum(-1), options_right,
                          question_right):
      name = QUESTION_TYPES[int(t)]
      self.options[name] += int(n)
      self.option_right[name] += int(o)
      self.questions[name] += 1
      self.question_right[name] += int(q)

  def results(self) -> dict[str, dict[str, float]]:
    out = {}
    if self.open_count:
      out['descriptive'] = {'accuracy': self.open_right / self.open_count,
                            'questions': self.open_count}
    for name in QUESTION_TYPES[1:]:
      if self.questions[name]:
        out[name] = {
            'per_option': self.option_right[name] / self.options[name],
            'per_question': self.question_right[name] / self.questions[name],
            'questions': self.questions[name]}
    if sum(self.questions.values()):
      out['multiple_choice'] = {
          'per_option': sum(self.option_right.values()) / sum(
              self.options.values()),
          'per_question': sum(self.question_right.values()) / sum(
              self.questions.values()),
          'questions': sum(self.questions.values())}
    return out


def open_accuracy_per_template(questions: Sequence[EncodedQuestion],
                               open_answers: Mapping[int, int]
                               ) -> dict[str, dict[str, float]]:
  """Descriptive accuracy per template (embedded data; CLEVRER's files have
  no templates): which questions read the slots shows here first.

  Args:
    questions: the encoded questions (``questions[k]``).
    open_answers: k -> predicted answer id, for descriptive questions.
  """
  right, count = collections.Counter(), collections.Counter()
  for k, answer in open_answers.items():
    q = questions[k]
    if q.template and q.answer >= 0:
      right[q.template] += int(answer == q.answer)
      count[q.template] += 1
  return {t: {'accuracy': right[t] / count[t], 'questions': count[t]}
          for t in sorted(count)}


# ----------------------------------------------------------------------------
# The answer prior
# ----------------------------------------------------------------------------


def _prior_key(q: EncodedQuestion) -> str:
  # Per template where known (embedded data), else per question type.
  return q.template or QUESTION_TYPES[q.question_type]


def fit_answer_prior(train: Sequence[EncodedQuestion]) -> dict[str, Any]:
  """The most frequent open answer per template, and the more frequent
  choice label per template (a model that never looks at the video or the
  words beyond the template)."""
  open_counts = collections.defaultdict(collections.Counter)
  choice_counts = collections.defaultdict(collections.Counter)
  for q in train:
    if q.is_descriptive:
      open_counts[_prior_key(q)][q.answer] += 1
    else:
      choice_counts[_prior_key(q)].update(q.choice_labels.tolist())
  def mode(counts: collections.Counter) -> int:
    # Ties go to the smaller id, independently of the question order.
    return min(counts, key=lambda value: (-counts[value], value))

  return {'open': {k: mode(c) for k, c in open_counts.items()},
          'choice': {k: mode(c) for k, c in choice_counts.items()}}


def evaluate_answer_prior(prior: Mapping[str, Any],
                          questions: Sequence[EncodedQuestion]
                          ) -> dict[str, dict[str, float]]:
  metrics = VqaMetrics()
  for q in questions:
    if q.is_descriptive:
      metrics.add_open(np.array([prior['open'].get(_prior_key(q), -1)]),
                       np.array([q.answer]))
    else:
      label = prior['choice'].get(_prior_key(q), 0)
      n = len(q.choice_labels)
      metrics.add_choices(np.full((1, n), label), q.choice_labels[None],
                          np.ones((1, n), bool), np.array([q.question_type]))
  return metrics.results()


# ----------------------------------------------------------------------------
# The public evaluation server's prediction file
# ----------------------------------------------------------------------------


def prediction_file(questions: Sequence[EncodedQuestion],
                    open_answers: Mapping[int, int],
                    choice_correct: Mapping[int, Sequence[bool]],
                    answer_names: Sequence[str]) -> list[dict[str, Any]]:
  """CLEVRER's submission layout: one entry per scene, in scene order::

    [{'scene_index': 15000, 'questions': [
        {'question_id': 0, 'answer': 'cube'},
        {'question_id': 3, 'choices': [{'choice_id': 0, 'answer': 'wrong'},
                                       ...]}]}, ...]

  Args:
    questions: the encoded test questions (``questions[k]``).
    open_answers: k -> answer id, for descriptive questions.
    choice_correct: k -> per-choice bool (choice order of the question).
    answer_names: answer id -> text.
  """
  scenes: dict[int, list[dict[str, Any]]] = collections.OrderedDict()
  for k, q in enumerate(questions):
    entries = scenes.setdefault(q.scene_index, [])
    if q.is_descriptive:
      entries.append({'question_id': q.question_id,
                      'answer': answer_names[int(open_answers[k])]})
    else:
      entries.append({'question_id': q.question_id, 'choices': [
          {'choice_id': int(c), 'answer': 'correct' if right else 'wrong'}
          for c, right in zip(q.choice_ids, choice_correct[k])]})
  return [{'scene_index': s, 'questions': sorted(
      entries, key=lambda e: e['question_id'])}
          for s, entries in sorted(scenes.items())]


def build_aloe(vqa: ml_collections.ConfigDict, vocab_size: int,
               num_answers: int, *, num_slots: int) -> Aloe:
  """Aloe for the `vqa` section, over `num_slots` slots per frame."""
  return Aloe(
      vocab_size=vocab_size, num_answers=num_answers,
      num_frames=vqa.num_frames, num_slots=num_slots,
      text_length=vqa.max_question_len + vqa.max_choice_len,
      question_length=vqa.max_question_len, d_model=vqa.d_model,
      word_dim=vqa.word_dim, num_layers=vqa.num_layers,
      num_heads=vqa.num_heads, mlp_size=vqa.mlp_size,
      head_size=vqa.head_size, dropout_rate=vqa.dropout_rate,
      positions=vqa.positions, layer_norm_epsilon=vqa.layer_norm_epsilon)
