"""Pictures that explain themselves and stages that say what long work
costs: the contact picture (drawn frames only, title, size), labelled grids
and attention figures, and the decoding announcement."""

from __future__ import annotations

import logging
import types

import jax.numpy as jnp
import numpy as np
from PIL import Image
import pytest

from slotformer_jax.config.defaults import contact_readout_config
from slotformer_jax.evaluation import visualize
from slotformer_jax.runtime import progress
from slotformer_jax.slot_models.base import Decoded
from slotformer_jax.stages import contact as contact_stage


def _ink(image: np.ndarray) -> bool:
  """Whether an area holds anything darker than near-white (text)."""
  return bool((image < 128).any())


def test_picture_frames_are_bounded_and_keep_both_phases():
  drawn = contact_stage.picture_frames(75, 15)
  assert len(drawn) <= contact_stage.MAX_PICTURE_COLUMNS
  assert drawn == sorted(set(drawn)) and drawn[-1] < 75
  assert drawn[0] == 0 and 15 in drawn  # the first rolled-out frame
  assert contact_stage.picture_frames(8, 4) == list(range(8))


def test_picture_title_says_threshold_decision_and_truth():
  lines = contact_stage.picture_title('video_00042 (test video 3)', 0.59,
                                      0.7, 1.0, 40, 15, 0)
  assert lines[0] == 'video_00042 (test video 3)'
  assert 'p(contact) = 0.59, threshold 0.70 -> no contact' in lines[1]
  assert 'truth: contact (onset frame 40); wrong' in lines[1]
  assert 'observed frames 0-14' in lines[2]
  right = contact_stage.picture_title('v', 0.59, 0.5, 1.0, -1, 15, 2)[1]
  assert '-> contact; truth: contact; right' in right and 'seed 2' in right
  # At the threshold itself the readout says no contact (accuracy_at: >).
  assert '-> no contact' in contact_stage.picture_title(
      'v', 0.5, 0.5, 0.0, -1, 15, 0)[1]


class _GeneratingSlotModel:
  """A slot model that 'generates' frames (decode_steps > 1) and records
  how many frames it was asked to decode."""

  label = 'Gen'
  decodes_pixels = True
  decode_steps = 16

  def __init__(self, resolution):
    self.resolution = resolution
    self.decoded_frames = []

  def decode(self, params, slots, presence=None):
    del params, presence
    self.decoded_frames.append(slots.shape[0])  # at trace time
    frames = jnp.broadcast_to(jnp.mean(slots, axis=(-1, -2))[:, None, None,
                                                              None],
                              (slots.shape[0], *self.resolution, 3))
    return Decoded(recon=frames, alpha_masks=None)


def _fake_run(tmp_path, num_frames=75, resolution=(64, 64), num_videos=3):
  readout = contact_readout_config()
  readout.num_pictures = 2
  readout.observed_frames = 15
  readout.seeds = (0,)
  rng = np.random.default_rng(0)
  videos = [{'video': rng.integers(0, 255, (num_frames, *resolution, 3),
                                   dtype=np.uint8),
             'contact_frame': np.int32(40)} for _ in range(num_videos)]
  readouts = tmp_path / 'readout'
  readouts.mkdir()
  return types.SimpleNamespace(
      config=types.SimpleNamespace(readout=readout),
      slot_model=_GeneratingSlotModel(resolution),
      stage1=types.SimpleNamespace(params={}),
      videos=lambda split: videos,
      paths=types.SimpleNamespace(readouts=str(readouts)))


def test_contact_picture_decodes_only_drawn_frames_and_is_labelled(
    tmp_path, caplog):
  run = _fake_run(tmp_path)
  rollout_slots = np.random.default_rng(1).random((3, 75, 4, 8), np.float32)
  with caplog.at_level(logging.WARNING):
    contact_stage.write_pictures(run, rollout_slots, np.array([0.9, 0.2, 0.5]),
                                 0.5, np.array([1.0, 0.0, 1.0]), seed=0,
                                 directory=run.paths.readouts)
  drawn = contact_stage.picture_frames(75, 15)
  # One compile for the drawn frames of a picture, none of the others.
  assert run.slot_model.decoded_frames == [len(drawn)]
  # Announced before the work: 2 pictures x the drawn frames x 16 passes.
  assert (f'contact pictures: Gen generates each decoded frame token by '
          f'token, 16 decoder passes a frame; {2 * len(drawn)} frames'
          in caplog.text)
  assert 'readout.num_pictures' in caplog.text
  for i in range(2):
    picture = np.asarray(Image.open(tmp_path / 'readout' / f'test_{i}.png'))
    assert not (tmp_path / 'readout' / 'test_2.png').exists()
    height, width = picture.shape[:2]
    assert width < 2000 and height < 600  # a screen shows it (was 14744)
    # The title band, the row labels and the column numbers carry text.
    assert _ink(picture[:40]) and _ink(picture[60:, :visualize._LABEL_WIDTH])


def test_labelled_tile_grid_labels_rows_and_columns():
  tile = np.zeros((10, 10, 3), np.uint8) + 200
  grid = visualize.labelled_tile_grid({'first': [tile] * 3,
                                       'second': [tile] * 3},
                                      ['t=0', 't=1', 't=2'])
  label_width = visualize._LABEL_WIDTH
  assert grid.shape == (14 + 2 * 10, label_width + 30, 3)
  header, body = grid[:14], grid[14:]
  for c in range(3):  # a number over every column
    assert _ink(header[:, label_width + 10 * c:label_width + 10 * (c + 1)])
  for r in range(2):  # a label left of every row
    assert _ink(body[10 * r:10 * (r + 1), :label_width])


def test_titled_widens_for_its_text_and_escapes_it():
  image = np.zeros((8, 8, 3), np.uint8)
  out = visualize.titled(image, ['a title much wider than the image'])
  assert out.shape[1] > 8 and out.shape[0] == 8 + 18
  assert visualize.printable('bad\x1b[31m\u00e9\nname') == (
      'bad?[31m\\xe9?name')
  assert len(visualize.printable('x' * 500)) == 160


def test_attention_figure_is_labelled(tmp_path):
  num_slots, num_frames = 3, 4
  rng = np.random.default_rng(0)
  attention = {
      'maps': rng.random((num_slots, num_frames, 8, 8, 3), np.float32),
      'predicted_recon': rng.random((8, 8, 3), np.float32),
      'predicted_views': rng.random((num_slots, 8, 8, 3), np.float32)}
  frames = rng.integers(0, 255, (num_frames + 1, 8, 8, 3), dtype=np.uint8)
  path = tmp_path / 'attention.png'
  visualize._write_attention_figure(str(path), frames, attention, 2,
                                    'val video 0')
  figure = np.asarray(Image.open(path))
  tile = 8 * 2 + 4
  grid_width = visualize._LABEL_WIDTH + (num_frames + 1) * tile
  assert figure.shape[1] >= grid_width
  assert figure.shape[0] == 3 * 14 + 4 + 14 + (num_slots + 1) * tile
  body = figure[3 * 14 + 4 + 14:]
  for row in range(num_slots + 1):  # 'input frames', 'slot i attends'
    assert _ink(body[row * tile:(row + 1) * tile, :visualize._LABEL_WIDTH])


@pytest.mark.parametrize('steps,expected', [(1, False), (64, True)])
def test_decoding_is_announced_only_when_frames_are_generated(
    caplog, steps, expected):
  model = types.SimpleNamespace(decode_steps=steps, label='M')
  with caplog.at_level(logging.WARNING):
    progress.announce_decoding('render', model, 10, '--config.x')
  assert ('render: M generates' in caplog.text) == expected
  if expected:
    assert '640 sequential passes on CPU -- minutes per video' in caplog.text


def test_target_rows_draw_flow_in_colour_and_depth_on_one_labelled_scale():
  """A SAVi reconstructing flow and depth: one row per method and target;
  depth on the first method's scale for every method, its range in the
  label; flow [-1, 1] -> [0, 1] colours."""
  from slotformer_jax import targets as targets_lib  # pylint: disable=g-import-not-at-top
  from slotformer_jax.evaluation import visualize  # pylint: disable=g-import-not-at-top
  rng = np.random.default_rng(0)
  shape = (3, 4, 4)
  out = {f'{m} targets': {
      'flow': rng.uniform(-1, 1, shape + (3,)).astype(np.float32),
      'depth': rng.uniform(low, low + 1, shape + (1,)).astype(np.float32)}
         for m, low in (('slotformer', 1.0), ('copy_last', 3.0))}
  labels = {'slotformer': 'SlotFormer', 'copy_last': 'copy-last'}
  rows = visualize.target_rows(targets_lib.of(('flow', 'depth')), out,
                               ['slotformer', 'copy_last'], labels)
  low, high = targets_lib.depth_range(out['slotformer targets']['depth'])
  scale = f'\n{low:.2g}..{high:.2g}'
  flow, depth = targets_lib.TARGETS['flow'], targets_lib.TARGETS['depth']
  assert list(rows) == [
      f'SlotFormer {flow.label}', f'copy-last {flow.label}',
      f'SlotFormer {depth.label}{scale}', f'copy-last {depth.label}{scale}']
  for picture in rows.values():
    assert picture.shape == shape + (3,)
    assert 0.0 <= picture.min() and picture.max() <= 1.0
  np.testing.assert_allclose(rows[f'SlotFormer {flow.label}'],
                             (out['slotformer targets']['flow'] + 1) / 2)
  # copy-last's depth lies above SlotFormer's range: white on that scale.
  assert np.all(rows[f'copy-last {depth.label}{scale}'] == 1.0)

  # With the data's flow and depth: their rows first, depth on the data's
  # scale for every row.
  truth = {'flow': rng.uniform(-1, 1, shape + (3,)).astype(np.float32),
           'depth': rng.uniform(2.0, 4.0, shape + (1,)).astype(np.float32)}
  rows = visualize.target_rows(targets_lib.of(('flow', 'depth')), out,
                               ['slotformer', 'copy_last'], labels, truth)
  low, high = targets_lib.depth_range(truth['depth'])
  scale = f'\n{low:.2g}..{high:.2g}'
  assert list(rows) == [
      flow.label, f'SlotFormer {flow.label}', f'copy-last {flow.label}',
      f'{depth.label}{scale}', f'SlotFormer {depth.label}{scale}',
      f'copy-last {depth.label}{scale}']
  np.testing.assert_allclose(rows[flow.label], (truth['flow'] + 1) / 2)
  grey = rows[f'{depth.label}{scale}']
  assert grey.min() == 0.0 and grey.max() == 1.0
  # SlotFormer's depth (1..2) lies below the data's range: black.
  assert np.all(rows[f'SlotFormer {depth.label}{scale}'] == 0.0)
