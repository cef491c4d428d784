"""Where a VQA config's questions and vocabulary come from.

A dataset that holds its questions says where (`Dataset.questions_root`:
the generated CLEVRER-like one keeps them in its folder, written by the data
stage, `--mode=prepare_data`; reading here only opens it); otherwise (CLEVRER)
set `vqa.questions_root` (the folder with questions/) and optionally
`vqa.vocab_file` (e.g. the official CLEVRER_vocab.json; default: built from
the training questions and CLEVRER's answers).

A question reads the slots of the video its `video_filename` names, found by
name among the converted split's videos (`join_videos`): a video skipped at
conversion leaves its questions out, and moves no other question.
"""

from __future__ import annotations

import dataclasses
import os

import ml_collections

from slotformer_jax import datasets
from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.data.video_names import name_key
from slotformer_jax.errors import ConfigError


def questions_root(config: ml_collections.ConfigDict) -> str:
  """The folder holding questions/ (and maybe vocab.json).

  Raises:
    MissingInputError: the generated dataset is not there (names the
      command).
    ConfigError: a dataset without questions of its own and no
      `vqa.questions_root`.
  """
  held = datasets.get(config.data.name).questions_root(config.data)
  if held is not None:
    return str(held)
  if not config.vqa.questions_root:
    raise ConfigError('set vqa.questions_root to the folder holding '
                     "CLEVRER's questions/{train,validation,test}.json")
  return config.vqa.questions_root


def vocabulary(config: ml_collections.ConfigDict) -> vqa_data.Vocabulary:
  """`vqa.vocab_file` when set (e.g. the official CLEVRER_vocab.json, which
  an official Aloe checkpoint's ids index), else the questions folder's
  vocab.json, else one built from the training questions."""
  if config.vqa.vocab_file:
    return vqa_data.Vocabulary.load(config.vqa.vocab_file)
  root = questions_root(config)
  path = os.path.join(root, 'vocab.json')
  if os.path.exists(path):
    return vqa_data.Vocabulary.load(path)
  return vqa_data.Vocabulary.from_scenes(
      vqa_data.read_clevrer_questions(root, 'train'),
      answers=vqa_data.CLEVRER_ANSWERS)


def encoded_questions(config: ml_collections.ConfigDict, split: str,
                      vocab: vqa_data.Vocabulary
                      ) -> list[vqa_data.EncodedQuestion]:
  root = questions_root(config)
  scenes = vqa_data.read_clevrer_questions(root, split)
  return vqa_data.encode_scenes(
      scenes, vocab, config.vqa.max_question_len, config.vqa.max_choice_len,
      path=os.path.join(root, 'questions',
                        vqa_data.CLEVRER_SPLIT_FILES[split]))


@dataclasses.dataclass(frozen=True)
class Joined:
  """The questions of a split joined to the rows of its videos by name.

  Attributes:
    questions: the questions whose video is in the split, in file order.
    rows: video name key (`video_names.name_key`) -> its row (the video's
      index in the converted split, i.e. its row of slots).
    total: questions in the file.
    missing_videos: name keys the file asks about that the split lacks
      (e.g. a video the converter skipped), sorted.
  """

  questions: list[vqa_data.EncodedQuestion]
  rows: dict[str, int]
  total: int
  missing_videos: tuple[str, ...]

  @property
  def num_missing(self) -> int:
    """Questions left out: their video is not in the split."""
    return self.total - len(self.questions)

  @property
  def missing_fraction(self) -> float:
    return self.num_missing / max(self.total, 1)

  def row(self, video_filename: str) -> int:
    """The row of a kept question's video."""
    return self.rows[name_key(video_filename)]

  def problem(self, split: str, limit: float, scoring: bool) -> str | None:
    """The one line that stops the VQA stage, or None: no question has its
    video; or, when `scoring`, more than `limit` (vqa.
    max_missing_video_fraction) of them have none."""
    if self.total and not self.questions:
      return (f'VQA {self.report(split)}: no question is left; convert the '
              f'{split} videos the questions are about')
    if scoring and self.missing_fraction > limit:
      return (f'VQA {self.report(split)}; that is more than vqa.'
              f'max_missing_video_fraction={limit}, so the score would not '
              f'be the split\'s. Convert the whole {split} split, or pass '
              '--config.vqa.max_missing_video_fraction=1 to score the '
              'questions that have a video')
    return None

  def report(self, split: str) -> str:
    """One line: what was left out and why."""
    examples = ', '.join(self.missing_videos[:3])
    videos = len(self.missing_videos)
    return (f'{split}: {self.num_missing} of {self.total} questions '
            f'({self.missing_fraction:.1%}) are about {videos} '
            f'video{"s" * (videos != 1)} not in the converted split (e.g. '
            f'{examples}: skipped at conversion, or not converted); they are '
            'left out')


def join_videos(questions: list[vqa_data.EncodedQuestion],
                names: list[str]) -> Joined:
  """Joins `questions` to the split whose video `names` (record order)
  are given: a question reads the row of the video it names, whatever was
  skipped before it; a question whose video is not there is left out."""
  rows = {name_key(name): row for row, name in enumerate(names)}
  kept = [q for q in questions if name_key(q.video_filename) in rows]
  missing = sorted({name_key(q.video_filename) for q in questions}
                   - set(rows))
  return Joined(questions=kept, rows=rows, total=len(questions),
                missing_videos=tuple(missing))


def split_video_names(data_config: ml_collections.ConfigDict, split: str
                      ) -> list[str]:
  """The name of every video of ``split`` of the dataset ``data_config``
  names, in record (= slot row) order (`data/video_names.py`).

  Raises:
    UserError: a converted folder records no names (names the command that
      converts it again).
    MissingInputError: the dataset is not there.
  """
  return datasets.get(data_config.name).video_names(data_config, split)


@dataclasses.dataclass(frozen=True)
class _Asked:
  """A question as `join_videos` sees it: the video it is about."""
  video_filename: str


def coverage(config: ml_collections.ConfigDict, split: str) -> Joined:
  """Which questions of the split's file have their video in the converted
  split, without encoding them (no vocabulary): what can be checked before
  any training once the data is there (`Joined.questions` then holds the
  video names of the kept questions, not encoded questions).

  Raises:
    MissingInputError / UserError: no question file, or no converted data.
  """
  scenes = vqa_data.read_clevrer_questions(questions_root(config), split)
  asked = [_Asked(scene['video_filename']) for scene in scenes
           for _ in scene['questions']]
  return join_videos(asked, split_video_names(config.data, split))


def joined_questions(config: ml_collections.ConfigDict, split: str,
                     vocab: vqa_data.Vocabulary) -> Joined:
  """The split's encoded questions joined to its videos by name."""
  return join_videos(encoded_questions(config, split, vocab),
                     split_video_names(config.data, split))
