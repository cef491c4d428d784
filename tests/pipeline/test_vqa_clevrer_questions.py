"""VQA on a converted CLEVRER source (issue 38).

The source is in its published layout; a video in the middle of each split
does not convert (train: no annotation; val: 10800, which the converter
always leaves out), and there are questions about every video:

* questions join the converted videos by name: each question reads its own
  video's slots, in training and in evaluation; the questions of the
  missing videos are left out, counted, and (evaluation) refused above
  `vqa.max_missing_video_fraction`;
* a question set of one kind (open-only, choice-only) trains: the kind it
  lacks is not drawn; nothing to draw at all is one line.
"""

from __future__ import annotations

import copy
import json
import math
import os
import shutil

import jax
import numpy as np
import pytest

import dataset_fixtures as fx
from pipeline_helpers import load_config
from pipeline_helpers import prepare_data
from pipeline_helpers import run_stage
from slotformer_jax import datasets
from slotformer_jax.data import prepare
from slotformer_jax.data import vqa_questions
from slotformer_jax.data.video_names import NAMES_FILE
from slotformer_jax.errors import UserError
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.stages import vqa as vqa_stages
from slotformer_jax.train import seeds as seeds_lib
from slotformer_jax.workdir.paths import Paths

pytestmark = pytest.mark.filterwarnings(
    r'ignore:os\.fork\(\) was called:RuntimeWarning')

# split -> [(video index, converts, the answer of its descriptive question)]
VIDEOS = {
    'train': [(0, True, 'red'), (1, False, 'blue'), (2, True, 'green'),
              (3, True, 'cyan')],
    'val': [(10799, True, 'red'), (10800, False, 'blue'),
            (10801, True, 'green')],
}
QUESTION_FILES = {'train': 'train.json', 'val': 'validation.json'}
FRAMES = 8
ROLLOUT = 4


def _scene(index: int, answer: str,
           kinds: tuple[str, ...] = ('descriptive', 'predictive')) -> dict:
  """A video's entry of a question file: a descriptive question whose
  answer names the video, and a predictive one (those of `kinds`)."""
  questions = {
      'descriptive': {'question_id': 0, 'question_type': 'descriptive',
                      'question': 'what color is the cube?',
                      'answer': answer},
      'predictive': {'question_id': 1, 'question_type': 'predictive',
                     'question': 'what will happen next?',
                     'choices': [{'choice_id': 0,
                                  'choice': 'the cube collides',
                                  'answer': 'correct'}]}}
  return {'scene_index': index, 'video_filename': f'video_{index:05d}.mp4',
          'questions': [questions[kind] for kind in kinds]}


@pytest.fixture(scope='module')
def clevrer(tmp_path_factory):
  """(config, workdir) with the converted splits and stand-in slots whose
  every value is the number of the video they belong to."""
  base = tmp_path_factory.mktemp('clevrer_join')
  root = base / 'CLEVRER'
  for split, videos in VIDEOS.items():
    for index, converts, _ in videos:
      fx.write_clevrer_video(root, split, index, num_frames=FRAMES,
                             annotated=converts or index == 10800)
    fx.write_json(root / 'questions' / QUESTION_FILES[split],
                  [_scene(index, answer) for index, _, answer in videos])
  assert prepare.main([
      '--dataset=clevrer', f'--source={root}', f'--data_dir={base / "data"}',
      '--resolution=8', f'--num_frames={FRAMES}', '--splits=train,val',
      '--masks=ignore', '--max_skip_fraction=0.5', '--num_workers=1',
      '--no_progress']) == 0
  config = load_config('clevrer_vqa')
  config.data.data_dir = str(base / 'data')
  config.data.resolution = (8, 8)
  vqa = config.vqa
  vqa.questions_root = str(root)
  vqa.video_length, vqa.rollout_frames = FRAMES, ROLLOUT
  vqa.num_frames, vqa.frame_stride = 2, 3
  vqa.word_dim, vqa.num_heads, vqa.d_model = 8, 4, 48
  vqa.num_layers, vqa.mlp_size, vqa.head_size = 1, 32, 16
  vqa.max_choices = 2
  vqa.open_batch_size = vqa.choice_batch_size = vqa.eval_batch_size = 8
  workdir = str(base / 'run')
  num_slots, slot_size = Run.create(config, workdir).slot_model.slot_shape
  for split, videos in VIDEOS.items():
    numbers = [index for index, converts, _ in videos if converts]
    slots = np.broadcast_to(
        np.array(numbers, np.float32)[:, None, None, None],
        (len(numbers), FRAMES + ROLLOUT, num_slots, slot_size))
    path = os.path.join(Paths.of(workdir).vqa, 'slots', f'{split}.npy')
    os.makedirs(os.path.dirname(path), exist_ok=True)
    np.save(path, slots)
  return config, workdir


def _check_open_rows(batch, vocab, split):
  """Every valid descriptive row reads the slots of the video its question
  names (answers identify the videos); returns how many rows."""
  video_of = {answer: index for index, _, answer in VIDEOS[split]}
  names = vocab.answer_names
  rows = np.flatnonzero(batch['open_valid'])
  for row in rows:
    video = video_of[names[int(batch['open_label'][row])]]
    np.testing.assert_array_equal(batch['open_slots'][row], float(video))
  return len(rows)


def test_training_questions_read_their_own_video_past_a_skipped_one(
    clevrer, monkeypatch):
  config, workdir = clevrer
  config = copy.deepcopy(config)
  captured = {}
  monkeypatch.setattr(seeds_lib, 'fit', lambda stages, **_: (
      captured.setdefault('stage', stages[0])))
  run_stage(config, workdir, sharding.make_mesh(), 'train_vqa')
  vocab = vqa_questions.vocabulary(config)
  batches = captured['stage'].batches(0)
  seen = sum(_check_open_rows(next(batches), vocab, 'train')
             for _ in range(4))
  assert seen == 4 * config.vqa.open_batch_size


def _untrained_aloe(run, inputs=None, seed=None):
  del inputs, seed
  vocab = vqa_questions.vocabulary(run.config)
  model, init = vqa_stages.model_and_init(run.config.vqa, vocab,
                                          run.slot_model.slot_shape)
  return vqa_stages.Aloe(module=model, params={'params': init(
      jax.random.key(0))}, step=0, vocab=vocab)


def test_evaluation_scores_each_question_on_its_own_video(clevrer,
                                                          monkeypatch):
  config, workdir = clevrer
  config = copy.deepcopy(config)
  monkeypatch.setattr(vqa_stages, 'load_aloe', _untrained_aloe)
  made = []
  build = vqa_stages.question_batches
  monkeypatch.setattr(vqa_stages, 'question_batches',
                      lambda *args: made.append(build(*args)) or made[-1])
  mesh = sharding.make_mesh()
  # 2 of the 6 validation questions are about video 10800: above 5%.
  with pytest.raises(UserError, match=r'2 of 6 questions .*video_10800.*'
                     r'max_missing_video_fraction=0.05'):
    run_stage(config, workdir, mesh, 'evaluate_vqa')
  config.vqa.max_missing_video_fraction = 0.5
  results = run_stage(config, workdir, mesh, 'evaluate_vqa')
  assert results['descriptive']['questions'] == 2
  assert results['predictive']['questions'] == 2
  assert results['left_out'] == {'questions': 2, 'of': 6,
                                 'videos_not_converted': ['video_10800']}
  vocab = vqa_questions.vocabulary(config)
  assert sum(_check_open_rows(batch, vocab, 'val')
             for batch, _, _ in made[-1].eval_batches(8, 8)) == 2


def test_a_folder_converted_before_the_names_gets_them_or_names_the_command(
    clevrer, tmp_path):
  config, _ = clevrer
  config = copy.deepcopy(config)
  shutil.copytree(config.data.data_dir, tmp_path / 'data')
  config.data.data_dir = str(tmp_path / 'data')
  names = datasets.get('clevrer').dataset_dir(config.data) / NAMES_FILE
  recorded = json.loads(names.read_text())
  assert recorded == {'train': ['video_00000', 'video_00002', 'video_00003'],
                      'val': ['video_10799', 'video_10801']}
  # As converted before the names were recorded: the data stage (which
  # every --mode runs first) takes them from the conversion's progress.
  names.unlink()
  prepare_data(config)
  assert json.loads(names.read_text()) == recorded
  # Without the progress files, the readers name the command.
  names.unlink()
  shutil.rmtree(names.parent / '_progress')
  prepare_data(config)
  with pytest.raises(UserError) as error:
    vqa_questions.split_video_names(config.data, 'val')
  message = str(error.value)
  assert 'records no video names' in message and '\n' not in message
  assert '--dataset=clevrer' in message and '--overwrite' in message


def _one_kind_run(clevrer, tmp_path, kinds):
  """(config, workdir): the training questions of `kinds` only, the
  converted videos and slots of `clevrer`, two steps of training."""
  config, workdir = clevrer
  config = copy.deepcopy(config)
  root = tmp_path / 'questions_root'
  fx.write_json(root / 'questions' / QUESTION_FILES['train'],
                [_scene(index, answer, kinds)
                 for index, _, answer in VIDEOS['train']])
  config.vqa.questions_root = str(root)
  config.vqa.num_train_steps = 2
  config.vqa.log_every = config.vqa.checkpoint_every = 1
  own = tmp_path / 'run'
  slots = os.path.join(Paths.of(str(own)).vqa, 'slots')
  os.makedirs(slots)
  shutil.copy(os.path.join(Paths.of(workdir).vqa, 'slots', 'train.npy'),
              slots)
  return config, str(own)


@pytest.mark.parametrize('kind', ['descriptive', 'predictive'])
def test_a_question_set_of_one_kind_trains(clevrer, tmp_path, kind):
  # Before: rng.integers(0, 0) of the empty kind, `ValueError: high <= 0`.
  config, workdir = _one_kind_run(clevrer, tmp_path, (kind,))
  run_stage(config, workdir, sharding.make_mesh(), 'train_vqa')
  log = os.path.join(Paths.of(workdir).aloe(config.vqa.inputs,
                                            config.vqa.seed),
                     'train_log.jsonl')
  with open(log) as f:
    records = [json.loads(line) for line in f]
  assert [r['step'] for r in records if 'loss' in r] == [1, 2]
  drawn, empty = (('open_loss', 'choice_loss') if kind == 'descriptive'
                  else ('choice_loss', 'open_loss'))
  for record in records:
    if 'loss' in record:
      assert record[drawn] > 0 and math.isfinite(record['loss'])
      assert record[empty] == 0.0  # no row of the other kind


def test_a_batch_size_of_0_leaves_a_kind_out_and_nothing_to_draw_is_one_line(
    clevrer, tmp_path, monkeypatch):
  config, workdir = _one_kind_run(clevrer, tmp_path, ('descriptive',))
  captured = {}
  monkeypatch.setattr(seeds_lib, 'fit', lambda stages, **_: (
      captured.setdefault('stage', stages[0])))
  mesh = sharding.make_mesh()
  config.vqa.open_batch_size = 0
  with pytest.raises(UserError) as error:
    run_stage(config, workdir, mesh, 'train_vqa')
  assert str(error.value) == (
      'VQA train: nothing to draw: 3 descriptive questions with '
      'vqa.open_batch_size=0, 0 multiple-choice ones with '
      'vqa.choice_batch_size=8; give a kind the training questions have a '
      'batch size > 0')
  # Both kinds, open_batch_size=0: only multiple-choice rows.
  config, workdir = _one_kind_run(clevrer, tmp_path / 'both',
                                  ('descriptive', 'predictive'))
  config.vqa.open_batch_size = 0
  run_stage(config, workdir, mesh, 'train_vqa')
  batch = next(captured['stage'].batches(0))
  assert batch['open_slots'].shape[0] == 0 and batch['open_valid'].size == 0
  assert batch['choice_valid'][:, 0].all()


def test_questions_about_videos_not_converted_stop_the_run_before_any_work(
    clevrer):
  """Issue 61: the missing-video check ran only after SAVi, extraction,
  SlotFormer and VQA training (9 min 45 s on real files), although the
  conversion already knew which videos it skipped. Now `--mode=all` (the
  checks before any work) says it."""
  from pipeline_helpers import check  # pylint: disable=g-import-not-at-top
  config, _ = clevrer
  config = copy.deepcopy(config)
  # (--mode=all checks its every stage with the same function; this
  # fixture's SlotFormer settings do not fit its 8 frames, so the task's
  # stages only.)
  every = ('train_vqa', 'evaluate_vqa')
  with pytest.raises(UserError) as error:
    check(config, every, num_devices=1)
  message = str(error.value)
  assert '\n' not in message
  assert 'val: 2 of 6 questions' in message and 'video_10800' in message
  assert 'max_missing_video_fraction=0.05' in message
  # Training alone leaves them out with a warning (no score is made).
  check(config, every[:-1], num_devices=1)
  config.vqa.max_missing_video_fraction = 0.5
  check(config, every, num_devices=1)
