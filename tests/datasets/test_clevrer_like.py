"""Tests of the CLEVRER-like scenario family: event log and counterfactuals."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from slotformer_jax import datasets

from slotformer_jax.datasets import clevrer_like
from slotformer_jax.datasets import synthetic
from slotformer_jax.data.events import EventLog
from dataset_fixtures import data_section

CONFIG = clevrer_like.ClevrerLikeConfig(
    observed_frames=12, predicted_frames=8, num_train=4, num_val=2,
    num_test=2)


def _two_spheres(gap: float, speed: float, *, third: bool = False
                 ) -> clevrer_like.Scene:
  """Two small spheres rolling at each other along x (+ a far resting cube).

  Surfaces start ``gap`` metres apart, each moving at ``speed`` m/s.
  """
  r = synthetic.SIZE_RADII[0]
  half = r + gap / 2
  n = 3 if third else 2
  xy = [[-half, 0.5], [half, 0.5], [0.0, 2.2]][:n]
  velocity = [[speed, 0.0], [-speed, 0.0], [0.0, 0.0]][:n]
  return clevrer_like.Scene(
      shapes=np.array([1, 1, 0][:n], np.int32),
      colors=np.array([1, 2, 3][:n], np.int32),
      sizes=np.zeros(n, np.int32),
      xy=np.array(xy, np.float64), yaw=np.zeros(n),
      velocity=np.array(velocity, np.float64),
      enter_frame=np.zeros(n, np.int32))


def test_collision_onset_at_substep_resolution():
  gap, speed = 0.6, 1.5
  sim = clevrer_like.simulate(_two_spheres(gap, speed), CONFIG)
  assert sim['collisions'], 'head-on spheres must collide'
  a, b, frame, substep = sim['collisions'][0]
  assert (a, b) == (0, 1)
  # Rolling friction slows them a little: contact no earlier than the
  # frictionless time, and within a few substeps of it.
  expected = gap / (2 * speed) / synthetic.PHYSICS_DT
  assert expected - 2 <= substep <= expected * 1.1 + 2, (substep, expected)
  assert frame == -(-substep // synthetic.SUBSTEPS_PER_FRAME)
  # The contact is reported once (restitution separates them, no chatter).
  assert [c[:2] for c in sim['collisions']].count((0, 1)) == 1


def test_counterfactual_removes_the_object_and_its_collisions():
  scene = _two_spheres(0.6, 1.5, third=True)
  full = clevrer_like.simulate(scene, CONFIG)
  without = clevrer_like.simulate(scene, CONFIG, removed=1)
  assert any(c[:2] == (0, 1) for c in full['collisions'])
  assert without['collisions'] == []
  assert not without['present'][:, 1].any()
  assert without['present'][:, [0, 2]].all()
  # Removing the resting cube (never hit) changes nothing of the rest.
  no_cube = clevrer_like.simulate(scene, CONFIG, removed=2)
  assert [c[:3] for c in no_cube['collisions']] == [
      c[:3] for c in full['collisions']]


def test_counterfactual_resimulation_is_deterministic():
  video = clevrer_like.generate_video(CONFIG, 'train', 3, render=False)
  again = clevrer_like.generate_video(CONFIG, 'train', 3, render=False)
  assert video['events'].to_dict() == again['events'].to_dict()
  scene = clevrer_like.sample_scene(
      clevrer_like.video_rng(CONFIG.seed, 'train', 3), CONFIG)
  for k in range(scene.num_objects):
    a = clevrer_like.simulate(scene, CONFIG, removed=k)
    b = clevrer_like.simulate(scene, CONFIG, removed=k)
    assert a['collisions'] == b['collisions']
    assert a['positions'].tobytes() == b['positions'].tobytes()


def test_entering_object_appears_later_and_enters_the_view():
  scene = _two_spheres(3.0, 0.0)
  # Object 1 enters at frame 3 from the right, rolling left into view.
  scene = dataclasses.replace(
      scene, xy=np.array([[-1.5, 0.5], [clevrer_like.ENTER_X, 0.5]]),
      velocity=np.array([[0.0, 0.0], [-4.0, 0.0]]),
      enter_frame=np.array([0, 3], np.int32))
  sim = clevrer_like.simulate(scene, CONFIG)
  assert not sim['present'][:3, 1].any() and sim['present'][3:, 1].all()
  assert sim['in_view'][:, 0].all()
  log = clevrer_like.event_log(scene, sim, CONFIG)
  assert [i for i, _ in log.entering] == [1]
  assert log.entering[0][1] > 3
  assert not sim['in_view'][log.entering[0][1] - 1, 1]


def test_generate_video_render_and_event_log_roundtrip():
  video = clevrer_like.generate_video(CONFIG, 'val', 0)
  t, (h, w) = CONFIG.num_frames, CONFIG.resolution
  assert video['video'].shape == (t, h, w, 3)
  assert video['segmentations'].shape == (t, h, w)
  assert video['boxes'].shape == (t, CONFIG.max_objects_total, 4)
  events = video['events']
  n = int(video['num_objects'])
  assert len(events.objects) == n and set(events.counterfactual) == set(
      range(n))
  assert len({o['color'] for o in events.objects}) == n  # distinct colours
  again = EventLog.from_dict(events.to_dict())
  assert again == events
  # Physics only (no rendering) gives the same events.
  physics = clevrer_like.generate_video(CONFIG, 'val', 0, render=False)
  assert physics['events'] == events


def test_config_rejects_too_many_objects():
  with pytest.raises(ValueError):
    clevrer_like.ClevrerLikeConfig(max_objects=7, max_entering=2)


def test_build_dataset_writes_videos_questions_and_vocabulary(tmp_path):
  import json  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import vqa  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data.write import generate  # pylint: disable=g-import-not-at-top
  from slotformer_jax.errors import MissingInputError  # pylint: disable=g-import-not-at-top
  data = data_section(
      name='clevrer_like', data_dir=str(tmp_path), resolution=(32, 32),
      observed_frames=12,
      predicted_frames=8, num_train=3, num_val=1, num_test=2, num_workers=1)
  generate.make_dataset(datasets.get('clevrer_like'), data)
  source = datasets.get_video_source(data, 'test')
  assert len(source) == 2
  item = source[1]
  assert item['video'].shape == (20, 32, 32, 3)
  # What the spec says a video holds.
  spec = datasets.get('clevrer_like').features()
  assert sorted(item) == sorted(spec)
  for key, feature in spec.items():
    assert item[key].dtype == feature.np_dtype, key
    assert item[key].ndim == len(feature.shape), key
  config = clevrer_like.config_from_data_config(data)
  np.testing.assert_array_equal(
      item['video'], clevrer_like.generate_video(config, 'test', 1)['video'])
  root = clevrer_like.dataset_dir(config, tmp_path)
  vocab = vqa.Vocabulary.load(root / 'vocab.json')
  scenes = vqa.read_clevrer_questions(root, 'test')
  assert [s['scene_index'] for s in scenes] == [15000, 15001]
  # Every generated question encodes with the stored vocabulary.
  vqa.encode_scenes(scenes, vocab, 20, 12)
  with open(root / 'test' / 'events.jsonl') as f:
    logs = [EventLog.from_dict(json.loads(line)) for line in f]
  assert logs[1] == clevrer_like.generate_video(
      config, 'test', 1, render=False)['events']
  # A dataset from an older question generator gets new questions from its
  # event logs; its videos are not regenerated.
  with open(root / 'complete.json') as f:
    complete = json.load(f)
  complete['questions_version'] -= 1
  with open(root / 'complete.json', 'w') as f:
    json.dump(complete, f)
  (root / 'questions' / 'test.json').write_text('[]')
  video_mtime = (root / 'test' / 'video.npy').stat().st_mtime_ns
  # ... which the readers refuse until the data stage has made them.
  with pytest.raises(MissingInputError, match='--mode=prepare_data'):
    datasets.get_video_source(data, 'test')
  assert clevrer_like.generate(config, generate.Output(tmp_path)) == root
  assert vqa.read_clevrer_questions(root, 'test') == scenes
  assert (root / 'test' / 'video.npy').stat().st_mtime_ns == video_mtime


def test_future_collision_fraction_gives_something_to_predict():
  # With fraction 1 every video is drawn among scenes where two objects in
  # view at the end of the video collide after it (if one is found within
  # MAX_SCENE_TRIES draws); with 0 it is the first draw.
  config = dataclasses.replace(CONFIG, future_collision_fraction=1.0)
  found = 0
  for index in range(4):
    scene = clevrer_like.sample_video_scene(
        clevrer_like.video_rng(0, 'train', index), config)
    found += clevrer_like.has_future_collision(
        clevrer_like.simulate(scene, config), config)
  assert found == 4
  plain = [clevrer_like.has_future_collision(clevrer_like.simulate(
      clevrer_like.sample_video_scene(clevrer_like.video_rng(0, 'train', i),
                                      CONFIG), CONFIG), CONFIG)
           for i in range(4)]
  assert sum(plain) < 4
  # Fraction 0 draws exactly the scenes of generator version 1.
  a = clevrer_like.sample_video_scene(clevrer_like.video_rng(0, 'val', 1),
                                      CONFIG)
  b = clevrer_like.sample_scene(clevrer_like.video_rng(0, 'val', 1), CONFIG)
  for field in dataclasses.fields(a):
    np.testing.assert_array_equal(getattr(a, field.name),
                                  getattr(b, field.name))
  with pytest.raises(ValueError):
    dataclasses.replace(CONFIG, future_collision_fraction=1.5)


# ---- predictive_design (issue 12, round 4) --------------------------------

DEFLECTED = dataclasses.replace(CONFIG, predictive_design='deflected',
                                future_collision_fraction=1.0)


def test_direct_design_is_the_generator_of_before():
  # The default design keeps the slugs (so the datasets already built) and
  # the event logs of generator version 2: values pinned before the field
  # existed.
  assert (clevrer_like.ClevrerLikeConfig().slug
          == 'r32x32_t24+16_o2-4+1_s0_038d4ccb')
  config = dataclasses.replace(CONFIG, future_collision_fraction=1.0)
  assert config.slug == 'r32x32_t12+8_o2-4+1_s0_41f59940'
  assert 'predictive_design' not in config.identity()
  events = clevrer_like.generate_video(config, 'train', 1,
                                       render=False)['events'].to_dict()
  assert 'extrapolated' not in events
  digest = hashlib.sha256(json.dumps(events, sort_keys=True).encode())
  assert digest.hexdigest() == ('f6aa069c54abd493a635d2785636ec24a7eff939d4'
                                '7fabc491cfe0b17bab5ee5')
  # The new design is another dataset.
  assert DEFLECTED.slug != config.slug
  assert DEFLECTED.identity()['predictive_design'] == 'deflected'
  with pytest.raises(ValueError):
    dataclasses.replace(CONFIG, predictive_design='bank')
  with pytest.raises(ValueError):
    dataclasses.replace(DEFLECTED, min_objects=2, max_objects=2)


def test_deflected_design_is_deterministic_and_asks_something():
  first = [clevrer_like.generate_video(DEFLECTED, 'val', i, render=False)
           for i in range(3)]
  again = clevrer_like.generate_video(DEFLECTED, 'val', 1, render=False)
  np.testing.assert_array_equal(first[1]['positions'], again['positions'])
  assert first[1]['events'].to_dict() == again['events'].to_dict()
  assert first[0]['events'].to_dict() != first[1]['events'].to_dict()
  for video in first:
    log = video['events']
    # A verdict for every pair in view at the end; the log round-trips.
    in_view = [i for i in range(log.num_objects) if log.in_view_at_end[i]]
    assert [(a, b) for a, b, _ in log.extrapolated] == [
        (a, b) for k, a in enumerate(in_view) for b in in_view[k + 1:]]
    assert EventLog.from_dict(
        json.loads(json.dumps(log.to_dict()))) == log
    # Drawn among scenes with a question balanced within a verdict.
    labels = {}
    future = {c.objects for c in log.future_collisions()}
    for a, b, verdict in log.extrapolated:
      labels.setdefault(verdict, set()).add((a, b) in future)
    assert any(len(v) == 2 for v in labels.values())


def _bank_shot() -> clevrer_like.Scene:
  """Cylinders in a row along x: A slides at 2.5 m/s at C, which rests 0.1
  m (surface to surface) in front of B. A reaches C after the 12 observed
  frames and pushes it into B; A itself never reaches B."""
  return clevrer_like.Scene(
      shapes=np.full(3, synthetic.SHAPES.index('cylinder'), np.int32),
      colors=np.array([1, 2, 3], np.int32), sizes=np.zeros(3, np.int32),
      xy=np.array([[-2.6, 0.5], [0.0, 0.5], [1.1, 0.5]]), yaw=np.zeros(3),
      velocity=np.array([[2.5, 0.0], [0.0, 0.0], [0.0, 0.0]]),
      enter_frame=np.zeros(3, np.int32))


def test_bank_shot_collision_that_extrapolation_misses():
  from slotformer_jax.datasets import clevrer_like_questions as questions  # pylint: disable=g-import-not-at-top
  config = dataclasses.replace(DEFLECTED, predicted_frames=12)
  scene = _bank_shot()
  sim = clevrer_like.simulate(scene, config)
  log = clevrer_like.event_log(scene, sim, config)
  observed = config.observed_frames
  assert all(c.frame >= observed for c in log.collisions)
  assert {c.objects for c in log.future_collisions()} == {(0, 1), (1, 2)}
  radii = np.array([clevrer_like.object_radius('cylinder', 'small', 1.0)] * 3)
  gap = lambda a, b: clevrer_like.extrapolated_clearance(
      sim['positions'], radii, a, b, observed, config.predicted_frames)
  # C and B rest at the end of the video: extrapolated, 0.1 m apart (a
  # near miss) -- but C is pushed into B after it.
  assert gap(1, 2) == pytest.approx(0.1, abs=0.01)
  # A's extrapolated path overlaps B (a close call), but C stops it.
  assert -0.5 < gap(0, 2) < 0.0
  assert gap(0, 1) < -0.5  # A hits C: extrapolation is right here
  # Verdicts (bin + 4 * motion): A-C a clear hit (3) closing in, met early
  # (motion 2); A-B a close call (2) closing in, met late (motion 3); B-C a
  # near miss (1) of a pair at rest (motion 0).
  hit, close_late, still_near = 3 + 8, 2 + 12, 1
  assert log.extrapolated == [(0, 1, hit), (0, 2, close_late),
                              (1, 2, still_near)]
  name = lambda a, b: questions.CHOICE_TEMPLATES['collides'].format(
      a=questions.name(log, a), b=questions.name(log, b))
  assert questions.predictive_choices(log, still_near) == ([name(1, 2)], [])
  assert questions.predictive_choices(log, close_late) == ([], [name(0, 2)])
  assert questions.predictive_choices(log, hit) == ([name(0, 1)], [])
  # No verdict has both labels here: no balanced question to ask.
  assert not clevrer_like.has_deflected_question(scene, sim, config)
  # Without C, A goes on and hits B, as extrapolation says: the collision
  # with C after the video is what decides both wrong answers.
  without = clevrer_like.simulate(scene, config, removed=1)
  assert [c[:2] for c in without['collisions']] == [(0, 2)]


def test_extrapolated_approach_and_verdict_by_hand():
  # Object 0 moves +0.1 m per frame along x towards object 1, resting 2 m
  # ahead at the last observed frame (frame 5); radii 0.5 each. Over 12
  # frames the gap falls to 2 - 1.2 - 1 = -0.2 m (a close call), first
  # within the 0.05 m margin after ceil((1 - 0.05) / 0.1) = 10 frames:
  # met late.
  t = np.arange(6, dtype=float)
  positions = np.zeros((6, 3, 2))
  positions[:, 0, 0] = 0.1 * t - 0.5
  positions[:, 1, 0] = 2.0
  positions[:, 2] = [0.0, 3.0]  # rests at (0, 3)
  radii = np.full(3, 0.5)
  gap, frame, speed, closing = clevrer_like.extrapolated_approach(
      positions, radii, 0, 1, 6, 12)
  assert gap == pytest.approx(-0.2)
  assert (frame, closing) == (10, True)
  assert speed == pytest.approx(0.1)
  assert clevrer_like.extrapolation_verdict(gap, frame, speed, closing,
                                            12) == 2 + 4 * 3
  assert clevrer_like.extrapolated_clearance(positions, radii, 0, 1, 6,
                                             12) == gap
  # Over 24 frames the centres meet (gap -1 m, a clear hit), and frame 10
  # is in the first half: motion 2.
  assert clevrer_like.extrapolation_verdict(
      *clevrer_like.extrapolated_approach(positions, radii, 0, 1, 6, 24),
      24) == 3 + 4 * 2
  # Two resting objects sqrt(13) m apart: far apart, still.
  still = clevrer_like.extrapolated_approach(positions, radii, 1, 2, 6, 12)
  assert still[0] == pytest.approx(np.sqrt(13.0) - 1.0)
  assert clevrer_like.extrapolation_verdict(*still, 12) == 0
  # Played backwards object 0 moves away: far apart, moving apart.
  apart = positions[::-1].copy()
  assert clevrer_like.extrapolation_verdict(
      *clevrer_like.extrapolated_approach(apart, radii, 0, 1, 6, 12),
      12) == 0 + 4 * 1
