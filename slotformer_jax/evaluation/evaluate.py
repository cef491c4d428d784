"""Video-prediction evaluation on held-out videos, for any slot model.

Protocol (the paper's): observe the slots of the first `burn_in` frames,
roll the dynamics model out for `rollout_steps` frames, decode the predicted
slots with the frozen slot model and compare every decoded frame and its
slot masks with the ground truth; metrics (`rollout_metrics`, registered by
name) per rollout step, averaged over videos per step, then over steps.
Methods: the dynamics models (every trained one of the registry:
`slotformer`, `slot_lstm`, ...), `copy_last` (no dynamics) and
`<slot model>_reconstruction` (the slot model's own slots of the future
decoded: a reference, not a prediction); also the slot model's own
segmentation of the videos. docs/evaluation.md says what each number is.

The slot model arrives as a `slot_models.base.SlotModel`, the dynamics
models as (module, params, step), every one trained: evaluation never builds
or loads a model, so it imports no training code. A slot model that decodes
no pixels is scored on its masks only, and the metrics say so.
"""

from __future__ import annotations

import csv
import functools
import logging
import math
import os
import time
from collections.abc import Callable
from typing import Any, Protocol

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import datasets
from slotformer_jax import inference
from slotformer_jax.config.sections import DYNAMICS
from slotformer_jax.data import pipeline
from slotformer_jax.data.pipeline import ClipSource
from slotformer_jax.errors import ConfigError
from slotformer_jax.evaluation import metrics as metrics_lib
from slotformer_jax.evaluation import rollout_metrics
from slotformer_jax.files import atomic_text
from slotformer_jax.files import write_json_atomic
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.runtime import precision
from slotformer_jax.runtime import progress
from slotformer_jax.runtime import sharding

logger = logging.getLogger(__name__)

SEGMENTATION_FIELD = 'segmentations'
# The dataset's per-object boxes (from each object's full mask) and whether
# each object is visible: AR's official ground truth.
BOX_FIELDS = ('boxes', 'visible')


class SlotDecoder(Protocol):
  """What evaluation needs of a slot model (see slot_models/base.py)."""

  name: str
  label: str
  reference_method: str
  slot_shape: tuple[int, int]
  mask_source: str
  decodes_pixels: bool
  decode_steps: int  # sequential decoder passes per frame

  def decode(self, params: Any, slots: jax.Array) -> Any:
    """slots [..., N, D] -> .recon [..., H, W, 3], .alpha_masks [..., N, H,
    W, 1], .rgb [..., N, H, W, 3] or None."""

  def observe(self, params: Any, slots: jax.Array, video: jax.Array,
              carry: Any) -> tuple[jax.Array, jax.Array | None, Any]:
    """-> (alpha_masks [B, T, N, H, W], recon [B, T, H, W, 3] or None,
    carry)."""


def predicted_segmentation(decoded, bg_threshold: float | None = None
                           ) -> jax.Array:
  """Decoded frames (alpha_masks [..., N, H, W, 1]) -> int32 [..., H, W]:
  the slot with the largest alpha per pixel (`bg_threshold`: the official
  post-processing, see `metrics.segmentation_from_alpha_masks`)."""
  return metrics_lib.segmentation_from_alpha_masks(
      decoded.alpha_masks[..., 0], bg_threshold=bg_threshold)


def num_true_ids(max_instances: int) -> int:
  """Ground-truth segmentation ids, background (0) included, of a dataset
  whose largest instance id is `max_instances` (`data.max_instances`)."""
  return int(max_instances) + 1


def _frame_step_metrics(decoded, frames: jax.Array, segmentation: jax.Array,
                        gt_boxes=None,
                        *, names: tuple[str, ...], num_true: int,
                        num_slots: int, lpips_fn: Callable | None,
                        background_threshold: float | None,
                        lpips_target: Any = None):
  """Metrics of one rollout step for a batch.

  decoded: DecodedSlots with leading [B] (recon in [0, 1]);
  frames: float [B, H, W, 3] in [0, 1]; segmentation: int [B, H, W];
  gt_boxes: None (AR's ground-truth boxes from the id map) or the dataset's
  per-object boxes ('boxes' [B, M, 4], 'visible' [B, M]).
  lpips_target: `lpips_fn.features(frames)`, computed once for all methods
  (None: LPIPS computes the frames' features itself).
  Returns {name: (value [B], valid [B])} of the registered metrics of
  `names` (`rollout_metrics`); a metric with an `on_host` step returns
  what that step reads (FG-mIoU: the IoU matrix [B, C-1, K] with 'present'
  [B, C-1], matched on the host).
  """
  masks = rollout_metrics.needing(names, rollout_metrics.MASKS)
  pred_ids = true_ids = table = None
  if masks:
    pred_ids = predicted_segmentation(decoded,
                                      bg_threshold=background_threshold)
    true_ids = segmentation.astype(jnp.int32)
    table = metrics_lib.contingency_table(
        true_ids[:, None], pred_ids[:, None], num_true, num_slots)
  step = rollout_metrics.Step(
      decoded=decoded, frames=frames, true_ids=true_ids, pred_ids=pred_ids,
      table=table, gt_boxes=gt_boxes, num_true=num_true, num_slots=num_slots,
      lpips_fn=lpips_fn, lpips_target=lpips_target)
  out = {}
  for name in rollout_metrics.ordered(names):
    scored = rollout_metrics.get(name).fn(step)
    if scored is not None:
      out[name] = scored
  return out


def uses_dataset_boxes(eval_config: ml_collections.ConfigDict,
                       names: tuple[str, ...]) -> bool:
  """Whether AR reads the dataset's per-object boxes (see the config)."""
  kind = eval_config.ar_gt_boxes
  if kind not in ('segmentation', 'object_masks'):
    raise ValueError("evaluation.ar_gt_boxes must be 'segmentation' or "
                     f"'object_masks', got {kind!r}")
  return 'ar' in names and kind == 'object_masks'


def make_rollout_evaluator(eval_config: ml_collections.ConfigDict, mesh: Mesh,
                           names: tuple[str, ...],
                           dynamics_modules: dict[str, Any],
                           slot_model: SlotDecoder, *, burn_in: int,
                           num_true: int, compute_dtype: str):
  """Jitted (dynamics_params, slot_params, batch, lpips_params) -> metrics.

  eval_config: the `evaluation` section (rollout_steps, background
  threshold, AR's boxes); dynamics_modules: {name: module} of the dynamics
  models rolled out after `burn_in` frames; num_true: ground-truth ids
  (`num_true_ids`).
  dynamics_params: {name: params} for every name in `dynamics_modules`;
  slot_params: the slot model's (`slot_model.decode` takes them).
  lpips_params: `metrics_lib.LpipsVgg.params` (None: LPIPS is not scored).
  The VGG's weights are an argument: closed over, they would be baked into
  the program as constants (59 MB; slower to compile, and in every
  compile-cache entry).
  batch: 'slots' [B, burn_in + R, N, D], 'video' uint8 [B, burn_in + R, H,
  W, 3] and, when an object metric is asked for, 'segmentations' [B,
  burn_in + R, H, W]. Returns {method: {name: (value [R, B], valid [R, B])}}
  (fg_miou: (iou, present)).
  """
  models_by_name = dict(dynamics_modules)
  rollout = eval_config.rollout_steps
  needs_segmentation = bool(rollout_metrics.needing(
      names, rollout_metrics.MASKS))
  boxes_from_dataset = uses_dataset_boxes(eval_config, names)
  # bfloat16: rollouts and decoding compute in it, metrics in float32.
  in_compute_dtype = functools.partial(precision.with_compute_dtype,
                                       compute_dtype=compute_dtype)
  reference = slot_model.reference_method

  def evaluate_batch(dynamics_params, slot_params, batch, lpips_params):
    lpips_fn = (None if lpips_params is None
                else metrics_lib.LpipsVgg(lpips_params))
    step_metrics = functools.partial(
        _frame_step_metrics, names=names,
        num_true=num_true, num_slots=slot_model.slot_shape[0],
        lpips_fn=lpips_fn,
        background_threshold=eval_config.background_threshold)
    history = batch['slots'][:, :burn_in]
    predictions = {
        name: in_compute_dtype(functools.partial(
            inference.rollout_slots, model=model, num_steps=rollout))(
                dynamics_params[name], history)
        for name, model in models_by_name.items()}
    predictions[reference] = batch['slots'][:, burn_in:burn_in + rollout]
    frames = batch['video'][:, burn_in:burn_in + rollout]
    if needs_segmentation:
      segmentation = batch[SEGMENTATION_FIELD][:, burn_in:burn_in + rollout]
    else:  # unused placeholder of the right leading shape
      segmentation = jnp.zeros(frames.shape[:2], jnp.int32)
    boxes = None
    if boxes_from_dataset:
      boxes = {field: batch[field][:, burn_in:burn_in + rollout]
               for field in BOX_FIELDS}
    time_major = lambda x: jnp.swapaxes(x, 0, 1)
    # The slot model's parameters are an argument of the wrapped decode, so
    # they are cast too: bound in a partial they would stay float32 and the
    # decoder would mix bfloat16 activations with float32 kernels.
    decode_in_dtype = in_compute_dtype(slot_model.decode)
    decode = lambda slots: decode_in_dtype(slot_params, slots)
    # Copy-last predicts the same slots at every step: decode them once.
    copied = decode(inference.copy_last_rollout(history, 1)[:, 0])
    with_lpips = lpips_fn is not None and 'lpips' in names

    def one_step(inputs):
      """All methods at one rollout step: the ground-truth frames' LPIPS
      features are computed once and shared by every method."""
      index, (slots_by_method, frame, seg, gt_boxes) = inputs
      progress.tick(index, slot_model.decode_steps)
      frame = model_to_unit(frames_to_model(frame))
      target = lpips_fn.features(frame) if with_lpips else None
      score = lambda decoded: step_metrics(decoded, frame, seg, gt_boxes,
                                           lpips_target=target)
      out = {method: score(decode(slots))
             for method, slots in slots_by_method.items()}
      out['copy_last'] = score(copied)
      return out

    # lax.map keeps one step's decoded frames in memory at a time.
    return jax.lax.map(one_step, (jnp.arange(frames.shape[1]), (
        {method: time_major(slots) for method, slots in predictions.items()},
        time_major(frames), time_major(segmentation),
        jax.tree.map(time_major, boxes))))

  replicated = sharding.replicated_sharding(mesh)
  return jax.jit(evaluate_batch,
                 in_shardings=(replicated, replicated,
                               sharding.batch_sharding(mesh), replicated))


def make_quality_evaluator(num_true: int, mesh: Mesh,
                           slot_model: SlotDecoder,
                           with_segmentation: bool = True):
  """Jitted quality of the slot model's account of a chunk of real frames.

  (slot_params, slots [B, T, N, D], video uint8 [B, T, H, W, 3],
  segmentations [B, T, H, W] (ignored without `with_segmentation`),
  frame_valid bool [B, T], carry) -> (out, carry): `out` has, summed over
  the valid frames of the chunk (chunks of one video add up), 'psnr_sum' [B]
  when the slot model reconstructs frames and, with segmentation, the
  per-video contingency tables 'table' [B, C, K] and per-frame FG-ARI sums
  and counts [B]; per frame, the FG-IoU matrices 'iou' [B, T, C-1, K] and
  'present' [B, T, C-1] (False on invalid frames).
  """
  num_slots = slot_model.slot_shape[0]

  def evaluate_frame(alpha, recon, video, segmentation, valid):
    """One frame of every video: alpha [B, N, H, W] ... valid [B]."""
    out = {}
    if recon is not None:
      frames = model_to_unit(frames_to_model(video))
      out['psnr_sum'] = jnp.where(valid, metrics_lib.psnr(recon, frames), 0.0)
    if not with_segmentation:
      return out
    pred_ids = metrics_lib.segmentation_from_alpha_masks(alpha)
    # Ids outside [0, C) are not counted: that drops the padded frames.
    true_ids = jnp.where(valid[:, None, None],
                         segmentation.astype(jnp.int32), -1)
    table = metrics_lib.contingency_table(
        true_ids[:, None], pred_ids[:, None], num_true, num_slots)  # [B,C,K]
    fg_ari = metrics_lib.ari_from_contingency(table, ignore_background=True)
    iou, present = metrics_lib.fg_iou_matrix(
        true_ids[:, None], pred_ids[:, None], num_true, num_slots)
    out.update(
        table=table,
        fg_ari_frame_sum=jnp.where(fg_ari.valid, fg_ari.value, 0.0),
        fg_ari_frame_count=fg_ari.valid.astype(jnp.int32),
        iou=iou, present=present & valid[:, None])
    return out

  def evaluate_chunk(slot_params, slots, video, segmentation, frame_valid,
                     carry):
    alpha, recon, carry = slot_model.observe(slot_params, slots, video, carry)
    # lax.map over time: one frame's metrics in memory at a time.
    per_frame = jax.lax.map(
        lambda inputs: evaluate_frame(*inputs),
        tuple(None if x is None else jnp.swapaxes(x, 0, 1)
              for x in (alpha, recon, video, segmentation, frame_valid)))
    out = {key: jnp.sum(value, axis=0) for key, value in per_frame.items()
           if key not in ('iou', 'present')}
    for key in ('iou', 'present'):
      if key in per_frame:
        out[key] = jnp.swapaxes(per_frame[key], 0, 1)
    return out, carry

  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  return jax.jit(evaluate_chunk,
                 in_shardings=(replicated,) + (batched,) * 5,
                 out_shardings=(batched, batched))


def evaluate_slot_model(eval_config: ml_collections.ConfigDict,
                        num_true: int, mesh: Mesh,
                        slot_model: SlotDecoder, slot_params: Any,
                        source: Any, num_frames: int,
                        with_segmentation: bool = True,
                        **batch_args) -> dict[str, Any]:
  """The slot model's reconstruction (where it has one) and segmentation of
  the first `num_frames` frames of every held-out video, in chunks of
  `evaluation.chunk_length` frames carrying its state.

  Returns 'psnr' (reconstructing models), 'fg_ari' / 'ari' pooled over each
  whole video and averaged over videos, 'fg_ari_per_frame' and
  'fg_miou_per_frame' (with segmentation), 'num_videos', 'num_frames'.
  With `evaluation.skip_first_frame` every one of them leaves out frame 0
  (SAVi's MOVi convention: conditional SAVi is given that frame's boxes);
  'num_frames' stays the frames encoded per video.
  """
  evaluator = make_quality_evaluator(num_true, mesh, slot_model,
                                     with_segmentation)
  # Batches split over this host's devices (`pipeline.host_batch_plan`).
  batch_args = {'multiple_of': len(mesh.local_devices), **batch_args}
  chunk = eval_config.chunk_length
  first_frame = 1 if eval_config.skip_first_frame else 0
  if num_frames <= first_frame:
    raise ConfigError('evaluation.skip_first_frame=True needs videos of at '
                      f'least 2 frames, these have {num_frames}')
  absent_ids = eval_config.miou_absent_ids
  fields = ('slots', 'video') + ((SEGMENTATION_FIELD,) if with_segmentation
                                 else ())
  fg_ari_video, ari_video, miou_frames = [], [], []
  psnr_sum, fg_ari_sum, fg_ari_count, num_valid_frames = 0.0, 0.0, 0, 0
  num_videos = 0
  has_psnr = False
  what = f'evaluate {slot_model.label}'
  num_batches = pipeline.num_eval_batches(source, **batch_args)
  progress.compiling(what, 'chunk')
  for batch_number, batch in enumerate(progress.bar(
      pipeline.eval_batches(source, num_frames=num_frames, **batch_args),
      desc=what, unit='batch', total=num_batches)):
    mask = sharding.gather_to_host(
        sharding.to_global_batch({'mask': batch['mask']}, mesh))['mask']
    totals, carry = {}, None
    # A split in one batch is one unit of the bar: its chunks say more.
    chunks = progress.Steps(f'{what} batch {batch_number + 1}/{num_batches}',
                            math.ceil(num_frames / chunk), 'chunks')
    for start in range(0, num_frames, chunk):
      pieces = {field: _padded_time_slice(batch[field], start, chunk)
                for field in fields}
      if not with_segmentation:
        pieces[SEGMENTATION_FIELD] = np.zeros(pieces['video'].shape[:2],
                                              np.uint8)
      frame_index = np.arange(start, start + chunk)
      frame_valid = (frame_index < num_frames) & (frame_index >= first_frame)
      pieces['frame_valid'] = np.broadcast_to(
          frame_valid, (len(batch['mask']), chunk)).copy()
      pieces = sharding.to_global_batch(pieces, mesh)
      out, carry = evaluator(
          slot_params, pieces['slots'], pieces['video'],
          pieces[SEGMENTATION_FIELD], pieces['frame_valid'], carry)
      out = sharding.gather_to_host(out)
      if 'iou' in out:
        # present is False on padded frames, so those frames are not valid.
        score = metrics_lib.hungarian_mean_iou(
            out.pop('iou')[mask], out.pop('present')[mask],
            absent_ids=absent_ids)
        miou_frames += list(np.asarray(score.value)[np.asarray(score.valid)])
      for key, value in out.items():
        totals[key] = totals.get(key, 0) + value
      chunks.advance()
    if 'psnr_sum' in totals:
      has_psnr = True
      psnr_sum += float(totals['psnr_sum'][mask].sum())
    num_videos += int(mask.sum())
    num_valid_frames += int(mask.sum()) * (num_frames - first_frame)
    if with_segmentation:
      table = totals['table'][mask]
      fg_ari_video += list(np.asarray(metrics_lib.ari_from_contingency(
          table, ignore_background=True).value))
      ari_video += list(np.asarray(
          metrics_lib.ari_from_contingency(table).value))
      fg_ari_sum += float(totals['fg_ari_frame_sum'][mask].sum())
      fg_ari_count += int(totals['fg_ari_frame_count'][mask].sum())
  results = {}
  if has_psnr:
    results['psnr'] = psnr_sum / max(num_valid_frames, 1)
  results.update(num_videos=num_videos, num_frames=num_frames)
  if with_segmentation:
    results.update(
        fg_ari=float(np.mean(fg_ari_video)),
        ari=float(np.mean(ari_video)),
        fg_ari_per_frame=fg_ari_sum / max(fg_ari_count, 1),
        fg_miou_per_frame=(float(np.mean(miou_frames)) if miou_frames
                           else None))
  return results


def _padded_time_slice(x: np.ndarray, start: int, length: int) -> np.ndarray:
  """x[:, start:start + length], padded along time by repeating the end."""
  piece = x[:, start:start + length]
  missing = length - piece.shape[1]
  if missing:
    piece = np.concatenate(
        [piece, np.repeat(piece[:, -1:], missing, axis=1)], axis=1)
  return piece


def _method_rank(method: str) -> tuple[int, str]:
  """Table order: the dynamics models as registered, copy-last, then the
  reference."""
  order = (*DYNAMICS, 'copy_last')
  return (order.index(method) if method in order else len(order)), method


class _StepAverager:
  """Sums of valid per-step values and their counts, per method and metric."""

  def __init__(self):
    self.sums: dict[str, dict[str, np.ndarray]] = {}
    self.counts: dict[str, dict[str, np.ndarray]] = {}

  def add(self, method: str, name: str, values: np.ndarray,
          valid: np.ndarray) -> None:
    """values, valid: [R, B]."""
    valid = valid & np.isfinite(values)
    sums = self.sums.setdefault(method, {})
    counts = self.counts.setdefault(method, {})
    sums[name] = sums.get(name, 0) + np.where(valid, values, 0.0).sum(axis=1)
    counts[name] = counts.get(name, 0) + valid.sum(axis=1)

  def results(self) -> dict[str, dict[str, dict[str, Any]]]:
    out = {}
    for method in sorted(self.sums, key=_method_rank):
      sums = self.sums[method]
      out[method] = {}
      for name, total in sums.items():
        count = self.counts[method][name]
        per_step = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        out[method][name] = {
            'mean': float(np.nanmean(per_step)) if np.any(count) else None,
            'per_step': [None if math.isnan(v) else float(v)
                         for v in per_step],
        }
    return out


def _lpips_or_none(names: tuple[str, ...]) -> metrics_lib.LpipsVgg | None:
  if 'lpips' not in names:
    return None
  try:
    return metrics_lib.make_lpips_vgg()
  except ImportError as error:
    logger.warning('LPIPS skipped: %s', error)
    print(f'LPIPS skipped: {error}')
    return None


def video_fields(eval_config: ml_collections.ConfigDict) -> tuple[str, ...]:
  """The video fields the metrics of `eval_config` read besides the slots."""
  names = tuple(eval_config.metrics)
  fields = ('video',)
  if rollout_metrics.needing(names, rollout_metrics.MASKS):
    fields += (SEGMENTATION_FIELD,)
  if uses_dataset_boxes(eval_config, names):
    fields += BOX_FIELDS
  return fields


def scored_metrics(names: tuple[str, ...], slot_model: SlotDecoder
                   ) -> tuple[tuple[str, ...], dict[str, str]]:
  """(the metrics of `names` the slot model can be scored on, {skipped
  metric: why}): a model that decodes no pixels has no frame metrics."""
  if slot_model.decodes_pixels:
    return names, {}
  why = f'{slot_model.label} decodes no pixels'
  frames = rollout_metrics.needing(names, rollout_metrics.FRAMES)
  return (tuple(n for n in names if n not in frames),
          {n: why for n in frames})


def evaluate(eval_config: ml_collections.ConfigDict,
             dynamics_config: ml_collections.ConfigDict, mesh: Mesh, *,
             slot_model: SlotDecoder, slot_params: Any,
             slot_steps: dict[str, int], dynamics: dict[str, Any],
             identity: dict[str, Any], source: Any, videos: Any,
             num_true: int, compute_dtype: str,
             output_dir: str | None) -> dict[str, Any]:
  """Evaluates the slot model and the rollouts on `evaluation.split`;
  writes metrics.json + per_step.csv to `output_dir` (lead host) and
  returns them.

  Args:
    eval_config: the `evaluation` section.
    dynamics_config: the first trained dynamics model's section
      (`sections.primary_dynamics`: its burn_in and frame_stride set the
      protocol for every dynamics model).
    slot_model, slot_params: the trained slot model (see `SlotDecoder`).
    slot_steps: its stage-1 checkpoint steps ({'savi': 4500}).
    dynamics: {name: object with `module`, `params`, `step`} of every
      dynamics model to evaluate (`dynamics.Loaded`).
    identity: what all of them are made from (stages/lineage.py), recorded
      with the metrics.
    source: the slots of the split with the `video_fields(eval_config)`.
    videos: the split's videos (read by a dataset's clip rule only).
    num_true: ground-truth segmentation ids (`num_true_ids`).
    compute_dtype: 'float32' or 'bfloat16' (rollouts and decoding).
    output_dir: where to write (None: nowhere).
  """
  started = time.time()
  names, skipped = scored_metrics(tuple(eval_config.metrics), slot_model)
  if skipped:
    logger.info('%s skipped: %s', ', '.join(skipped),
                next(iter(skipped.values())))
  with_segmentation = bool(rollout_metrics.needing(
      names, rollout_metrics.MASKS))
  lpips_fn = _lpips_or_none(names)
  dynamics_params = {name: model.params for name, model in dynamics.items()}
  burn_in = dynamics_config.burn_in
  rollout = eval_config.rollout_steps
  stride = dynamics_config.frame_stride
  fields = video_fields(eval_config)
  if with_segmentation:
    _check_has_segmentations(source, names)
  elif videos is not None and len(videos) and (
      SEGMENTATION_FIELD not in videos[0]):
    logger.info('the videos have no ground-truth masks: %s left out (frame '
                'metrics only)', ', '.join(rollout_metrics.needing(
                    tuple(rollout_metrics.labels()), rollout_metrics.MASKS)))
  num_videos = min(len(source), eval_config.num_videos or len(source))
  source = evaluation_clips(
      eval_config.clips, source, ('slots',) + fields, num_videos,
      videos=videos, burn_in=burn_in, rollout=rollout, frame_stride=stride)
  local_batch_size = sharding.per_host_batch_size(eval_config.batch_size, mesh)
  shared = dict(batch_size=local_batch_size,
                fields=('slots',) + fields,
                process_index=jax.process_index(),
                process_count=jax.process_count(), max_videos=len(source),
                multiple_of=len(mesh.local_devices))
  needed = (burn_in + rollout - 1) * stride + 1
  _check_length(source, needed, burn_in, rollout, stride)

  quality_started = time.time()
  quality = {}
  if eval_config.savi_metrics:
    quality = evaluate_slot_model(eval_config, num_true, mesh, slot_model,
                                  slot_params, source, needed,
                                  with_segmentation, **shared)
  quality_seconds = time.time() - quality_started

  # Rollouts.
  rollout_started = time.time()
  lpips_params = None if lpips_fn is None else lpips_fn.params
  evaluator = make_rollout_evaluator(
      eval_config, mesh, names,
      {name: model.module for name, model in dynamics.items()}, slot_model,
      burn_in=burn_in, num_true=num_true, compute_dtype=compute_dtype)
  averager = _StepAverager()
  progress.announce_decoding(
      'evaluate', slot_model,
      len(source) * rollout * (len(dynamics) + 2),
      f'--config.evaluation.num_videos (now {eval_config.num_videos}) or '
      '--config.evaluation.rollout_steps')
  num_batches = pipeline.num_eval_batches(source, **shared)
  progress.compiling('evaluate rollouts', 'batch')
  for batch_number, batch in enumerate(progress.bar(
      pipeline.eval_batches(source, num_frames=needed, **shared),
      desc='evaluate rollouts', unit='batch', total=num_batches)):
    mask = batch.pop('mask')
    batch.pop('index')
    for field in batch:
      batch[field] = batch[field][:, ::stride]
    # The rollout steps of one batch (a split in one batch: the only unit).
    with progress.ticking(progress.Steps(
        f'evaluate rollouts batch {batch_number + 1}/{num_batches}', rollout,
        'rollout steps')):
      out = sharding.gather_to_host(evaluator(
          dynamics_params, slot_params,
          sharding.to_global_batch(batch, mesh), lpips_params))
    mask = sharding.gather_to_host(
        sharding.to_global_batch({'mask': mask}, mesh))['mask']
    for method, per_metric in out.items():
      for name, (values, valid) in per_metric.items():
        on_host = rollout_metrics.get(name).on_host
        if on_host is not None:  # e.g. FG-mIoU's Hungarian matching
          values, valid = on_host(values, valid, eval_config)
        averager.add(method, name, np.asarray(values),
                     np.asarray(valid) & mask[None, :])
  rollout_results = averager.results()

  protocol = {'split': eval_config.split, 'num_videos': num_videos,
              'num_clips': len(source), 'clips': eval_config.clips,
              'burn_in': burn_in, 'rollout_steps': rollout,
              'frame_stride': stride,
              'background_threshold': eval_config.background_threshold,
              'ar_gt_boxes': eval_config.ar_gt_boxes,
              'miou_absent_ids': eval_config.miou_absent_ids,
              # The slot model's whole-video metrics without frame 0
              # (SAVi paper) or over every frame.
              'skip_first_frame': bool(eval_config.skip_first_frame),
              'masks': slot_model.mask_source}
  if skipped:
    protocol['skipped_metrics'] = skipped
  results = {
      'slot_model': slot_model.name,
      slot_model.name: quality,
      'rollout': rollout_results,
      'protocol': protocol,
      'checkpoints': {
          **{f'{key}_step': step for key, step in slot_steps.items()},
          **{f'{name}_step': model.step for name, model in dynamics.items()}},
      'identity': identity,
      'seconds': {slot_model.name: quality_seconds,
                  'rollout': time.time() - rollout_started,
                  'total': time.time() - started},
  }
  if jax.process_index() == 0 and output_dir is not None:
    _write_results(output_dir, results)
    print(format_table(results, slot_model.label))
  return results


def _check_length(source: Any, needed: int, burn_in: int, rollout: int,
                  stride: int) -> None:
  """The videos must cover burn-in + rollout (a one-line error if not)."""
  if not len(source):
    return
  length = len(source[0]['slots'])
  if length < needed:
    raise ConfigError(
        f'evaluation needs {needed} frames per video (burn-in {burn_in} + '
        f'{rollout} rollout steps, stride {stride}), the videos have '
        f'{length}; lower evaluation.rollout_steps')


def evaluation_clips(kind: str, source: Any, time_fields: tuple[str, ...],
                     num_videos: int, *, videos: Any, burn_in: int,
                     rollout: int, frame_stride: int) -> Any:
  """The evaluated clips of the first `num_videos` videos.

  `kind` (`evaluation.clips`): 'first' evaluates each video from its first
  frame; any other is a clip rule of the dataset (`datasets/base.py`, e.g.
  CLEVRER's official clips, which read the stored `in_view` of `videos`).
  """
  if kind == datasets.FIRST_CLIPS:
    return ClipSource(source, [(i, 0) for i in range(num_videos)],
                      time_fields)
  clips = datasets.clip_rule(kind)(videos, num_videos, burn_in, rollout,
                                   frame_stride)
  return ClipSource(source, clips, time_fields)


def _check_has_segmentations(source: Any, names: tuple[str, ...]) -> None:
  """Object metrics need ground-truth masks; say so before any compute."""
  if not len(source):
    return
  try:
    source[0]
  except KeyError:
    asked = list(rollout_metrics.needing(names, rollout_metrics.MASKS))
    frame_only = ','.join(rollout_metrics.needing(names,
                                                  rollout_metrics.FRAMES))
    raise ConfigError(
        f'evaluation.metrics asks for {asked}, which need ground-truth '
        f"'{SEGMENTATION_FIELD}', but this dataset has none. Evaluate frame "
        f'metrics only: --config.evaluation.metrics={frame_only or "psnr"}')


def _write_results(directory: str, results: dict[str, Any]) -> None:
  # Atomic: a crash or a full disk leaves the old files, never torn ones.
  write_json_atomic(os.path.join(directory, 'metrics.json'), results,
                    sort_keys=False)
  with atomic_text(os.path.join(directory, 'per_step.csv'), newline='') as f:
    writer = csv.writer(f)
    writer.writerow(['method', 'metric', 'step', 'value'])
    for method, per_metric in results['rollout'].items():
      for name, result in per_metric.items():
        for step, value in enumerate(result['per_step'], start=1):
          writer.writerow([method, name, step, value])


def format_table(results: dict[str, Any], label: str) -> str:
  """A method x metric table of the step-averaged rollout metrics; `label`
  names the slot model ('SAVi')."""
  rollout = results['rollout']
  names = rollout_metrics.ordered(
      n for m in rollout.values() for n in m)
  protocol = results['protocol']
  lines = [f'Rollout of {protocol["rollout_steps"]} steps after '
           f'{protocol["burn_in"]} burn-in frames, {protocol["num_videos"]} '
           f'{protocol["split"]} videos (mean over steps):']
  header = f'{"method":<22}' + ''.join(f'{n:>10}' for n in names)
  lines += [header, '-' * len(header)]
  for method, per_metric in rollout.items():
    cells = []
    for name in names:
      value = per_metric.get(name, {}).get('mean')
      cells.append(f'{"-" if value is None else f"{value:.4f}":>10}')
    lines.append(f'{method:<22}' + ''.join(cells))
  quality = results.get(results['slot_model'], {})
  parts = []
  if 'fg_ari' in quality:
    parts.append(f'FG-ARI {quality["fg_ari"]:.4f} (per frame '
                 f'{quality["fg_ari_per_frame"]:.4f})')
    if quality['fg_miou_per_frame'] is not None:
      parts.append(f'FG-mIoU per frame {quality["fg_miou_per_frame"]:.4f}')
    parts.append(f'ARI {quality["ari"]:.4f}')
  if 'psnr' in quality:
    parts.append(f'PSNR {quality["psnr"]:.2f} dB')
  if parts:
    skipped = (' (first frame skipped)'
               if protocol.get('skip_first_frame') else '')
    lines.append(f'{label} on the whole videos{skipped}: ' + ', '.join(parts))
  else:
    lines.append(f'{label} on the whole videos: not evaluated '
                 '(evaluation.savi_metrics=False)')
  return '\n'.join(lines)
