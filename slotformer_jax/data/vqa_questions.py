"""Where a VQA config's questions and vocabulary come from.

The embedded family ('clevrer_like') keeps them in its dataset folder
(written by the data stage, `--mode=prepare_data`; reading here only opens
it); for CLEVRER set `vqa.questions_root` (the folder with questions/) and
optionally `vqa.vocab_file` (e.g. the official CLEVRER_vocab.json; default:
built from the training questions and CLEVRER's answers).
"""

from __future__ import annotations

import os

import ml_collections

from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.data.data_dir import resolve_data_dir
from slotformer_jax.data.embedded import clevrer_like
from slotformer_jax.errors import ConfigError


def questions_root(config: ml_collections.ConfigDict) -> str:
  """The folder holding questions/ (and maybe vocab.json).

  Raises:
    MissingInputError: the embedded dataset is not generated (names the
      command).
    ConfigError: CLEVRER without `vqa.questions_root`.
  """
  if config.data.name == 'clevrer_like':
    return str(clevrer_like.complete_dataset_dir(
        config.data, resolve_data_dir(config.data.data_dir)))
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


def filename_to_index(config: ml_collections.ConfigDict,
                       split: str) -> dict[str, int]:
  scenes = vqa_data.read_clevrer_questions(questions_root(config), split)
  if config.data.name == 'clevrer_like':
    offset = clevrer_like.SCENE_OFFSETS[split]
    return {s['video_filename']: int(s['scene_index']) - offset
            for s in scenes}
  # CLEVRER: converted videos are in file-name order within a split.
  names = sorted(s['video_filename'] for s in scenes)
  return {name: k for k, name in enumerate(names)}
