"""The rollout metrics, registered by name: one function each, with its label.

A metric scores one rollout step of a batch of videos: `fn(step)` ->
(value [B], valid [B]) from a `Step` (the decoded prediction, the real
frames and, for a metric that needs masks, the predicted and true ids with
their contingency table). `evaluate` scores every method with the metrics
of `evaluation.metrics` in registration order; metrics.json, per_step.csv,
the tables, the seeds' summary, render/per_step.png and the explorer's
curves read their names, labels and directions here. A metric registered
from elsewhere (`register_metric`) becomes a value `evaluation.metrics`
takes. docs/developing.md, "Adding a metric".
"""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections

from slotformer_jax.config import defaults
from slotformer_jax.evaluation import metrics as metrics_lib

# What a metric reads besides the decoded prediction.
FRAMES = 'frames'  # the real frames (skipped for a model that decodes none)
MASKS = 'masks'  # the ground-truth segmentation (the dataset must have it)


@dataclasses.dataclass(frozen=True)
class Step:
  """One rollout step of a batch, as a metric reads it.

  decoded: the slot model's decoding of the predicted slots, leading [B]
    (recon [B, H, W, 3] in [0, 1], alpha_masks [B, N, H, W, 1]).
  frames: float [B, H, W, 3] in [0, 1].
  true_ids, pred_ids: int32 [B, H, W] (None unless a metric needs masks).
  table: the contingency table of (true_ids, pred_ids) [B, C, K].
  gt_boxes: None, or the dataset's boxes ('boxes' [B, M, 4], 'visible').
  num_true, num_slots: the ids C of the ground truth and K of the slots.
  lpips_fn, lpips_target: LPIPS and the real frames' features (or None).
  """

  decoded: Any
  frames: jax.Array
  true_ids: jax.Array | None
  pred_ids: jax.Array | None
  table: jax.Array | None
  gt_boxes: Any
  num_true: int
  num_slots: int
  lpips_fn: Callable | None = None
  lpips_target: Any = None


@dataclasses.dataclass(frozen=True)
class Metric:
  """A rollout metric.

  Attributes:
    name: its `evaluation.metrics` value and its key in metrics.json.
    label: how tables, pictures and the explorer name it ('PSNR (dB)').
    higher_is_better: its direction.
    needs: FRAMES or MASKS.
    fn: (Step) -> (value [B], valid [B]); None when it cannot be computed
      (LPIPS without its weights).
    per_video: drawn per video by the explorer (cheap, computed on every
      rollout there: not LPIPS, nor a metric with an `on_host` step).
    on_host: None, or (value, valid, evaluation section) -> (value [R, B],
      valid [R, B]): a last step on the host (FG-mIoU's Hungarian matching
      of the IoU matrices `fn` returns).
  """

  name: str
  label: str
  higher_is_better: bool
  needs: str
  fn: Callable[[Step], Any]
  per_video: bool = True
  on_host: Callable[..., Any] | None = None


# {name: metric}, in the order of every table, file and picture.
METRICS: dict[str, Metric] = {}


def register_metric(name: str, label: str, *, higher_is_better: bool,
                    needs: str, per_video: bool = True,
                    on_host: Callable[..., Any] | None = None
                    ) -> Callable[[Callable[[Step], Any]],
                                  Callable[[Step], Any]]:
  """Registers rollout metric `name` (a decorator of its function) and
  makes it a value of `evaluation.metrics`."""
  if needs not in (FRAMES, MASKS):
    raise ValueError(f'{name}: needs is {FRAMES!r} or {MASKS!r}')

  def decorate(fn):
    METRICS[name] = Metric(name, label, higher_is_better, needs, fn,
                           per_video and on_host is None, on_host)
    # Before any base_config() declared the field: its built-in values.
    choices = defaults.CHOICES.get('evaluation.metrics',
                                   defaults.ROLLOUT_METRICS)
    if name not in choices:
      defaults.CHOICES['evaluation.metrics'] = choices + (name,)
    return fn

  return decorate


def get(name: str) -> Metric:
  return METRICS[name]


def ordered(names: Any) -> list[str]:
  """The registered metrics among `names`, in registration order."""
  names = set(names)
  return [name for name in METRICS if name in names]


def needing(names: Any, what: str) -> tuple[str, ...]:
  """The metrics of `names` that need `what` (FRAMES or MASKS)."""
  return tuple(name for name in names if METRICS[name].needs == what)


def labels() -> dict[str, str]:
  """{name: label} of every registered metric."""
  return {name: metric.label for name, metric in METRICS.items()}


def _everywhere(step: Step) -> jax.Array:
  return jnp.ones(step.frames.shape[0], bool)


@register_metric('psnr', 'PSNR (dB)', higher_is_better=True, needs=FRAMES)
def psnr(step: Step):
  return metrics_lib.psnr(step.decoded.recon, step.frames), _everywhere(step)


@register_metric('ssim', 'SSIM', higher_is_better=True, needs=FRAMES)
def ssim(step: Step):
  return metrics_lib.ssim(step.decoded.recon, step.frames), _everywhere(step)


@register_metric('lpips', 'LPIPS', higher_is_better=False, needs=FRAMES,
                 per_video=False)
def lpips(step: Step):
  if step.lpips_fn is None:
    return None
  if step.lpips_target is None:
    return step.lpips_fn(step.decoded.recon, step.frames), _everywhere(step)
  return (step.lpips_fn.distance_to_features(step.decoded.recon,
                                             step.lpips_target),
          _everywhere(step))


@register_metric('ari', 'ARI', higher_is_better=True, needs=MASKS,
                 per_video=False)
def ari(step: Step):
  return tuple(metrics_lib.ari_from_contingency(step.table))


@register_metric('fg_ari', 'FG-ARI', higher_is_better=True, needs=MASKS)
def fg_ari(step: Step):
  return tuple(metrics_lib.ari_from_contingency(step.table,
                                                ignore_background=True))


def _hungarian(iou, present, eval_config: ml_collections.ConfigDict):
  score = metrics_lib.hungarian_mean_iou(
      iou, present, absent_ids=eval_config.miou_absent_ids)
  return score.value, score.valid


@register_metric('fg_miou', 'FG-mIoU', higher_is_better=True, needs=MASKS,
                 on_host=_hungarian)
def fg_miou(step: Step):
  """The IoU matrix [B, C-1, K] and 'present' [B, C-1], matched on the
  host (`_hungarian`)."""
  return metrics_lib.fg_iou_matrix(step.true_ids[:, None],
                                   step.pred_ids[:, None], step.num_true,
                                   step.num_slots)


@register_metric('ar', 'AR', higher_is_better=True, needs=MASKS,
                 per_video=False)
def ar(step: Step):
  """Average recall of the predicted segments' boxes: against the boxes of
  the ground-truth ids, or the dataset's own (`evaluation.ar_gt_boxes`)."""
  if step.gt_boxes is None:
    boxes, valid = metrics_lib.segmentation_to_boxes(step.true_ids,
                                                     step.num_true)
    # Row 0 of the ground truth is the background, not an object.
    boxes, valid = boxes[:, 1:], valid[:, 1:]
  else:
    # Row k - 1 is id k, so the greedy matching visits the same order.
    boxes, valid = metrics_lib.boxes_from_normalized(
        step.gt_boxes['boxes'], step.gt_boxes['visible'],
        height=step.frames.shape[-3], width=step.frames.shape[-2])
  pred_boxes, pred_valid = metrics_lib.segmentation_to_boxes(
      step.pred_ids, step.num_slots)
  return tuple(metrics_lib.average_recall(boxes, valid, pred_boxes,
                                          pred_valid))
