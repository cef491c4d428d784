"""CLEVRER question files: vocabulary, tokens, and the encoded questions.

Reads CLEVRER's ``questions/{train,validation,test}.json`` layout (a list of
scenes ``{'scene_index', 'video_filename', 'questions': [...]}``; a question
has ``question_id``, ``question_type`` (descriptive, explanatory, predictive,
counterfactual), ``question`` and either ``answer`` or ``choices``
``[{'choice_id', 'choice', 'answer': 'correct' | 'wrong'}]``; the test split
has no answers). The embedded generator
(:mod:`slotformer_jax.data.convert.questions`) writes the same layout.

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
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.files import read_json

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

  def save(self, path: str | os.PathLike[str]) -> None:
    with open(path, 'w') as f:
      json.dump({'q_vocab': self.questions, 'a_vocab': self.answers}, f,
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
      with open(path) as f:
        d = json.load(f)
    except (OSError, json.JSONDecodeError) as error:
      raise ConfigError(f'vocabulary file {path}: {error}') from error
    tables = []
    for key in ('q_vocab', 'a_vocab'):
      table = d.get(key) if isinstance(d, dict) else None
      if not isinstance(table, dict):
        raise ConfigError(f'vocabulary file {path} has no {key!r} mapping '
                          "(expected {'q_vocab': {word: id}, 'a_vocab': "
                          '{answer: id}})')
      try:
        table = {str(k): int(v) for k, v in table.items()}
      except (TypeError, ValueError) as error:
        raise ConfigError(f'vocabulary file {path}: {key} ids must be '
                          f'integers ({error})') from error
      # Ids index the embedding / answer logits: PAD = 0, then 1..n-1.
      if table.get(PAD) != 0 or sorted(table.values()) != list(
          range(len(table))):
        raise ConfigError(f'vocabulary file {path}: {key} must map {PAD!r} '
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


def encode_text(text: str, vocab: Mapping[str, int], length: int
                ) -> tuple[np.ndarray, np.ndarray]:
  """Text -> (tokens int32 [length], pad_mask bool [length], True = pad)."""
  words = tokenize(text)
  if len(words) > length:
    raise ValueError(f'{len(words)} words do not fit in {length}: {text!r}')
  unknown = [w for w in words if w not in vocab]
  if unknown:
    raise KeyError(f'words {unknown} of {text!r} are not in the vocabulary')
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
  q_type = QUESTION_TYPES.index(q['question_type'])
  common = dict(scene_index=int(scene['scene_index']),
                video_filename=scene['video_filename'],
                question_id=int(q['question_id']), question_type=q_type,
                template=q.get('template', ''))
  if q_type == DESCRIPTIVE:
    tokens, pad = encode_text(q['question'], vocab.questions,
                              max_question_len + max_choice_len)
    answer = vocab.answers[q['answer']] if 'answer' in q else -1
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
    labels.append({'correct': 1, 'wrong': 0}[choice['answer']]
                  if 'answer' in choice else -1)
  return EncodedQuestion(
      tokens=np.stack(tokens), pad_mask=np.stack(pads),
      choice_ids=np.array(ids, np.int32),
      choice_labels=np.array(labels, np.int32), **common)


def encode_scenes(scenes: Sequence[Mapping[str, Any]], vocab: Vocabulary,
                  max_question_len: int, max_choice_len: int
                  ) -> list[EncodedQuestion]:
  """Every question of every scene, in file order."""
  return [encode_question(scene, q, vocab, max_question_len, max_choice_len)
          for scene in scenes for q in scene['questions']]


def read_clevrer_questions(data_root: str | os.PathLike[str], split: str
                           ) -> list[dict[str, Any]]:
  """``<data_root>/questions/<train|validation|test>.json`` of CLEVRER."""
  path = Path(data_root) / 'questions' / CLEVRER_SPLIT_FILES[split]
  if not path.is_file():
    raise MissingInputError(
        f'{path} not found: CLEVRER keeps its questions in '
        '<data_root>/questions/{train,validation,test}.json (set '
        'vqa.questions_root to the folder holding questions/)')
  return read_json(path, fix='Restore it from the CLEVRER download.')
