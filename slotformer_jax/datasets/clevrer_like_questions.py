"""CLEVRER-style questions about CLEVRER-like videos, answered by the simulator.

Questions come from a video's :class:`slotformer_jax.data.events.EventLog`
only, by templates of CLEVRER's four types (descriptive, explanatory,
predictive, counterfactual); explanatory and counterfactual answers come from
re-simulating the world without an object. Choices are balanced per choice
kind and open answers per template, so neither the wording nor the template
tells a label and a question-only model cannot do well. The output uses
CLEVRER's ``questions/<split>.json`` layout plus a ``template`` field, so one
reader (:mod:`slotformer_jax.data.vqa`) serves embedded and real data. The
templates, answers and balance rules: docs/vqa.md, "Questions (CLEVRER's
four types)".
"""

from __future__ import annotations

import collections
import itertools
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from slotformer_jax.data.events import NUM_VERDICTS
from slotformer_jax.data.events import Collision
from slotformer_jax.data.events import EventLog
from slotformer_jax.datasets.synthetic import COLORS
from slotformer_jax.datasets.synthetic import SHAPES

# Bump QUESTIONS_VERSION (datasets/clevrer_like.py) when the questions
# generated from an event log change: a built dataset then regenerates its
# questions from its stored event logs (the videos do not change).

QUESTION_TYPES = ('descriptive', 'explanatory', 'predictive',
                  'counterfactual')
MAX_COUNT = 5  # CLEVRER's count answers are 0..5
MAX_CHOICES = 4  # choices per question (the embedded config's max_choices)
MAX_PREDICTIVE = 2  # predictive questions per video (disjoint choices)
MAX_EXPLANATORY = 2  # explanatory questions per video (different targets)

# template -> (question type, question text with {placeholders}).
TEMPLATES: dict[str, tuple[str, str]] = {
    'count_collisions': ('descriptive', 'how many collisions happen'),
    'count_entering': ('descriptive', 'how many objects enter the scene'),
    'count_moving_end': ('descriptive',
                         'how many objects are moving when the video ends'),
    'is_moving_end': ('descriptive',
                      'is the {obj} moving when the video ends'),
    'color_collides_with': ('descriptive',
                            'what color is the object that collides with the '
                            '{obj}'),
    'shape_collides_with': ('descriptive',
                            'what shape is the object that collides with the '
                            '{obj}'),
    'color_entering': ('descriptive',
                       'what color is the object that enters the scene'),
    'responsible': ('explanatory',
                    'which of the following is responsible for the collision '
                    'between the {a} and the {b}'),
    'next': ('predictive', 'what will happen next'),
    'removed': ('counterfactual', 'what will happen if the {obj} is removed'),
}
CHOICE_TEMPLATES = {
    'presence': 'the presence of the {obj}',
    'collision_event': 'the collision between the {a} and the {b}',
    'collides': 'the {a} collides with the {b}',
}


def name(log: EventLog, i: int) -> str:
  obj = log.objects[i]
  return f"{obj['color']} {obj['shape']}"


def _pairs_colliding(collisions: Iterable[Collision]) -> set[tuple[int, int]]:
  return {c.objects for c in collisions}


def _seen(log: EventLog) -> list[int]:
  """Objects in view at some observed frame: those questions may name.

  Objects entering after the video (never seen) cannot be asked about.
  """
  late = {i for i, f in log.entering if f >= log.observed_frames}
  first_entry = {}
  for i, f in log.entering:
    first_entry.setdefault(i, f)
  return [i for i in range(log.num_objects)
          if i not in late or first_entry[i] < log.observed_frames]


def entered_objects(log: EventLog) -> list[int]:
  """Objects that come into view during the video from outside it, each
  once: an object's first entering counts, unless it was in view before
  (it left and came back) or it enters after the video."""
  first_exit = {}
  for i, f in log.exiting:
    first_exit.setdefault(i, f)
  first_entry = {}
  for i, f in log.entering:
    first_entry.setdefault(i, f)
  return sorted((i for i, f in first_entry.items()
                 if f < log.observed_frames
                 and first_exit.get(i, log.num_frames) > f),
                key=lambda i: (first_entry[i], i))


def moving_in_view_at_end(log: EventLog) -> list[int]:
  """Objects in view and moving at the last observed frame."""
  return [i for i in _seen(log)
          if log.in_view_at_end[i] and log.moving_at_end[i]]


def _balanced_choices(rng: np.random.Generator,
                      kinds: Sequence[tuple[Sequence[str], Sequence[str]]]
                      ) -> list[dict[str, Any]] | None:
  """Choices with as many correct as wrong ones within every choice kind.

  Args:
    kinds: per choice kind, its (correct, wrong) candidate texts.

  A kind with only one label offered is left out (its wording would tell the
  label); from each other kind the same number m of correct and wrong
  choices is drawn, m in 1..2 (1 when two kinds share the MAX_CHOICES
  choices; when more kinds qualify than MAX_CHOICES / 2, a random
  MAX_CHOICES / 2 of them). Returns the shuffled choices, or None if no kind
  has both labels.
  """
  usable = [(c, w) for c, w in kinds if c and w]
  if not usable:
    return None
  if 2 * len(usable) > MAX_CHOICES:
    keep = sorted(rng.choice(len(usable), MAX_CHOICES // 2, replace=False))
    usable = [usable[int(i)] for i in keep]
  per_kind = MAX_CHOICES // (2 * len(usable))
  picked = []
  for correct, wrong in usable:
    m = int(rng.integers(1, min(per_kind, len(correct), len(wrong)) + 1))
    for pool, label in ((correct, 'correct'), (wrong, 'wrong')):
      for idx in rng.choice(len(pool), m, replace=False):
        picked.append((pool[int(idx)], label))
  order = rng.permutation(len(picked))
  return [{'choice_id': c, 'choice': picked[int(k)][0],
           'answer': picked[int(k)][1]} for c, k in enumerate(order)]


def _prevents(log: EventLog, x: int, pair: tuple[int, int]) -> bool:
  """Whether ``pair`` does not collide during the video without ``x``."""
  return not any(c.objects == pair for c in log.counterfactual[x]
                 if c.frame < log.observed_frames)


def responsible_choices(log: EventLog, k: int
                        ) -> dict[str, tuple[list[str], list[str]]]:
  """Per choice kind, the (correct, wrong) choices of "which is responsible
  for the collision ``log.observed_collisions()[k]``".

  Kinds: 'presence'; 'collision_event', an earlier collision that involves
  one of the target's objects; 'other_collision_event', one that does not.
  The two collision kinds are balanced apart because the words tell them
  apart (a collision naming an object of the question is far more often
  responsible).

  The presence of X (seen before the target, not one of its objects) is
  responsible iff the target pair does not collide during the video in the
  world without X. An earlier collision between C and D (not the target
  pair) is responsible iff removing each of C, D that is not in the target
  prevents it the same way: removing an object removes its collisions, and
  asking it of every such object ties the label to this collision rather
  than to one object's other effects.
  """
  observed = log.observed_collisions()
  target = observed[k]
  presence: tuple[list[str], list[str]] = ([], [])
  for x in _seen(log):
    if x in target.objects or x not in log.counterfactual:
      continue
    if any(e == x and f > target.frame for e, f in log.entering):
      continue  # not there yet when the collision happened
    text = CHOICE_TEMPLATES['presence'].format(obj=name(log, x))
    presence[0 if _prevents(log, x, target.objects) else 1].append(text)
  events: dict[bool, tuple[list[str], list[str]]] = {True: ([], []),
                                                     False: ([], [])}
  for c in observed:
    if c.frame >= target.frame or c.objects == target.objects:
      continue
    others = [x for x in c.objects if x not in target.objects]
    if not all(x in log.counterfactual for x in others):
      continue
    text = CHOICE_TEMPLATES['collision_event'].format(
        a=name(log, c.objects[0]), b=name(log, c.objects[1]))
    kind = events[len(others) == 1]  # shares an object with the target
    if text in kind[0] or text in kind[1]:
      continue  # the same pair collided twice before the target
    kind[0 if all(_prevents(log, x, target.objects) for x in others)
         else 1].append(text)
  return {'presence': presence, 'collision_event': events[True],
          'other_collision_event': events[False]}


def predictive_choices(log: EventLog, verdict: int | None = None
                       ) -> tuple[list[str], list[str]]:
  """(correct, wrong) choices of "what will happen next": pairs of objects in
  view at the end of the video, correct iff they collide after it.

  With ``verdict`` (a log of the 'deflected' design only), only the pairs
  on which extrapolating the observed end gives that verdict
  (``log.extrapolated``; clevrer_like.extrapolation_verdict).
  """
  future = _pairs_colliding(log.future_collisions())
  at_end = [i for i in _seen(log) if log.in_view_at_end[i]]
  verdicts = {(a, b): v for a, b, v in log.extrapolated or []}
  correct, wrong = [], []
  for a, b in itertools.combinations(at_end, 2):
    if verdict is not None and verdicts.get((a, b)) != verdict:
      continue
    text = CHOICE_TEMPLATES['collides'].format(a=name(log, a), b=name(log, b))
    (correct if (a, b) in future else wrong).append(text)
  return correct, wrong


def predictive_kinds(log: EventLog) -> list[tuple[list[str], list[str]]]:
  """The (correct, wrong) pools of the predictive choices, one per choice
  kind: all pairs in one kind, or, for a log that carries the
  extrapolation's verdicts ('deflected' design), one kind per verdict, so
  that within each the extrapolation says the same of either label (a
  rule on the verdict is right on half the options)."""
  if log.extrapolated is None:
    return [predictive_choices(log)]
  return [predictive_choices(log, v) for v in range(NUM_VERDICTS)]


def counterfactual_choices(log: EventLog, x: int
                           ) -> tuple[list[str], list[str]]:
  """(correct, wrong) choices of "what will happen if x is removed".

  Correct: pairs colliding during the video in the world without ``x``.
  Wrong: pairs that collided in the video but not without ``x`` when there
  are any (so that "nothing changes" is not a winning guess), else pairs
  that collide in neither world.
  """
  seen = [i for i in _seen(log) if i != x]
  happened = _pairs_colliding(
      c for c in log.counterfactual[x] if c.frame < log.observed_frames)
  factual = _pairs_colliding(log.observed_collisions())
  correct, hard_wrong, wrong = [], [], []
  for a, b in itertools.combinations(seen, 2):
    text = CHOICE_TEMPLATES['collides'].format(a=name(log, a), b=name(log, b))
    if (a, b) in happened:
      correct.append(text)
    elif (a, b) in factual:
      hard_wrong.append(text)
    else:
      wrong.append(text)
  return correct, hard_wrong or wrong


def candidate_questions(log: EventLog, rng: np.random.Generator
                        ) -> list[dict[str, Any]]:
  """Every question the templates can ask about one video (unbalanced).

  Each has ``template``, ``question_type``, ``question`` and either
  ``answer`` (descriptive) or ``choices`` (the rest).
  """
  out: list[dict[str, Any]] = []
  seen = _seen(log)
  observed = log.observed_collisions()

  def ask(template: str, answer: Any = None, choices=None, **names: str):
    q_type, text = TEMPLATES[template]
    q = {'template': template, 'question_type': q_type,
         'question': text.format(**names)}
    if q_type == 'descriptive':
      q['answer'] = str(answer)
    else:
      if choices is None:
        return
      q['choices'] = choices
    out.append(q)

  # ---- descriptive ---------------------------------------------------------
  if len(observed) <= MAX_COUNT:
    ask('count_collisions', len(observed))
  # Objects, not entering events: one that leaves and comes back is not
  # counted, nor twice.
  entered = entered_objects(log)
  if len(entered) <= MAX_COUNT:
    ask('count_entering', len(entered))
  present_at_end = [i for i in seen if log.in_view_at_end[i]]
  # Only what the last frame shows: an object moving outside the view is not
  # "in the video" any more.
  ask('count_moving_end', len(moving_in_view_at_end(log)))
  if present_at_end:
    i = present_at_end[int(rng.integers(len(present_at_end)))]
    ask('is_moving_end', 'yes' if log.moving_at_end[i] else 'no',
        obj=name(log, i))
  partners: dict[int, set[int]] = collections.defaultdict(set)
  for c in observed:
    a, b = c.objects
    partners[a].add(b)
    partners[b].add(a)
  single = sorted(i for i, p in partners.items() if len(p) == 1)
  if single:
    i = single[int(rng.integers(len(single)))]
    (other,) = partners[i]
    ask('color_collides_with', log.objects[other]['color'], obj=name(log, i))
    j = single[int(rng.integers(len(single)))]
    (other,) = partners[j]
    ask('shape_collides_with', log.objects[other]['shape'], obj=name(log, j))
  if len(entered) == 1:
    ask('color_entering', log.objects[entered[0]]['color'])

  # ---- explanatory ---------------------------------------------------------
  # Targets: first collisions of a pair with both labels in some choice kind.
  targets = [k for k, c in enumerate(observed)
             if all(d.objects != c.objects for d in observed[:k])
             and any(right and wrong
                     for right, wrong in responsible_choices(log, k).values())]
  picked = rng.choice(len(targets), min(MAX_EXPLANATORY, len(targets)),
                      replace=False) if targets else []
  for k in sorted(targets[int(i)] for i in picked):
    target = observed[k].objects
    ask('responsible', choices=_balanced_choices(
        rng, list(responsible_choices(log, k).values())),
        a=name(log, target[0]), b=name(log, target[1]))

  # ---- predictive ----------------------------------------------------------
  # Up to MAX_PREDICTIVE questions, the pools dealt out so that no choice is
  # asked twice about one video.
  kinds = predictive_kinds(log)
  if len(kinds) == 1:  # the 'direct' design, as in VERSION 2
    correct, wrong = kinds[0]
    num = min(MAX_PREDICTIVE, len(correct), len(wrong))
    correct = [correct[int(i)] for i in rng.permutation(len(correct))]
    wrong = [wrong[int(i)] for i in rng.permutation(len(wrong))]
    for part in range(num):
      ask('next', choices=_balanced_choices(
          rng, [(correct[part::num], wrong[part::num])]))
  else:
    shuffled = [([c[int(i)] for i in rng.permutation(len(c))],
                 [w[int(i)] for i in rng.permutation(len(w))])
                for c, w in kinds]
    num = min(MAX_PREDICTIVE, max(min(len(c), len(w)) for c, w in kinds))
    for part in range(num):
      ask('next', choices=_balanced_choices(
          rng, [(c[part::num], w[part::num]) for c, w in shuffled]))

  # ---- counterfactual ------------------------------------------------------
  removable = [x for x in seen if x in log.counterfactual]
  if removable:
    x = removable[int(rng.integers(len(removable)))]
    ask('removed', choices=_balanced_choices(
        rng, [counterfactual_choices(log, x)]), obj=name(log, x))
  return out


def lower_median(counts: Sequence[int]) -> int:
  """The median of ``counts``; of the two middle values, the smaller."""
  return int(sorted(counts)[(len(counts) - 1) // 2])


def balance(questions: list[dict[str, Any]], rng: np.random.Generator
            ) -> list[dict[str, Any]]:
  """Keeps each open answer at most (lower-)median-count times per template.

  The lower median makes a two-answer template (yes / no, 0 / 1) exactly
  balanced.

  Multiple-choice questions are kept as they are (each already mixes correct
  and wrong choices). Returns the kept questions in their original order.
  """
  groups: dict[tuple[str, str], list[int]] = collections.defaultdict(list)
  for k, q in enumerate(questions):
    if q['question_type'] == 'descriptive':
      groups[(q['template'], q['answer'])].append(k)
  per_template: dict[str, list[int]] = collections.defaultdict(list)
  for (template, _), members in groups.items():
    per_template[template].append(len(members))
  drop: set[int] = set()
  for (template, _), members in sorted(groups.items()):
    cap = lower_median(per_template[template])
    if len(members) > cap:
      keep = set(rng.choice(members, cap, replace=False).tolist())
      drop.update(m for m in members if m not in keep)
  return [q for k, q in enumerate(questions) if k not in drop]


def generate_split(logs: Sequence[EventLog], seed: int, split: str,
                   video_filenames: Sequence[str] | None = None,
                   scene_offset: int = 0) -> list[dict[str, Any]]:
  """Questions of one split in CLEVRER's ``questions/<split>.json`` layout.

  Args:
    logs: event logs of the split's videos, in video order.
    seed: generation seed (with ``split``, it fixes every choice made here).
    video_filenames: per video (default ``video_<index>.mp4``).
    scene_offset: added to the video index to make ``scene_index``.

  Returns:
    One entry per video: {'scene_index', 'video_filename', 'questions': [
    {'question_id', 'question_type', 'question', 'template', 'answer' |
    'choices': [{'choice_id', 'choice', 'answer'}]}]}.
  """
  split_id = ('train', 'val', 'test').index(split)
  flat, owner = [], []
  for v, log in enumerate(logs):
    rng = np.random.default_rng([seed, split_id, v, 1212])
    for q in candidate_questions(log, rng):
      flat.append(q)
      owner.append(v)
  kept_ids = {id(q) for q in balance(flat, np.random.default_rng(
      [seed, split_id, 9999]))}
  scenes = []
  for v in range(len(logs)):
    filename = (video_filenames[v] if video_filenames is not None
                else f'video_{v + scene_offset:05d}.mp4')
    scenes.append({'scene_index': v + scene_offset,
                   'video_filename': filename, 'questions': []})
  for q, v in zip(flat, owner):
    if id(q) in kept_ids:
      questions = scenes[v]['questions']
      questions.append({'question_id': len(questions), **q})
  return scenes


def template_words() -> list[str]:
  """Every word the templates can produce (the embedded question vocabulary)."""
  words = set()
  texts = [t for _, t in TEMPLATES.values()] + list(CHOICE_TEMPLATES.values())
  for text in texts:
    words.update(w for w in text.split() if not w.startswith('{'))
  words.update(COLORS)
  words.update(SHAPES)
  return sorted(words)


def template_answers() -> list[str]:
  """Every open answer the descriptive templates can give."""
  return sorted([str(k) for k in range(MAX_COUNT + 1)] + list(COLORS)
                + list(SHAPES) + ['no', 'yes'])


def max_lengths() -> tuple[int, int]:
  """(words of the longest question, of the longest choice) any template can
  produce (every object name is two words)."""
  def words(text: str) -> int:
    return len(text.split()) + text.count('{')  # "{obj}" -> 2 words
  return (max(words(t) for _, t in TEMPLATES.values()),
          max(words(t) for t in CHOICE_TEMPLATES.values()))
