"""SAVi's random resized crop (data/augment.py) and SAVi's training input
with it: the geometry of every field, the draw, and the batches."""

from __future__ import annotations

import numpy as np
import pytest

from slotformer_jax import targets
from slotformer_jax.data import augment
from slotformer_jax.data import flow_depth
from slotformer_jax.data import pipeline

T, H, W = 2, 32, 40


def _clip():
  """A bright rectangle (rows 8..16, columns 10..22) on black, its id 1,
  its box, a flow of (2, -3) pixels on it, depth 4 on it and 9 elsewhere;
  a second box outside the crops below, a no-track box."""
  video = np.zeros((T, H, W, 3), np.uint8)
  video[:, 8:16, 10:22] = 200
  seg = np.zeros((T, H, W), np.uint8)
  seg[:, 8:16, 10:22] = 1
  boxes = np.zeros((T, 3, 4), np.float32)
  boxes[:, 0] = (8 / H, 10 / W, 16 / H, 22 / W)
  boxes[:, 1] = (28 / H, 34 / W, 31 / H, 39 / W)  # bottom right corner
  flow = np.zeros((T, H, W, 2), np.float32)
  flow[:, 8:16, 10:22] = (2.0, -3.0)
  distance = np.full((T, H, W, 1), 9.0, np.float32)
  distance[:, 8:16, 10:22] = 4.0
  return {'video': video, 'segmentations': seg, 'boxes': boxes,
          'backward_flow': flow, 'depth': np.log1p(distance),
          'num_instances': np.int32(1)}


def test_the_whole_frame_is_the_clip_itself():
  clip = _clip()
  out = augment.crop_clip(clip, (0, 0, H, W))
  for key, value in clip.items():
    np.testing.assert_allclose(out[key], value, rtol=1e-6, atol=1e-6)
    assert out[key].dtype == np.asarray(value).dtype, key


def test_a_crop_moves_boxes_masks_flow_and_depth_together():
  """The crop (top 4, left 6, 16 x 20) resized to 32 x 40 doubles every
  length: the rectangle's box, its mask, and its flow vector (row x 32 /
  16, column x 40 / 20); depth keeps its values; a box left outside is
  SAVi's no-track box, a no-track box stays one."""
  box = (4, 6, 16, 20)
  out = augment.crop_clip(_clip(), box)
  ymin, xmin, ymax, xmax = out['boxes'][0, 0]
  np.testing.assert_allclose(out['boxes'][0, 0],
                             ((8 - 4) / 16, (10 - 6) / 20, (16 - 4) / 16,
                              min(22 - 6, 20) / 20), atol=1e-6)
  assert out['boxes'][:, 1].tolist() == [[0.0] * 4] * T  # left the crop
  assert out['boxes'][:, 2].tolist() == [[0.0] * 4] * T  # stays no-track
  # The mask is the box: rows ymin * H .. ymax * H, columns likewise.
  rows, cols = np.nonzero(out['segmentations'][0] == 1)
  assert (rows.min(), rows.max() + 1) == (round(ymin * H), round(ymax * H))
  assert (cols.min(), cols.max() + 1) == (round(xmin * W), round(xmax * W))
  # Inside the object: its flow scaled by (32 / 16, 40 / 20), its depth.
  mask = np.pad(out['segmentations'] == 1, ((0, 0), (1, 1), (1, 1)))
  inside = (mask[:, 1:-1, 1:-1] & mask[:, :-2, 1:-1] & mask[:, 2:, 1:-1]
            & mask[:, 1:-1, :-2] & mask[:, 1:-1, 2:])  # away from its edge
  flows = out['backward_flow'][inside]
  np.testing.assert_allclose(flows, np.broadcast_to([4.0, -6.0],
                                                    flows.shape), atol=1e-5)
  np.testing.assert_allclose(np.expm1(out['depth'][inside]), 4.0,
                             rtol=1e-5)
  assert (out['video'][inside] == 200).all()
  # A point and where it moves to map through the same crop: the flow of
  # the output pixel is the difference of the mapped points.
  point = np.array([10.0, 12.0])
  moved = point + np.array([2.0, -3.0])

  def mapped(p):
    return (p - (4, 6)) * (H / 16, W / 20)

  np.testing.assert_allclose(mapped(moved) - mapped(point), (4.0, -6.0))


def test_flow_in_the_contract_cannot_be_cropped():
  clip = flow_depth.to_contract(_clip())
  assert 'flow' in clip and 'backward_flow' not in clip
  with pytest.raises(ValueError, match="crop 'backward_flow'"):
    augment.crop_clip(clip, (0, 0, H, W))


def test_draws_keep_savi_plus_plus_s_bounds():
  crop = augment.RandomResizedCrop()
  rng = np.random.default_rng(0)
  boxes = [crop.sample(rng, 64, 64) for _ in range(500)]
  for top, left, height, width in boxes:
    assert 0 <= top and top + height <= 64 and 0 <= left
    assert left + width <= 64
    assert height * width >= 0.75 * 64 * 64
    assert 3 / 4 - 0.05 <= width / height <= 4 / 3 + 0.05
  assert len(set(boxes)) > 100  # crops vary
  assert (0, 0, 64, 64) in boxes or any(b[2] * b[3] > 0.95 * 64 * 64
                                        for b in boxes)
  # Nothing but the whole frame covers all of it.
  whole = augment.RandomResizedCrop(min_object_covered=1.0)
  assert whole.sample(rng, 64, 64) == (0, 0, 64, 64)
  again = [crop.sample(np.random.default_rng(0), 64, 64) for _ in range(2)]
  assert again[0] == again[1] == boxes[0]


def test_crop_settings_are_checked_in_one_line():
  import ml_collections  # pylint: disable=g-import-not-at-top
  section = ml_collections.ConfigDict(dict(
      enabled=True, min_object_covered=1.5, aspect_ratio_range=(2.0, 1.0),
      area_range=(0.5, 1.5), max_attempts=0))
  problems = augment.config_problems(section, 'savi.random_resized_crop')
  assert len(problems) == 4 and all('savi.random_resized_crop.' in p
                                    for p in problems)
  assert augment.config_problems(None, 'x') == []


class _Videos:
  """Eight clips' worth of videos with flows (a list source)."""

  def __init__(self):
    rng = np.random.default_rng(0)
    self.items = []
    for _ in range(8):
      item = _clip()
      item['video'] = rng.integers(0, 256, (T * 3, H, W, 3), np.uint8)
      item['backward_flow'] = rng.normal(size=(T * 3, H, W, 2)).astype(
          np.float32)
      item['depth'] = np.log1p(rng.uniform(1, 9, (T * 3, H, W, 1))).astype(
          np.float32)
      item['boxes'] = np.repeat(item['boxes'][:1], T * 3, axis=0)
      del item['segmentations']
      self.items.append(item)

  def __len__(self):
    return len(self.items)

  def __getitem__(self, index):
    return self.items[index]


def _savi_part(enabled):
  from slotformer_jax.config.defaults import base_config  # pylint: disable=g-import-not-at-top
  from slotformer_jax.slot_models.savi import Savi  # pylint: disable=g-import-not-at-top
  config = base_config()
  config.data.resolution = (H, W)
  config.savi.targets = ('flow', 'depth')
  config.savi.random_resized_crop.enabled = enabled
  return Savi(config).parts[0]


def test_savi_s_training_input_with_the_crop():
  """Off (the default): SAVi reads `flow` and `depth` as served, no
  transform. On: it reads the backward flow in pixels and each clip is
  cropped, then its flow coloured; the batch of a step is the same
  whichever host builds which rows."""
  off, on = _savi_part(False), _savi_part(True)
  assert off.transform is None and off.batch_fields == ('video', 'flow',
                                                        'depth')
  assert on.batch_fields == ('video', 'backward_flow', 'depth')
  source = _Videos()
  kwargs = dict(batch_size=4, clip_length=T, seed=3,
                fields=on.batch_fields, transform=on.transform)
  batch = pipeline.make_train_batch(source, 5, **kwargs)
  assert set(batch) == {'video', 'flow', 'depth'}
  assert batch['flow'].shape == (4, T, H, W, 3)
  assert batch['flow'].dtype == np.float32 and batch['video'].dtype == np.uint8
  assert np.abs(batch['flow']).max() <= 1.0
  plain = pipeline.make_train_batch(source, 5, **{**kwargs,
                                                  'transform': None})
  assert not np.array_equal(plain['video'], batch['video'])  # cropped
  again = pipeline.make_train_batch(source, 5, **kwargs)
  for key in batch:
    np.testing.assert_array_equal(batch[key], again[key])
  halves = [pipeline.make_train_batch(
      source, 5, **{**kwargs, 'batch_size': 2}, process_index=p,
      process_count=2) for p in range(2)]
  for key in batch:
    np.testing.assert_array_equal(
        batch[key], np.concatenate([h[key] for h in halves]))
  # The crop is the one its row's generator draws.
  videos, fractions = pipeline._train_plan(3, 5, 4, len(source))  # pylint: disable=protected-access
  row = 2
  item = source[int(videos[row])]
  start = int(fractions[row] * (len(item['video']) - T + 1))
  clip = {key: item[key][start:start + T] for key in on.batch_fields}
  want = flow_depth.to_contract(augment.RandomResizedCrop()(
      clip, pipeline.transform_rng(3, 5, row)))
  for key in batch:
    np.testing.assert_array_equal(batch[key][row], want[key])
  assert targets.FLOW.field in want
