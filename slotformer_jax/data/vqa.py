"""CLEVRER question files: vocabulary, tokens, and the encoded questions.

Reads CLEVRER's ``questions/{train,validation,test}.json`` layout (a list of
scenes ``{'scene_index', 'video_filename', 'questions': [...]}``; a question
has ``question_id``, ``question_type`` (descriptive, explanatory, predictive,
counterfactual), ``question`` and either ``answer`` or ``choices``
``[{'choice_id', 'choice', 'answer': 'correct' | 'wrong'}]``; the test split
has no answers). The embedded generator
(:mod:`slotformer_jax.datasets.clevrer_like_questions`) writes the same layout.

Text is tokenised like the official Aloe re-implementation: lower case, '?'
dropped, split on single spaces (so "cube," is its own word). A vocabulary
maps words to ids with PAD = 0 and the other words in sorted order; built from
CLEVRER's training questions this gives the official question ids, and
:data:`CLEVRER_ANSWERS` the official answer ids.

Encoded layout (what Aloe reads; L_q / L_c = max question / choice length):
  descriptive: tokens [L_q + L_c] (question, then padding);
  multiple choice: per choice, tokens [L_q + L_c] = question padded to L_q,
  then the choice padded to L_c. Pad masks are True at padding.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slotformer_jax.data import json_array
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import shown
from slotformer_jax.files import UntrustedFileError
from slotformer_jax.files import read_untrusted_json
from slotformer_jax.files import read_untrusted_text

PAD = 'PAD'
QUESTION_TYPES: tuple[str, ...] = (
    'descriptive', 'explanatory', 'predictive', 'counterfactual')
DESCRIPTIVE = 0
# CLEVRER's split files are named train / validation / test.
CLEVRER_SPLIT_FILES = {'train': 'train.json', 'val': 'validation.json',
                       'test': 'test.json'}
# CLEVRER's open answers: counts, colours, shapes, materials, yes/no.
CLEVRER_ANSWERS: tuple[str, ...] = (
    '0', '1', '2', '3', '4', '5', 'blue', 'brown', 'cube', 'cyan',
    'cylinder', 'gray', 'green', 'metal', 'no', 'purple', 'red', 'rubber',
    'sphere', 'yellow', 'yes')
# Limits of a question file from elsewhere (CLEVRER's train.json is about
# 40 MB; its scenes nest 4 levels deep, one scene's questions take a few
# kB), of one scene in it, and of one text. Memory at the limits:
# docs/reliability.md (the reader limits table).
MAX_QUESTION_FILE_BYTES = 256 << 20
MAX_SCENE_CHARS = 4 << 20
MAX_QUESTION_FILE_DEPTH = 8
MAX_TEXT_CHARS = 2000
MAX_VOCABULARY = 1_000_000


class QuestionFileError(ConfigError):
  """A question or vocabulary file that is not what CLEVRER's are: the
  message names the file, the scene and question, and what is wrong."""


def tokenize(text: str) -> list[str]:
  return [w for w in text.lower().replace('?', '').split(' ') if w]


def make_vocabulary(words: Iterable[str]) -> dict[str, int]:
  """PAD -> 0, then the distinct words in sorted order -> 1, 2, ..."""
  vocab = {PAD: 0}
  for k, word in enumerate(sorted(set(words) - {PAD}), start=1):
    vocab[word] = k
  return vocab


@dataclasses.dataclass(frozen=True)
class Vocabulary:
  """Question words and open answers, both with PAD = 0."""

  questions: dict[str, int]
  answers: dict[str, int]

  @classmethod
  def from_scenes(cls, scenes: Sequence[Mapping[str, Any]],
                  answers: Iterable[str] | None = None) -> Vocabulary:
    """Words of every question and choice; answers from the descriptive
    questions unless given (e.g. :data:`CLEVRER_ANSWERS`)."""
    words, seen_answers = set(), set()
    for scene in scenes:
      for q in scene['questions']:
        words.update(tokenize(q['question']))
        for choice in q.get('choices', ()):
          words.update(tokenize(choice['choice']))
        if q['question_type'] == 'descriptive' and 'answer' in q:
          seen_answers.add(q['answer'])
    return cls(make_vocabulary(words),
               make_vocabulary(seen_answers if answers is None else answers))

  def to_json(self) -> str:
    """What :meth:`load` reads back (the generator writes it)."""
    return json.dumps({'q_vocab': self.questions, 'a_vocab': self.answers},
                      indent=1, sort_keys=True)

  @classmethod
  def load(cls, path: str | os.PathLike[str]) -> Vocabulary:
    """A vocabulary file: ``{'q_vocab': {word: id}, 'a_vocab': {answer:
    id}}``, as :meth:`save` writes it and as the official Aloe's
    ``CLEVRER_vocab.json`` is (82 question words, 22 answers, PAD = 0 in
    both).

    Raises:
      ConfigError: the file is not such a vocabulary (one line naming it).
    """
    try:
      d = read_untrusted_json(path, what='vocabulary file',
                              max_bytes=64 << 20, max_depth=2)
    except OSError as error:
      raise QuestionFileError(f'vocabulary file {path}: '
                              f'{error.strerror or error}') from None
    except UntrustedFileError as error:
      raise QuestionFileError(str(error)) from None
    tables = []
    for key in ('q_vocab', 'a_vocab'):
      table = d.get(key) if isinstance(d, dict) else None
      if not isinstance(table, dict) or len(table) > MAX_VOCABULARY:
        raise QuestionFileError(
            f'vocabulary file {path} has no {key!r} mapping '
            "(expected {'q_vocab': {word: id}, 'a_vocab': {answer: id}})")
      wrong = [(k, v) for k, v in table.items() if not _is_id(v)]
      if wrong:
        k, v = wrong[0]
        raise QuestionFileError(
            f'vocabulary file {path}: {key} ids must be integers; '
            f"'{shown(k, 60)}' has {shown(repr(v), 60)}")
      table = {k: int(v) for k, v in table.items()}
      # Ids index the embedding / answer logits: PAD = 0, then 1..n-1.
      if table.get(PAD) != 0 or sorted(table.values()) != list(
          range(len(table))):
        raise QuestionFileError(f'vocabulary file {path}: {key} must map {PAD!r} '
                          'to 0 and its words to distinct ids 0..n-1')
      tables.append(table)
    return cls(*tables)

  @property
  def answer_names(self) -> list[str]:
    """Answer id -> answer text."""
    names = [''] * len(self.answers)
    for word, k in self.answers.items():
      names[k] = word
    return names


def _is_id(value: Any) -> bool:
  """An int (not a bool), or its digits as a string."""
  if isinstance(value, str):
    return value.isascii() and value.isdigit() and len(value) <= 9
  return isinstance(value, int) and not isinstance(value, bool)


def encode_text(text: str, vocab: Mapping[str, int], length: int
                ) -> tuple[np.ndarray, np.ndarray]:
  """Text -> (tokens int32 [length], pad_mask bool [length], True = pad).

  Raises:
    QuestionFileError: more words than `length`, or a word outside `vocab`
      (the caller adds where the text is).
  """
  words = tokenize(text)
  if len(words) > length:
    raise QuestionFileError(f'{len(words)} words do not fit in {length}: '
                            f"'{shown(text, 120)}'")
  unknown = [w for w in words if w not in vocab]
  if unknown:
    raise QuestionFileError(
        f"the word '{shown(unknown[0], 40)}' of '{shown(text, 120)}' is not "
        'in the vocabulary' + (f' (nor {len(unknown) - 1} more)'
                               if len(unknown) > 1 else ''))
  tokens = np.full((length,), vocab[PAD], np.int32)
  tokens[:len(words)] = [vocab[w] for w in words]
  pad_mask = np.ones((length,), bool)
  pad_mask[:len(words)] = False
  return tokens, pad_mask


def decode_tokens(tokens: np.ndarray, pad_mask: np.ndarray,
                  vocab: Mapping[str, int]) -> str:
  """The inverse of :func:`encode_text` (up to case and '?')."""
  words = {k: w for w, k in vocab.items()}
  return ' '.join(words[int(t)] for t, pad in zip(tokens, pad_mask)
                  if not pad)


@dataclasses.dataclass
class EncodedQuestion:
  """One question, encoded (C = its number of choices, 0 if descriptive).

  Attributes:
    scene_index, video_filename, question_id: as in the file.
    question_type: index into QUESTION_TYPES.
    template: the embedded generator's template ('' for CLEVRER's files).
    tokens: int32 [C or 1, L_q + L_c]; pad_mask: bool, same shape.
    answer: descriptive answer id (-1 when unknown, e.g. the test split).
    choice_ids: int32 [C]; choice_labels: int32 [C], 1 correct, 0 wrong, -1
      unknown.
  """

  scene_index: int
  video_filename: str
  question_id: int
  question_type: int
  template: str
  tokens: np.ndarray
  pad_mask: np.ndarray
  answer: int = -1
  choice_ids: np.ndarray = dataclasses.field(
      default_factory=lambda: np.zeros((0,), np.int32))
  choice_labels: np.ndarray = dataclasses.field(
      default_factory=lambda: np.zeros((0,), np.int32))

  @property
  def is_descriptive(self) -> bool:
    return self.question_type == DESCRIPTIVE


def encode_question(scene: Mapping[str, Any], q: Mapping[str, Any],
                    vocab: Vocabulary, max_question_len: int,
                    max_choice_len: int) -> EncodedQuestion:
  """One question of a scene that `check_scenes` accepted.

  Raises:
    QuestionFileError: a text longer than its length, a word or an answer
      outside the vocabulary.
  """
  q_type = QUESTION_TYPES.index(q['question_type'])
  common = dict(scene_index=int(scene['scene_index']),
                video_filename=scene['video_filename'],
                question_id=int(q['question_id']), question_type=q_type,
                template=q.get('template', ''))
  if q_type == DESCRIPTIVE:
    tokens, pad = encode_text(q['question'], vocab.questions,
                              max_question_len + max_choice_len)
    answer = -1
    if 'answer' in q:
      if q['answer'] not in vocab.answers:
        raise QuestionFileError(f"the answer '{shown(q['answer'], 60)}' is "
                                'not in the vocabulary')
      answer = vocab.answers[q['answer']]
    return EncodedQuestion(tokens=tokens[None], pad_mask=pad[None],
                           answer=answer, **common)
  q_tokens, q_pad = encode_text(q['question'], vocab.questions,
                                max_question_len)
  tokens, pads, ids, labels = [], [], [], []
  for choice in q['choices']:
    c_tokens, c_pad = encode_text(choice['choice'], vocab.questions,
                                  max_choice_len)
    tokens.append(np.concatenate([q_tokens, c_tokens]))
    pads.append(np.concatenate([q_pad, c_pad]))
    ids.append(int(choice['choice_id']))
    labels.append(_CHOICE_LABELS[choice['answer']]
                  if 'answer' in choice else -1)
  return EncodedQuestion(
      tokens=np.stack(tokens), pad_mask=np.stack(pads),
      choice_ids=np.array(ids, np.int32),
      choice_labels=np.array(labels, np.int32), **common)


_CHOICE_LABELS = {'correct': 1, 'wrong': 0}


def encode_scenes(scenes: Sequence[Mapping[str, Any]], vocab: Vocabulary,
                  max_question_len: int, max_choice_len: int, *,
                  path: str | os.PathLike[str] = 'the questions'
                  ) -> list[EncodedQuestion]:
  """Every question of every scene, in file order.

  Raises:
    QuestionFileError: naming `path`, the scene and the question.
  """
  out = []
  for i, scene in enumerate(scenes):
    for j, q in enumerate(scene['questions']):
      try:
        out.append(encode_question(scene, q, vocab, max_question_len,
                                   max_choice_len))
      except QuestionFileError as error:
        raise QuestionFileError(f'{path}: scene {i} question {j}: {error}'
                                ) from None
  return out


def _problem(value: Any, kind: str) -> str | None:
  """Why `value` is not of `kind` ('int', 'text', 'list', 'object'), or
  None."""
  if kind == 'int':  # ids and indices are stored as int32
    ok = isinstance(value, int) and not isinstance(value, bool) and (
        -2**31 <= value < 2**31)
  elif kind == 'text':
    ok = isinstance(value, str) and len(value) <= MAX_TEXT_CHARS
  elif kind == 'list':
    ok = isinstance(value, list)
  else:
    ok = isinstance(value, dict)
  if ok:
    return None
  if kind == 'text' and isinstance(value, str):
    return f'is a text of {len(value)} characters, more than {MAX_TEXT_CHARS}'
  if kind == 'int' and isinstance(value, int) and not isinstance(value, bool):
    return f'is {shown(repr(value), 40)}, outside the 32-bit ints'
  what = (f'a {type(value).__name__}' if isinstance(value, (dict, list))
          else f'{shown(repr(value), 40)} ({type(value).__name__})')
  return f'is {what}, not {"an" if kind in ("int", "object") else "a"} {kind}'



def _check_fields(entry: Any, fields: Mapping[str, str],
                  optional: Mapping[str, str], where: str) -> None:
  if not isinstance(entry, dict):
    raise QuestionFileError(f'{where} {_problem(entry, "object")}')
  for key, kind in {**fields, **optional}.items():
    if key not in entry:
      if key in fields:
        raise QuestionFileError(f'{where} has no {key!r}')
      continue
    problem = _problem(entry[key], kind)
    if problem:
      raise QuestionFileError(f'{where}: {key!r} {problem}')


def check_scenes(scenes: Any, path: str | os.PathLike[str]
                 ) -> list[dict[str, Any]]:
  """`scenes` (a question file as read) if it has CLEVRER's layout
  (`checked_scene`), each scene with only the fields this module reads.

  Raises:
    QuestionFileError: the first problem, naming the file, the scene and
      the question.
  """
  if not isinstance(scenes, list):
    raise QuestionFileError(f'{path} {_problem(scenes, "list")} of scenes')
  return [checked_scene(scene, i, path) for i, scene in enumerate(scenes)]


# The fields this module reads; the others (CLEVRER's `program`,
# `question_subtype`) are not kept: they would cost memory for nothing.
_SCENE_FIELDS = ('scene_index', 'video_filename', 'questions')
_QUESTION_FIELDS = ('question_id', 'question_type', 'question', 'template',
                    'answer', 'choices')
_CHOICE_FIELDS = ('choice_id', 'choice', 'answer')


def checked_scene(scene: Any, i: int, path: str | os.PathLike[str]
                  ) -> dict[str, Any]:
  """Scene `i` of a question file if it has CLEVRER's layout: every field
  present and of its type, question types and choice answers from their
  sets; a copy with only the fields this module reads (its repeated words
  shared). The rest of this module relies on it.

  Raises:
    QuestionFileError: the first problem, naming the file, the scene and
      the question.
  """
  where = f'{path}: scene {i}'
  _check_fields(scene, {'scene_index': 'int', 'video_filename': 'text',
                        'questions': 'list'}, {}, where)
  for j, q in enumerate(scene['questions']):
    question = f'{where} question {j}'
    _check_fields(q, {'question_id': 'int', 'question_type': 'text',
                      'question': 'text'}, {'template': 'text'}, question)
    if q['question_type'] not in QUESTION_TYPES:
      raise QuestionFileError(
          f"{question}: the question type '{shown(q['question_type'], 40)}'"
          f' is not one of {", ".join(QUESTION_TYPES)}')
    if q['question_type'] == 'descriptive':
      _check_fields(q, {}, {'answer': 'text'}, question)
      continue
    _check_fields(q, {'choices': 'list'}, {}, question)
    if not q['choices']:
      raise QuestionFileError(f'{question} has no choices')
    for k, choice in enumerate(q['choices']):
      where_choice = f'{question} choice {k}'
      _check_fields(choice, {'choice_id': 'int', 'choice': 'text'},
                    {'answer': 'text'}, where_choice)
      if choice.get('answer', 'correct') not in _CHOICE_LABELS:
        raise QuestionFileError(
            f"{where_choice}: the answer '{shown(choice['answer'], 40)}' "
            "is not 'correct' or 'wrong'")
  return {**_kept(scene, _SCENE_FIELDS), 'questions': [
      _kept(q, _QUESTION_FIELDS) for q in scene['questions']]}


def _kept(entry: dict[str, Any], fields: Sequence[str]) -> dict[str, Any]:
  """`entry` with only `fields` (those it has); words shared (interned),
  choices kept the same way."""
  kept = {}
  for key in fields:
    if key not in entry:
      continue
    value = entry[key]
    if key in ('question_type', 'answer', 'template'):
      value = sys.intern(value)
    elif key == 'choices':
      value = [_kept(c, _CHOICE_FIELDS) for c in value]
    elif key == 'questions':
      continue  # the caller's
    kept[key] = value
  return kept


def read_clevrer_questions(data_root: str | os.PathLike[str], split: str
                           ) -> list[dict[str, Any]]:
  """``<data_root>/questions/<train|validation|test>.json`` of CLEVRER,
  read with limits (size, depth) and checked (`check_scenes`).

  Raises:
    MissingInputError: no such file.
    QuestionFileError: a file that is not CLEVRER's layout (one line).
  """
  path = Path(data_root) / 'questions' / CLEVRER_SPLIT_FILES[split]
  if not path.is_file():
    raise MissingInputError(
        f'{path} not found: CLEVRER keeps its questions in '
        '<data_root>/questions/{train,validation,test}.json (set '
        'vqa.questions_root to the folder holding questions/)')
  # Scene by scene (`json_array`): each is checked and kept small before
  # the next is parsed, so memory stays near the file's size.
  try:
    text = read_untrusted_text(path, what='question file',
                                max_bytes=MAX_QUESTION_FILE_BYTES)
    return [checked_scene(scene, i, path) for i, scene in enumerate(
        json_array.elements(text, where=f'question file {path}',
                            items='scenes',
                            max_element_chars=MAX_SCENE_CHARS,
                            max_depth=MAX_QUESTION_FILE_DEPTH - 1))]
  except UntrustedFileError as error:
    raise QuestionFileError(f'{error}. Restore it from the CLEVRER '
                            'download.') from None
