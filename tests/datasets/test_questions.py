"""Question generator: every template against a hand-built event log."""

from __future__ import annotations

import collections
import re

import numpy as np
import pytest

from slotformer_jax.data import vqa
from slotformer_jax.datasets import clevrer_like_questions as qg
from slotformer_jax.data.events import Collision
from slotformer_jax.data.events import EventLog

RED_CUBE, BLUE_SPHERE, GREEN_CYL, YELLOW_SPHERE = range(4)
NAMES = ['red cube', 'blue sphere', 'green cylinder', 'yellow sphere']


def hand_log() -> EventLog:
  """Red cube hits blue sphere (3), blue sphere hits green cylinder (8), the
  yellow sphere enters (5) and hits the green cylinder (12); after the video
  (observed 20 frames) the red cube and yellow sphere collide (24).

  Counterfactuals: without the red cube the blue sphere never reaches the
  cylinder; without the cylinder only the first collision is left.
  """
  return EventLog(
      objects=[{'color': 'red', 'shape': 'cube', 'size': 'small'},
               {'color': 'blue', 'shape': 'sphere', 'size': 'large'},
               {'color': 'green', 'shape': 'cylinder', 'size': 'small'},
               {'color': 'yellow', 'shape': 'sphere', 'size': 'small'}],
      observed_frames=20, num_frames=30,
      collisions=[Collision((0, 1), 3), Collision((1, 2), 8),
                  Collision((2, 3), 12), Collision((0, 3), 24)],
      entering=[(3, 5)], exiting=[],
      moving_at_end=[False, True, True, True],
      in_view_at_end=[True, True, True, True],
      final_positions=[[0.0, 0.0, 0.5]] * 4,
      counterfactual={
          0: [Collision((2, 3), 12)],
          1: [Collision((2, 3), 13)],
          2: [Collision((0, 1), 3)],
          3: [Collision((0, 1), 3), Collision((1, 2), 8)],
      })


def collides(a: int, b: int) -> str:
  return f'the {NAMES[a]} collides with the {NAMES[b]}'


def _by_template(log: EventLog, seed: int) -> dict[str, dict]:
  out = {}
  for q in qg.candidate_questions(log, np.random.default_rng(seed)):
    out[q['template']] = q
  return out


def _named(text: str) -> int:
  found = [k for k, n in enumerate(NAMES) if n in text]
  assert len(found) == 1, text
  return found[0]


def test_descriptive_answers():
  log = hand_log()
  # The randomly picked object changes with the seed; the answer must match.
  for seed in range(8):
    q = _by_template(log, seed)
    assert q['count_collisions']['answer'] == '3'  # the 4th is after the video
    assert q['count_entering']['answer'] == '1'
    assert q['count_moving_end']['answer'] == '3'
    assert q['color_entering']['answer'] == 'yellow'
    obj = _named(q['is_moving_end']['question'])
    assert q['is_moving_end']['answer'] == ('no' if obj == RED_CUBE else 'yes')
    # Only the red cube (-> blue sphere) and the yellow sphere (-> green
    # cylinder) collide with exactly one object during the video.
    obj = _named(q['color_collides_with']['question'])
    assert q['color_collides_with']['answer'] == {
        RED_CUBE: 'blue', YELLOW_SPHERE: 'green'}[obj]
    obj = _named(q['shape_collides_with']['question'])
    assert q['shape_collides_with']['answer'] == {
        RED_CUBE: 'sphere', YELLOW_SPHERE: 'cylinder'}[obj]
  # Every template has a question about this log.
  assert set(_by_template(log, 0)) == set(qg.TEMPLATES)


def test_count_templates_count_objects_in_view():
  log = hand_log()
  # The blue sphere leaves the view (14) and comes back (17): not an entering
  # object (it was there from the start), and not counted twice. The green
  # cylinder is still moving at the end but out of view: not counted.
  log.exiting = [(BLUE_SPHERE, 14)]
  log.entering = [(YELLOW_SPHERE, 5), (BLUE_SPHERE, 17)]
  log.in_view_at_end[GREEN_CYL] = False
  assert qg.entered_objects(log) == [YELLOW_SPHERE]
  assert qg.moving_in_view_at_end(log) == [BLUE_SPHERE, YELLOW_SPHERE]
  for seed in range(4):
    q = _by_template(log, seed)
    assert q['count_entering']['answer'] == '1'
    assert q['color_entering']['answer'] == 'yellow'
    assert q['count_moving_end']['answer'] == '2'
  # An object that enters twice (in, out, in) is one entering object; one
  # entering after the video is none.
  log.exiting = [(YELLOW_SPHERE, 9)]
  log.entering = [(YELLOW_SPHERE, 5), (YELLOW_SPHERE, 11), (RED_CUBE, 25)]
  assert qg.entered_objects(log) == [YELLOW_SPHERE]
  assert _by_template(log, 0)['count_entering']['answer'] == '1'


def chain_log() -> EventLog:
  """Five objects; the target is the green cylinder - purple cube collision
  (10). The red cube hits the blue sphere (3), which hits the cylinder (6),
  which goes on to the purple cube; the yellow sphere hits the purple cube
  (4) but the cylinder would reach the cube anyway.

  Counterfactuals: without the red cube or the blue sphere the target does
  not happen; without the yellow sphere it happens one frame later.
  """
  return EventLog(
      objects=[{'color': 'red', 'shape': 'cube', 'size': 'small'},
               {'color': 'blue', 'shape': 'sphere', 'size': 'large'},
               {'color': 'green', 'shape': 'cylinder', 'size': 'small'},
               {'color': 'yellow', 'shape': 'sphere', 'size': 'small'},
               {'color': 'purple', 'shape': 'cube', 'size': 'small'}],
      observed_frames=20, num_frames=30,
      collisions=[Collision((0, 1), 3), Collision((3, 4), 4),
                  Collision((1, 2), 6), Collision((2, 4), 10)],
      entering=[], exiting=[],
      moving_at_end=[False, False, True, False, True],
      in_view_at_end=[True] * 5, final_positions=[[0.0, 0.0, 0.5]] * 5,
      counterfactual={
          0: [Collision((3, 4), 4)],
          1: [Collision((3, 4), 4)],
          2: [Collision((0, 1), 3), Collision((3, 4), 4)],
          3: [Collision((0, 1), 3), Collision((1, 2), 6),
              Collision((2, 4), 11)],
          4: [Collision((0, 1), 3), Collision((1, 2), 6)],
      })


def test_explanatory_choices():
  log = hand_log()
  # Target blue sphere - green cylinder (8): without the red cube it does not
  # happen; the yellow sphere (entered at 5) is not needed. The red cube -
  # blue sphere collision is responsible too (without the red cube, no
  # target), but it is the only collision choice: that kind has one label.
  assert qg.responsible_choices(log, 1) == {
      'presence': (['the presence of the red cube'],
                   ['the presence of the yellow sphere']),
      'collision_event': (
          ['the collision between the red cube and the blue sphere'], []),
      'other_collision_event': ([], [])}
  # Target green cylinder - yellow sphere (12): no single object's absence
  # prevents it (it happens a frame later without the blue sphere), so
  # nothing is responsible: no question about it. The red cube - blue sphere
  # collision shares no object with the target: the other kind.
  assert qg.responsible_choices(log, 2) == {
      'presence': ([], ['the presence of the red cube',
                        'the presence of the blue sphere']),
      'collision_event': ([], [
          'the collision between the blue sphere and the green cylinder']),
      'other_collision_event': ([], [
          'the collision between the red cube and the blue sphere'])}
  log = chain_log()
  # The presence and the collision kinds agree: both by re-simulation.
  assert qg.responsible_choices(log, 3) == {
      'presence': (['the presence of the red cube',
                    'the presence of the blue sphere'],
                   ['the presence of the yellow sphere']),
      'collision_event': (
          ['the collision between the blue sphere and the green cylinder'],
          ['the collision between the yellow sphere and the purple cube']),
      'other_collision_event': (
          ['the collision between the red cube and the blue sphere'], [])}


def test_explanatory_labels_balanced_within_each_choice_kind():
  # Within a question, each kind of choice ("the presence of ...", "the
  # collision between ..." naming an object of the target or not) has as
  # many correct as wrong choices, so the wording of a choice does not tell
  # its label (the old generator's collision choices were almost always
  # correct).
  names = NAMES + ['purple cube']
  # Targets with both labels in some kind: the chain log's blue sphere -
  # green cylinder and green cylinder - purple cube, the hand log's blue
  # sphere - green cylinder.
  for log, targets in ((chain_log(), {(1, 2), (2, 4)}),
                       (hand_log(), {(1, 2)})):
    observed = [c.objects for c in log.observed_collisions()]
    for seed in range(16):
      asked = set()
      for q in qg.candidate_questions(log, np.random.default_rng(seed)):
        if q['template'] != 'responsible':
          continue
        pair = tuple(sorted(names.index(n) for n in re.search(
            'between the (.*) and the (.*)', q['question']).groups()))
        asked.add(pair)
        kinds = qg.responsible_choices(log, observed.index(pair))
        per_kind = collections.defaultdict(collections.Counter)
        for choice in q['choices']:
          (kind,) = [k for k, pools in kinds.items()
                     if choice['choice'] in pools[choice['answer'] == 'wrong']]
          per_kind[kind][choice['answer']] += 1
        for counts in per_kind.values():
          assert counts['correct'] == counts['wrong'] >= 1, q
        assert len(q['choices']) <= qg.MAX_CHOICES
      assert asked == targets
  # Both kinds have both labels for the chain log's last collision: 2 + 2.
  for q in qg.candidate_questions(chain_log(), np.random.default_rng(0)):
    if q['template'] == 'responsible' and 'purple' in q['question']:
      assert len(q['choices']) == 4


def test_predictive_choices():
  log = hand_log()
  correct, wrong = qg.predictive_choices(log)
  assert correct == [collides(RED_CUBE, YELLOW_SPHERE)]
  assert sorted(wrong) == sorted(
      collides(a, b) for a, b in [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)])
  # An object out of view at the end is not asked about.
  log.in_view_at_end[YELLOW_SPHERE] = False
  correct, wrong = qg.predictive_choices(log)
  assert correct == [] and len(wrong) == 3


def test_two_predictive_questions_with_disjoint_balanced_choices():
  log = hand_log()
  # Two collisions after the video: two questions, each with one correct
  # and one wrong choice (balanced), no choice asked twice.
  log.collisions.append(Collision((1, 2), 26))
  correct, wrong = qg.predictive_choices(log)
  assert sorted(correct) == sorted([collides(RED_CUBE, YELLOW_SPHERE),
                                    collides(BLUE_SPHERE, GREEN_CYL)])
  for seed in range(8):
    questions = [q for q in qg.candidate_questions(
        log, np.random.default_rng(seed)) if q['template'] == 'next']
    assert len(questions) == qg.MAX_PREDICTIVE == 2
    asked = [c['choice'] for q in questions for c in q['choices']]
    assert len(asked) == len(set(asked))
    for q in questions:
      labels = collections.Counter(c['answer'] for c in q['choices'])
      assert labels['correct'] == labels['wrong'] >= 1
      for choice in q['choices']:
        assert choice['choice'] in (correct if choice['answer'] == 'correct'
                                    else wrong)
  # One future collision: one question.
  log.collisions.pop()
  assert [q['template'] for q in qg.candidate_questions(
      log, np.random.default_rng(0))].count('next') == 1


def test_deflected_predictive_choices_balanced_within_each_verdict():
  # A log of the 'deflected' design carries the extrapolation's verdict
  # per pair (clevrer_like.extrapolation_verdict): every predictive question has
  # as many correct as wrong choices within each verdict, so a rule on the
  # verdict is right on half of them.
  log = hand_log()
  log.collisions.append(Collision((1, 2), 26))  # future: (0, 3), (1, 2)
  log.extrapolated = [(0, 1, 3), (0, 2, 0), (0, 3, 3), (1, 2, 1),
                      (1, 3, 1), (2, 3, 0)]
  verdict = {collides(a, b): v for a, b, v in log.extrapolated}
  assert qg.predictive_choices(log, 3) == ([collides(0, 3)],
                                           [collides(0, 1)])
  assert qg.predictive_choices(log, 1) == ([collides(1, 2)],
                                           [collides(1, 3)])
  assert qg.predictive_choices(log, 0) == ([], [collides(0, 2),
                                                collides(2, 3)])
  asked = set()
  for seed in range(8):
    questions = [q for q in qg.candidate_questions(
        log, np.random.default_rng(seed)) if q['template'] == 'next']
    assert questions
    seen = [c['choice'] for q in questions for c in q['choices']]
    assert len(seen) == len(set(seen))
    for q in questions:
      labels = collections.Counter((verdict[c['choice']], c['answer'])
                                   for c in q['choices'])
      for v in {v for v, _ in labels}:
        assert labels[(v, 'correct')] == labels[(v, 'wrong')] >= 1
      asked.update(c['choice'] for c in q['choices'])
  # Verdict 0 has no collision: its pairs are never offered.
  assert collides(0, 2) not in asked and collides(2, 3) not in asked
  # Without verdicts (the 'direct' design), the far pairs are offered.
  log.extrapolated = None
  assert any(collides(0, 2) in [c['choice'] for c in q['choices']]
             for seed in range(8)
             for q in qg.candidate_questions(log, np.random.default_rng(seed))
             if q['template'] == 'next')


def test_counterfactual_choices():
  log = hand_log()
  # Without the red cube only green cylinder - yellow sphere happens; the
  # blue sphere - green cylinder collision of the video is the wrong choice.
  assert qg.counterfactual_choices(log, RED_CUBE) == (
      [collides(GREEN_CYL, YELLOW_SPHERE)],
      [collides(BLUE_SPHERE, GREEN_CYL)])
  # Without the yellow sphere the first two collisions still happen; the
  # only pair that does not collide is the wrong choice.
  assert qg.counterfactual_choices(log, YELLOW_SPHERE) == (
      [collides(RED_CUBE, BLUE_SPHERE), collides(BLUE_SPHERE, GREEN_CYL)],
      [collides(RED_CUBE, GREEN_CYL)])
  for seed in range(8):
    q = _by_template(log, seed)['removed']
    x = _named(q['question'])
    correct, wrong = qg.counterfactual_choices(log, x)
    labels = collections.Counter(c['answer'] for c in q['choices'])
    assert labels['correct'] == labels['wrong'] >= 1
    for choice in q['choices']:
      assert choice['choice'] in (correct if choice['answer'] == 'correct'
                                  else wrong)


def _logs(n: int) -> list[EventLog]:
  """Variations of the hand-built log (different collision counts)."""
  logs = []
  for k in range(n):
    log = hand_log()
    log.collisions = log.collisions[k % 3:]
    log.moving_at_end = [bool((k + i) % 2) for i in range(4)]
    logs.append(log)
  return logs


def test_split_is_deterministic_and_balanced():
  logs = _logs(30)
  a = qg.generate_split(logs, seed=3, split='train')
  assert a == qg.generate_split(logs, seed=3, split='train')
  assert a != qg.generate_split(logs, seed=4, split='train')
  per_template = collections.defaultdict(collections.Counter)
  for scene in a:
    ids = [q['question_id'] for q in scene['questions']]
    assert ids == list(range(len(ids)))
    for q in scene['questions']:
      if q['question_type'] == 'descriptive':
        per_template[q['template']][q['answer']] += 1
      else:
        labels = collections.Counter(c['answer'] for c in q['choices'])
        assert labels['correct'] == labels['wrong'] >= 1
  unbalanced = collections.defaultdict(collections.Counter)
  for v, log in enumerate(logs):
    rng = np.random.default_rng([3, 0, v, 1212])
    for q in qg.candidate_questions(log, rng):
      if q['question_type'] == 'descriptive':
        unbalanced[q['template']][q['answer']] += 1
  for template, counts in per_template.items():
    cap = qg.lower_median(list(unbalanced[template].values()))
    assert max(counts.values()) <= cap, (template, counts)
  # A two-answer template is exactly balanced (the lower median).
  assert per_template['is_moving_end']['yes'] == per_template[
      'is_moving_end']['no'] > 0
  # count_collisions answers 3, 2, 1 equally often before and after.
  assert set(per_template['count_collisions']) == {'1', '2', '3'}


def test_vocabulary_covers_templates_and_encoding_round_trips():
  scenes = qg.generate_split(_logs(12), seed=0, split='val')
  vocab = vqa.Vocabulary.from_scenes(scenes, answers=qg.template_answers())
  assert set(vocab.questions) - {vqa.PAD} <= set(qg.template_words())
  n = 0
  for scene in scenes:
    for q in scene['questions']:
      tokens, pad = vqa.encode_text(q['question'], vocab.questions, 20)
      assert vqa.decode_tokens(tokens, pad, vocab.questions) == q['question']
      enc = vqa.encode_question(scene, q, vocab, 20, 12)
      if q['question_type'] == 'descriptive':
        assert vocab.answer_names[enc.answer] == q['answer']
        assert enc.tokens.shape == (1, 32)
      else:
        for row, pad_row, choice in zip(enc.tokens, enc.pad_mask,
                                        q['choices']):
          assert vqa.decode_tokens(row[:20], pad_row[:20],
                                   vocab.questions) == q['question']
          assert vqa.decode_tokens(row[20:], pad_row[20:],
                                   vocab.questions) == choice['choice']
        assert enc.choice_labels.tolist() == [
            int(c['answer'] == 'correct') for c in q['choices']]
      n += 1
  assert n > 0
  with pytest.raises(vqa.QuestionFileError, match='do not fit in 3'):
    vqa.encode_text('how many collisions happen', vocab.questions, 3)
  with pytest.raises(vqa.QuestionFileError, match="word 'dragons'"):
    vqa.encode_text('how many dragons', vocab.questions, 5)


def test_official_vocabulary_conventions():
  # PAD first, then sorted words: the official ids, e.g. 'yes' is 21.
  answers = vqa.make_vocabulary(vqa.CLEVRER_ANSWERS)
  assert answers['PAD'] == 0 and answers['0'] == 1 and answers['yes'] == 21
  assert answers['blue'] == 7 and answers['yellow'] == 20
  assert vqa.tokenize('What is the shape of the cube, that enters?') == [
      'what', 'is', 'the', 'shape', 'of', 'the', 'cube,', 'that', 'enters']


def test_synthetic_vqa_config_fits_every_template():
  from pipeline_helpers import load_config  # pylint: disable=g-import-not-at-top
  config = load_config('synthetic_vqa')
  question, choice = qg.max_lengths()
  assert question == 17 and choice == 10  # the explanatory template
  assert config.vqa.max_question_len >= question
  assert config.vqa.max_choice_len >= choice
  # The counted worst case is real: encode it.
  vocab = vqa.make_vocabulary(qg.template_words())
  text = qg.TEMPLATES['responsible'][1].format(a='green cylinder',
                                               b='blue sphere')
  vqa.encode_text(text, vocab, question)
