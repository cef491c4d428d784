"""VQA task pieces: frame windows, scoring against hand computations,
batches, the answer prior and the prediction file."""

from __future__ import annotations

import numpy as np
import pytest

from slotformer_jax.data import vqa
from slotformer_jax.tasks import vqa as task


def test_official_frame_window():
  # CLEVRER: 128 frames, 25 samples with stride 128 // 25 = 5 -> 8 starts.
  assert task.num_starts(128, 25, 5) == 8
  idx = task.question_frames(7, video_length=128, available=128,
                             num_frames=25, stride=5, predictive=False)
  assert idx[0] == 7 and idx[-1] == 127
  # Predictive questions over observed + rollout slots move onto the rollout.
  idx = task.question_frames(7, video_length=128, available=128 + 40,
                             num_frames=25, stride=5, predictive=True)
  assert idx[0] == 47 and idx[-1] == 167
  # Other questions keep reading the observed frames.
  idx = task.question_frames(0, video_length=128, available=168,
                             num_frames=25, stride=5, predictive=False)
  assert idx[-1] == 120
  with pytest.raises(ValueError):
    task.num_starts(10, 5, 3)


def test_multiple_choice_scoring_by_hand():
  # 3 questions, up to 4 options (the last option of q0 and q2 is padding).
  predicted = np.array([[1, 0, 1, 1], [1, 1, 0, 0], [0, 0, 1, 0]], bool)
  labels = np.array([[1, 0, 1, 0], [1, 0, 0, 0], [0, 0, 1, 1]], bool)
  valid = np.array([[1, 1, 1, 0], [1, 1, 1, 1], [1, 1, 1, 0]], bool)
  types = np.array([2, 2, 3])
  # By hand: q0 3/3 options right (the wrong 4th is padding) -> right;
  # q1 3/4 -> wrong; q2 3/3 -> right (4th is padding).
  options, questions = task.score_choices(predicted == labels, valid)
  assert options.tolist() == [3, 3, 3]
  assert questions.tolist() == [True, False, True]
  metrics = task.VqaMetrics()
  metrics.add_choices(predicted, labels, valid, types)
  metrics.add_open(np.array([1, 2, 3, 4]), np.array([1, 2, 0, 0]))
  r = metrics.results()
  assert r['predictive'] == {'per_option': 6 / 7, 'per_question': 1 / 2,
                             'questions': 2}
  assert r['counterfactual'] == {'per_option': 1.0, 'per_question': 1.0,
                                 'questions': 1}
  assert r['descriptive'] == {'accuracy': 0.5, 'questions': 4}
  assert r['multiple_choice']['per_option'] == 9 / 10
  assert r['multiple_choice']['per_question'] == 2 / 3


def _scenes():
  return [
      {'scene_index': 15000, 'video_filename': 'video_15000.mp4',
       'questions': [
           {'question_id': 0, 'question_type': 'descriptive',
            'question': 'What color is the cube?', 'answer': 'red'},
           {'question_id': 1, 'question_type': 'predictive',
            'question': 'What will happen next?',
            'choices': [
                {'choice_id': 0, 'choice': 'The cube collides with the sphere',
                 'answer': 'correct'},
                {'choice_id': 1, 'choice': 'The sphere collides with the cube',
                 'answer': 'wrong'}]}]},
      {'scene_index': 15001, 'video_filename': 'video_15001.mp4',
       'questions': [
           {'question_id': 0, 'question_type': 'counterfactual',
            'question': 'What will happen without the cube?',
            'choices': [
                {'choice_id': 0, 'choice': 'The sphere collides with the cube',
                 'answer': 'wrong'},
                {'choice_id': 1, 'choice': 'The cube collides with the sphere',
                 'answer': 'wrong'},
                {'choice_id': 2, 'choice': 'The sphere collides with the cube',
                 'answer': 'correct'}]},
           {'question_id': 1, 'question_type': 'descriptive',
            'question': 'What shape is the red object?', 'answer': 'cube'}]}]


def test_batches_shapes_masks_and_rollout_window():
  scenes = _scenes()
  vocab = vqa.Vocabulary.from_scenes(scenes, answers=vqa.CLEVRER_ANSWERS)
  questions = vqa.encode_scenes(scenes, vocab, 8, 6)
  # Slot value = frame index, so the chosen frames can be read back.
  frames = np.arange(30, dtype=np.float32)[:, None, None] * np.ones((1, 3, 2))
  batches = task.QuestionBatches(
      questions, lambda name: frames, video_length=20, num_frames=4,
      stride=5, max_choices=4)
  assert batches.num_starts == 5
  batch, open_ids, choice_ids = next(batches.eval_batches(4, 4))
  assert open_ids == [0, 1] and choice_ids == [0, 1]
  assert batch['open_slots'].shape == (4, 4, 3, 2)
  assert batch['open_valid'].tolist() == [True, True, False, False]
  assert batch['choice_tokens'].shape == (4, 4, 14)
  assert batch['choice_valid'].tolist() == [
      [True, True, False, False], [True, True, True, False],
      [False] * 4, [False] * 4]
  assert batch['choice_label'][1, :3].tolist() == [0, 0, 1]
  assert batch['choice_type'][:2].tolist() == [2, 3]
  assert batch['open_label'][:2].tolist() == [vocab.answers['red'],
                                               vocab.answers['cube']]
  # Middle start (2); the predictive question reads 10 frames later.
  assert batch['open_slots'][0, :, 0, 0].tolist() == [2, 7, 12, 17]
  assert batch['choice_slots'][0, :, 0, 0].tolist() == [12, 17, 22, 27]
  assert batch['choice_slots'][1, :, 0, 0].tolist() == [2, 7, 12, 17]
  blind = task.QuestionBatches(questions, lambda name: frames,
                               video_length=20, num_frames=4, stride=5,
                               max_choices=4, blind=True)
  assert not next(blind.eval_batches(4, 4))[0]['open_slots'].any()
  # Training batches: a function of (seed, step).
  a = next(batches.train_batches(2, 2, seed=0, start_step=5))
  b = next(batches.train_batches(2, 2, seed=0, start_step=5))
  for key in a:
    np.testing.assert_array_equal(a[key], b[key])


@pytest.mark.parametrize('weights', [None, {'predictive': 3.0}])
def test_hosts_rows_concatenate_to_the_one_host_batch(weights):
  scenes = _scenes()
  vocab = vqa.Vocabulary.from_scenes(scenes, answers=vqa.CLEVRER_ANSWERS)
  questions = vqa.encode_scenes(scenes, vocab, 8, 6)
  frames = np.arange(30, dtype=np.float32)[:, None, None] * np.ones((1, 3, 2))
  batches = task.QuestionBatches(
      questions, lambda name: frames, video_length=20, num_frames=4,
      stride=5, max_choices=4, choice_weights=weights)
  one = batches.train_batches(6, 4, seed=3, start_step=2)
  hosts = [batches.train_batches(3, 2, seed=3, start_step=2, process_index=p,
                                 process_count=2) for p in (0, 1)]
  for _ in range(4):
    expected, parts = next(one), [next(host) for host in hosts]
    for key in expected:
      np.testing.assert_array_equal(
          np.concatenate([part[key] for part in parts]), expected[key],
          err_msg=key)


def test_choice_type_weights_set_the_share_of_each_type():
  scenes = _scenes()
  vocab = vqa.Vocabulary.from_scenes(scenes, answers=vqa.CLEVRER_ANSWERS)
  questions = vqa.encode_scenes(scenes, vocab, 8, 6)
  frames = np.zeros((30, 3, 2), np.float32)

  def share_of_predictive(weights):
    batches = task.QuestionBatches(
        questions, lambda name: frames, video_length=20, num_frames=4,
        stride=5, max_choices=4, choice_weights=weights)
    stream = batches.train_batches(1, 64, seed=0)
    types = np.concatenate([next(stream)['choice_type'] for _ in range(20)])
    return np.mean(types == task.PREDICTIVE)

  # One predictive and one counterfactual question: uniform draws give ~1/2,
  # weight 3 on predictive ~3/4, weight 0 on counterfactual all predictive.
  assert abs(share_of_predictive(None) - 0.5) < 0.06
  assert abs(share_of_predictive({'predictive': 3.0}) - 0.75) < 0.06
  assert share_of_predictive({'counterfactual': 0.0}) == 1.0
  with pytest.raises(ValueError):
    share_of_predictive({'descriptive': 2.0})


def test_answer_prior_and_prediction_file():
  scenes = _scenes()
  vocab = vqa.Vocabulary.from_scenes(scenes, answers=vqa.CLEVRER_ANSWERS)
  questions = vqa.encode_scenes(scenes, vocab, 8, 6)
  prior = task.fit_answer_prior(questions)
  # Per question type here (no templates); the predictive tie goes to 0.
  assert prior['choice'] == {'predictive': 0, 'counterfactual': 0}
  r = task.evaluate_answer_prior(prior, questions)
  assert r['predictive'] == {'per_option': 0.5, 'per_question': 0.0,
                             'questions': 1}
  assert r['counterfactual']['per_option'] == 2 / 3
  predictions = task.prediction_file(
      questions, open_answers={0: vocab.answers['red'], 3: 0},
      choice_correct={1: [True, False], 2: [False, False, True]},
      answer_names=vocab.answer_names)
  assert predictions == [
      {'scene_index': 15000, 'questions': [
          {'question_id': 0, 'answer': 'red'},
          {'question_id': 1, 'choices': [
              {'choice_id': 0, 'answer': 'correct'},
              {'choice_id': 1, 'answer': 'wrong'}]}]},
      {'scene_index': 15001, 'questions': [
          {'question_id': 0, 'choices': [
              {'choice_id': 0, 'answer': 'wrong'},
              {'choice_id': 1, 'answer': 'wrong'},
              {'choice_id': 2, 'answer': 'correct'}]},
          {'question_id': 1, 'answer': 'PAD'}]}]


def test_rollout_after_video_interleaves_strided_predictions():
  # A "dynamics model" that continues the frame index linearly: slot value
  # = frame number, so every predicted frame must equal its index.
  def rollout(history, steps):
    step = history[:, 1] - history[:, 0]
    return history[:, -1:] + step[:, None] * np.arange(
        1, steps + 1)[None, :, None, None]
  observed = np.arange(20, dtype=np.float32)[None, :, None, None] * np.ones(
      (2, 1, 3, 1))
  for stride in (1, 2, 3):
    future = task.rollout_after_video(rollout, observed, burn_in=4,
                                      stride=stride, num_frames=7)
    assert future.shape == (2, 7, 3, 1)
    assert future[0, :, 0, 0].tolist() == list(range(20, 27))


def test_open_accuracy_per_template_by_hand():
  def q(template: str, answer: int) -> vqa.EncodedQuestion:
    return vqa.EncodedQuestion(
        scene_index=0, video_filename='v', question_id=0, question_type=0,
        template=template, tokens=np.zeros((1, 3), np.int32),
        pad_mask=np.zeros((1, 3), bool), answer=answer)
  questions = [q('count_collisions', 2), q('count_collisions', 3),
               q('color_entering', 5), q('', 1), q('color_entering', -1)]
  # 1 of 2 count_collisions right, 1 of 1 color_entering; no template (a
  # CLEVRER file) or no answer: not counted.
  got = task.open_accuracy_per_template(
      questions, {0: 2, 1: 2, 2: 5, 3: 1, 4: 7})
  assert got == {'color_entering': {'accuracy': 1.0, 'questions': 1},
                 'count_collisions': {'accuracy': 0.5, 'questions': 2}}
