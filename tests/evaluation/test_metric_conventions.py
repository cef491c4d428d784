"""The official metric conventions as options ."""

import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.datasets.clevrer import boxes_from_masks
from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import metrics
from slotformer_jax.modules.decoders import DecodedSlots


def test_absent_id_counts_zero_in_the_official_convention():
  # Ground truth: id 1 absent, id 2 = left half; slot 0 = left half.
  true_ids = np.zeros((1, 1, 4, 4), np.int32)
  true_ids[..., :2] = 2
  pred_ids = np.ones((1, 1, 4, 4), np.int32)
  pred_ids[..., :2] = 0
  skip = metrics.fg_miou(true_ids, pred_ids, 3, 2)
  zero = metrics.fg_miou(true_ids, pred_ids, 3, 2, absent_ids='zero')
  np.testing.assert_allclose(skip.value, [1.0])
  np.testing.assert_allclose(zero.value, [0.5])  # (1 + 0) / 2, as official
  # Ids above the largest present one never count.
  id_one = np.where(true_ids == 2, 1, 0)
  np.testing.assert_allclose(
      metrics.fg_miou(id_one, pred_ids, 3, 2, absent_ids='zero').value, [1.0])
  with pytest.raises(ValueError, match='absent_ids'):
    metrics.hungarian_mean_iou(np.zeros((1, 2, 2)), np.ones((1, 2), bool),
                               absent_ids='nan')


def test_stored_boxes_convert_to_the_mask_boxes():
  rng = np.random.default_rng(0)
  masks = rng.random((3, 4, 12, 10)) > 0.9  # [T, O, H, W]
  masks[0, 1] = False  # an empty mask
  stored, visible = boxes_from_masks(masks)
  boxes, valid = metrics.boxes_from_normalized(stored, visible, height=12,
                                               width=10)
  expected, expected_valid = metrics.masks_to_boxes(masks)
  np.testing.assert_array_equal(valid, expected_valid)
  np.testing.assert_array_equal(boxes, expected)


def _one_frame_step(gt_boxes):
  """AR of one frame: two overlapping objects; object 1 hidden behind 2
  except two pixel columns, the slots get the visible parts exactly."""
  h = w = 8
  full_1 = np.zeros((h, w), bool)
  full_1[2:6, 0:5] = True
  full_2 = np.zeros((h, w), bool)
  full_2[2:6, 2:7] = True
  ids = np.where(full_2, 2, np.where(full_1, 1, 0))
  alpha = np.stack([ids == 0, ids == 1, ids == 2]).astype(np.float32)
  alpha = jnp.asarray(alpha)[None, :, :, :, None]  # [1, N=3, H, W, 1]
  decoded = DecodedSlots(recon=jnp.zeros((1, h, w, 3)),
                         rgb=jnp.zeros((1, 3, h, w, 3)), alpha_masks=alpha,
                         segmentation=jnp.zeros((1, h, w), jnp.int32))
  boxes = None
  if gt_boxes:
    stored, visible = boxes_from_masks(np.stack([full_1, full_2])[None])
    boxes = {'boxes': jnp.asarray(stored), 'visible': jnp.asarray(visible)}
  out = evaluate._frame_step_metrics(
      decoded, jnp.zeros((1, h, w, 3)), jnp.asarray(ids)[None], boxes,
      names=('ar',), num_true=3, num_slots=3, lpips_fn=None,
      background_threshold=None)
  return float(out['ar'][0][0])


def test_ar_ground_truth_from_full_masks_differs_from_the_id_map():
  # From the id map both objects' boxes equal the slots' boxes: recall 1.
  assert _one_frame_step(gt_boxes=False) == 1.0
  # Object 1's full box (area 4 x 3 in torchvision's convention) holds its
  # visible box (1 x 3) at IoU 0.25 < 0.5: the official ground truth misses
  # it.
  assert _one_frame_step(gt_boxes=True) == 0.5


def test_official_background_post_processing():
  alpha = np.full((1, 2, 2, 2), 0.3, np.float32)  # [B, N, H, W]
  alpha[0, 0, 0, 0] = 0.45  # slot 0 holds the largest alpha: slot 1 is bg
  alpha[0, 1, 0, 0] = 0.1
  plain = metrics.segmentation_from_alpha_masks(alpha)
  post = metrics.segmentation_from_alpha_masks(
      alpha, bg_threshold=metrics.SLOTFORMER_BG_THRESHOLD)
  assert plain[0, 1, 1] == 0  # tie -> lowest id
  np.testing.assert_array_equal(post[0], [[1, 1], [1, 1]])
