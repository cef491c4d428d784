"""Tests of the embedded Physion-style contact (OCP) generator."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slotformer_jax.data.write.generate import Output
from slotformer_jax.datasets import synthetic_contact as contact
from slotformer_jax.datasets import synthetic

TINY = contact.ContactConfig(resolution=(16, 16), num_frames=24,
                                  observed_frames=8, supersample=1,
                                  num_train=2, num_readout_train=2,
                                  num_readout_val=2, num_readout_test=2)
SPHERE = synthetic.SHAPES.index('sphere')
SMALL = synthetic.SIZES.index('small')


def _head_on_scene(patient_x: float) -> synthetic.Scene:
  """A small yellow sphere at (patient_x, 1); a small red sphere rolling
  straight up the y axis from (0, -2.4) at 4 m/s."""
  return synthetic.Scene(
      shapes=np.array([SPHERE, SPHERE], np.int32),
      colors=np.array([contact.PATIENT_COLOR, contact.AGENT_COLOR], np.int32),
      sizes=np.array([SMALL, SMALL], np.int32),
      xy=np.array([[patient_x, 1.0], [0.0, -2.4]]),
      yaw=np.zeros(2),
      launch_velocity=np.array([0.0, 4.0]))


def test_known_contact_and_its_onset():
  out = contact.simulate(_head_on_scene(0.0), TINY, render=False)
  assert bool(out['contact'])
  onset = int(out['contact_frame'])
  # Touching means centre distance = 2 radii; the gap before is closed at
  # the onset frame and open one frame earlier.
  radius = synthetic.SIZE_RADII[SMALL]
  agent, patient = int(out['agent_index']), int(out['patient_index'])
  gap = np.linalg.norm(out['positions'][:, agent, :2]
                       - out['positions'][:, patient, :2], axis=-1) - 2 * radius
  assert gap[onset - 1] > 0.0
  assert gap[:onset].min() > 0.0
  # Frame-rate resolution: within one frame's travel (~0.2 m) of touching.
  assert gap[onset] < 0.25
  # The patient starts moving only after the hit.
  speed = np.linalg.norm(out['velocities'][:, patient], axis=-1)
  assert speed[:onset].max() < 1e-3 and speed[onset:].max() > 0.5
  # Rolling friction slows the agent: 3.4 m at 4 m/s takes > 0.5 s (10 frames).
  assert 10 <= onset <= 20


def test_known_miss():
  out = contact.simulate(_head_on_scene(2.0), TINY, render=False)
  assert not bool(out['contact'])
  assert int(out['contact_frame']) == -1


def test_generator_is_deterministic_and_labels_as_designed():
  first = [contact.generate_video(TINY, 'readout_val', i) for i in range(2)]
  again = contact.generate_video(TINY, 'readout_val', 1)
  for key, value in first[1].items():
    np.testing.assert_array_equal(value, again[key], err_msg=key)
  other_seed = contact.generate_video(
      dataclasses.replace(TINY, seed=1), 'readout_val', 1)
  assert not np.array_equal(other_seed['video'], again['video'])
  # Video i wants label i % 2; contacts only after the observed frames.
  assert [bool(v['contact']) for v in first] == [False, True]
  assert int(first[1]['contact_frame']) >= TINY.observed_frames
  video = first[1]
  assert video['video'].shape == (24, 16, 16, 3)
  assert video['colors'][int(video['agent_index'])] == contact.AGENT_COLOR
  assert video['colors'][int(video['patient_index'])] == contact.PATIENT_COLOR


def test_bad_config():
  with pytest.raises(ValueError, match='observed_frames'):
    contact.ContactConfig(num_frames=8, observed_frames=8)


def test_written_dataset_reads_back(tmp_path):
  from slotformer_jax.data import sources  # pylint: disable=g-import-not-at-top
  config = dataclasses.replace(TINY, num_train=1, num_readout_train=2,
                               num_readout_val=0, num_readout_test=0)
  path = contact.generate(config, Output(tmp_path))
  source = sources.TfdsVideoSource(path, 'readout_train')
  assert len(source) == 2
  item = source[1]
  expected = contact.generate_video(config, 'readout_train', 1)
  for key, value in expected.items():
    np.testing.assert_array_equal(item[key], value, err_msg=key)
  assert contact.generate(config, Output(tmp_path)) == path


def test_parallel_build_writes_the_serial_videos_in_order(tmp_path):
  from slotformer_jax.data import sources  # pylint: disable=g-import-not-at-top
  # 9 videos in chunks of 4 over 2 worker processes: out-of-order chunks
  # would put a video at the wrong record.
  config = dataclasses.replace(TINY, num_train=0, num_readout_train=9,
                               num_readout_val=0, num_readout_test=0)
  path = contact.generate(config, Output(tmp_path, 2))
  source = sources.TfdsVideoSource(path, 'readout_train')
  assert len(source) == 9
  for index in range(9):
    expected = contact.generate_video(config, 'readout_train', index)
    for key, value in expected.items():
      np.testing.assert_array_equal(source[index][key], value,
                                    err_msg=f'{index} {key}')


def test_side_launch_moves_across_the_view():
  side = dataclasses.replace(TINY, launch_side='side')
  videos = [contact.generate_video(side, 'readout_test', i) for i in range(4)]
  assert [bool(v['contact']) for v in videos] == [False, True, False, True]
  for video in videos:
    agent, patient = int(video['agent_index']), int(video['patient_index'])
    start = video['positions'][0, agent]
    # From the left / right edge, on the side away from the patient, at its
    # depth, moving mostly across the view (x) rather than along it (y).
    assert abs(start[0]) == pytest.approx(contact.SIDE_LAUNCH_X)
    assert np.sign(start[0]) != np.sign(video['positions'][0, patient, 0])
    assert abs(start[1] - video['positions'][0, patient, 1]) <= (
        contact.SIDE_LAUNCH_DEPTH_NOISE + 1e-6)
    vx, vy = video['velocities'][0, agent, :2]
    assert abs(vx) > abs(vy)
    if bool(video['contact']):
      assert int(video['contact_frame']) >= side.observed_frames
  again = contact.generate_video(side, 'readout_test', 3)
  for key, value in videos[3].items():
    np.testing.assert_array_equal(value, again[key], err_msg=key)
  assert side.slug != TINY.slug
  with pytest.raises(ValueError, match='launch_side'):
    dataclasses.replace(TINY, launch_side='top')


def test_front_launch_datasets_are_unchanged_by_the_option():
  # The slug of the default (front) config, as before `launch_side` existed:
  # cached datasets keep their names (the generated videos are unchanged,
  # checked against the previous generator when the option was added).
  config = contact.ContactConfig(resolution=(16, 16), supersample=1,
                                      num_frames=12, observed_frames=6)
  assert config.slug == 'r16x16_t12_obs6_d1-2_s0_n1000-400-100-200_19cd5100'


def _bank_scene(bumper_size: int, patient_x: float) -> synthetic.Scene:
  """Row 0 a small yellow sphere at (patient_x, 0), row 1 a sphere bumper
  of ``bumper_size`` at (0, 0), a small red sphere rolling along +x from
  (-2.6, 0) at 4 m/s: straight at the bumper, which is straight in front
  of the patient."""
  return synthetic.Scene(
      shapes=np.array([SPHERE] * 3, np.int32),
      colors=np.array([contact.PATIENT_COLOR, contact.DISTRACTOR_COLORS[0],
                       contact.AGENT_COLOR], np.int32),
      sizes=np.array([SMALL, bumper_size, SMALL], np.int32),
      xy=np.array([[patient_x, 0.0], [0.0, 0.0], [-2.6, 0.0]]),
      yaw=np.zeros(3),
      launch_velocity=np.array([4.0, 0.0]))


BANK = dataclasses.replace(TINY, launch_side='side', scenario='bank')


def test_bank_labels_on_simulated_cases():
  # The agent hits the (heavier) bumper head-on; the bumper goes on and
  # hits the patient, the agent never does: the patient moved, yet the
  # label (agent touches patient) is False.
  large = synthetic.SIZES.index('large')
  out = contact.simulate(_bank_scene(large, 1.4), BANK, render=False)
  bump = int(out['bump_frame'])
  radius = synthetic.SIZE_RADII
  gap = np.linalg.norm(out['positions'][:, 2, :2] - out['positions'][:, 1, :2],
                       axis=-1) - radius[SMALL] - radius[large]
  assert gap[:bump].min() > 0.0 and gap[bump] < 0.25
  # 2.6 m - 1.3 m of radii at ~4 m/s, slowed by rolling friction: frame 8.
  assert 7 <= bump <= 9
  patient_speed = np.linalg.norm(out['velocities'][:, 0], axis=-1)
  assert patient_speed[:bump].max() < 1e-3 and patient_speed.max() > 0.2
  assert out['positions'][-1, 2, 0] < -1.0  # the light agent bounced back
  assert not bool(out['contact']) and int(out['contact_frame']) == -1
  # The direct scenario reports no bump_frame (its datasets are unchanged).
  assert 'bump_frame' not in contact.simulate(
      _head_on_scene(0.0), TINY, render=False)


def test_bank_generator_is_deterministic_and_labels_as_designed():
  videos = [contact.generate_states(BANK, 'readout_val', i) for i in range(4)]
  assert [bool(v['contact']) for v in videos] == [False, True, False, True]
  for video in videos:
    bump = int(video['bump_frame'])
    # The bounce happens after the observed frames, and a contact after it.
    assert bump >= BANK.observed_frames
    if bool(video['contact']):
      assert int(video['contact_frame']) > bump
    agent = int(video['agent_index'])
    assert abs(video['positions'][0, agent, 0]) == pytest.approx(
        contact.SIDE_LAUNCH_X)
  rendered = contact.generate_video(BANK, 'readout_val', 3)
  for key, value in videos[3].items():
    np.testing.assert_array_equal(value, rendered[key], err_msg=key)
  again = contact.generate_video(BANK, 'readout_val', 3)
  for key, value in rendered.items():
    np.testing.assert_array_equal(value, again[key], err_msg=key)
  other = contact.generate_states(dataclasses.replace(BANK, seed=1),
                                  'readout_val', 3)
  assert not np.array_equal(other['positions'], videos[3]['positions'])
  assert BANK.slug != dataclasses.replace(BANK, scenario='direct').slug
  with pytest.raises(ValueError, match='scenario'):
    dataclasses.replace(BANK, scenario='pool')
  with pytest.raises(ValueError, match='bank'):
    dataclasses.replace(BANK, launch_side='front')


def test_bank_config_variant():
  from configs import synthetic_contact  # pylint: disable=g-import-not-at-top
  bank = contact.config_from_data_config(
      synthetic_contact.get_config('bank').data)
  assert (bank.scenario, bank.launch_side, bank.seed) == ('bank', 'side', 2)
  side = contact.config_from_data_config(
      synthetic_contact.get_config('side').data)
  assert (side.scenario, side.launch_side, side.seed) == ('direct', 'side', 1)
