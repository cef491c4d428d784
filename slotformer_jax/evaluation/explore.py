"""The run explorer: one offline page of a run's rollouts, slot by slot,
with counterfactual rollouts computed by the model.

``--mode=explore`` writes ``<workdir>/explore/index.html`` (everything
embedded, no server, no network) with ``identity.json`` beside it, for
``explore.num_videos`` held-out videos of ``evaluation.split``: every
method's rollout and segmentation, SlotFormer's slots one by one, the
per-step metric curves, and for every slot k two interventions, *remove*
(k masked out of the dynamics model's attention and the decoder's softmax)
and *freeze* (k held at its last observed value). All interventions of all
videos are one batch of one jitted function (:class:`Explorer`), compiled
once per shape. What the page shows and why: docs/explore.md.

Shapes: slots [V, T, N, D] (V videos, T = burn_in + rollout frames), video
uint8 [V, T, H, W, 3], segmentation int [V, T, H, W].
"""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import json
import logging
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from PIL import Image

from slotformer_jax import inference
from slotformer_jax import targets as targets_lib
from slotformer_jax.config.sections import DYNAMICS
from slotformer_jax.config import defaults
from slotformer_jax.dynamics import base as dynamics_base
from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import explore_page
from slotformer_jax.evaluation import page_text
from slotformer_jax.evaluation import metrics_file
from slotformer_jax.evaluation import metrics as metrics_lib
from slotformer_jax.evaluation import rollout_metrics
from slotformer_jax.evaluation import visualize
from slotformer_jax import frames as frames_lib
from slotformer_jax.errors import UserError
from slotformer_jax.files import write_atomic
from slotformer_jax.files import write_json_atomic
from slotformer_jax.runtime import progress

logger = logging.getLogger(__name__)

INTERVENTIONS = ('remove', 'freeze')
# |intervention - factual| is small next to the frames' range: shown x4.
DIFF_GAIN = 4.0
# render/'s colours, labels and conversion: the page matches its pictures.
# pylint: disable=protected-access
_PALETTE = frames_lib.SLOT_COLOURS
_to_uint8 = frames_lib.to_uint8


def intervention_masks(num_slots: int) -> tuple[np.ndarray, np.ndarray]:
  """(presence, frozen), bool [1 + 2N, N] each: row 0 is the factual
  rollout, row 1 + k removes slot k, row 1 + N + k freezes it."""
  eye = np.eye(num_slots, dtype=bool)
  everyone = np.ones((1, num_slots), bool)
  nobody = np.zeros((1, num_slots), bool)
  presence = np.concatenate([everyone, ~eye, np.ones_like(eye)])
  frozen = np.concatenate([nobody, np.zeros_like(eye), eye])
  return presence, frozen


def counterfactual_rollouts(params: Any, burn_in_slots: jax.Array, *,
                            model: Any, num_steps: int
                            ) -> tuple[jax.Array, jax.Array]:
  """Every intervention of every video in one batch.

  burn_in_slots [V, B, N, D] -> (slots [V, 1 + 2N, B + num_steps, N, D]:
  the burn-in and rollout of the factual run and of each intervention (rows
  as `intervention_masks`), presence bool [1 + 2N, N]).
  """
  videos, burn_in, num_slots, slot_size = burn_in_slots.shape
  presence, frozen = (jnp.asarray(m) for m in intervention_masks(num_slots))
  rows = presence.shape[0]
  history = jnp.broadcast_to(burn_in_slots[:, None],
                             (videos, rows, burn_in, num_slots, slot_size))
  flat = history.reshape(videos * rows, burn_in, num_slots, slot_size)
  tile = lambda mask: jnp.tile(mask, (videos, 1))
  future = inference.rollout_slots(
      params, flat, model=model, num_steps=num_steps,
      slot_presence=tile(presence), frozen=tile(frozen))
  whole = jnp.concatenate([flat, future], axis=1)
  return whole.reshape(videos, rows, *whole.shape[1:]), presence


def primary_target(slot_model: Any) -> targets_lib.Target:
  """What the page draws a method's rollout as: the frames, or the first
  target of a slot model reconstructing no frames (SAVi with flow/depth)."""
  if slot_model.decodes_pixels:
    return targets_lib.RGB
  return getattr(slot_model, 'targets', (targets_lib.RGB,))[0]


def _shown(slot_model: Any, decoded: Any) -> tuple[jax.Array, dict[str,
                                                                     Any]]:
  """(the primary target's values, {name: values} of its other targets)
  of one `Decoded`."""
  first = primary_target(slot_model)
  others = dict(decoded.targets or {})
  primary = (decoded.recon if first == targets_lib.RGB
             else others.pop(first.name))
  return primary, others


class Explorer:
  """Jitted (dynamics_params, slot_params, slots [V, T, N, D], video uint8
  [V, T, H, W, 3], segmentation int [V, T, H, W] or None) -> the arrays of
  the page (see `_explore`); `trace_count` counts its compilations."""

  def __init__(self, dynamics_modules: dict[str, Any], slot_model: Any, *,
               burn_in: int, rollout: int, num_true: int,
               background_threshold: float | None,
               metrics: tuple[str, ...] = defaults.ROLLOUT_METRICS):
    self.slot_model = slot_model
    # The per-video curves: the metrics of these drawn per video.
    self.metrics = tuple(metrics)
    self.dynamics_names = tuple(dynamics_modules)
    # The model the interventions act on (SlotFormer): the first that
    # takes them; the others are rolled out as they are.
    self.primary = dynamics_base.intervened(dynamics_modules)
    self.intervened = dynamics_modules[self.primary]
    self.baselines = {name: module
                      for name, module in dynamics_modules.items()
                      if name != self.primary}
    self.burn_in = burn_in
    self.rollout = rollout
    self.num_true = num_true
    self.background_threshold = background_threshold
    self.trace_count = 0
    self._jitted = jax.jit(self._explore)

  def __call__(self, dynamics_params, slot_params, slots, video,
               segmentation=None):
    return self._jitted(dynamics_params, slot_params, slots, video,
                        segmentation)

  def _explore(self, dynamics_params, slot_params, slots, video,
               segmentation):
    self.trace_count += 1  # runs only while tracing
    burn_in = self.burn_in
    history = slots[:, :burn_in]
    num_slots = slots.shape[2]
    counterfactual, presence = counterfactual_rollouts(
        dynamics_params[self.primary], history, model=self.intervened,
        num_steps=self.rollout)
    # The other methods' factual rollouts join the batch (always present).
    others = inference.rollouts(dynamics_params, self.baselines, history,
                                self.rollout)
    names = [self.primary, *others]
    other_slots = jnp.stack(
        [jnp.concatenate([history, others[name]], axis=1) for name in others],
        axis=1)
    everything = jnp.concatenate([counterfactual, other_slots], axis=1)
    rows_presence = jnp.concatenate(
        [presence, jnp.ones((len(others), num_slots), bool)])
    # One frame of every row at a time: [T, V, rows, N, D]; with a
    # token-by-token decoder each frame ticks the progress (minutes a video
    # with STEVE on a CPU).
    def decode_frame(inputs):
      index, frame = inputs
      progress.tick(index, self.slot_model.decode_steps)
      return self.slot_model.decode(slot_params, frame, rows_presence)
    time_major = jnp.moveaxis(everything, 2, 0)
    decoded = jax.lax.map(
        decode_frame, (jnp.arange(time_major.shape[0]), time_major))
    move = lambda x: jnp.moveaxis(x, 0, 2)  # -> [V, rows, T, ...]
    # What the page draws first: the frames, or (a SAVi reconstructing no
    # frames) its first target; the other targets as rows of their own.
    primary, besides = _shown(self.slot_model, decoded)
    pictures = move(primary)
    alpha = move(decoded.alpha_masks)[..., 0]  # [V, rows, T, N, H, W]
    num_cf = 1 + 2 * num_slots
    method_rows = [0, *range(num_cf, num_cf + len(others))]
    out = {
        'methods': {name: pictures[:, row] for name, row in
                    zip(names, method_rows)},
        'slotformer_masks': alpha[:, 0],
        'counterfactual': pictures[:, 1:num_cf],  # [V, 2N, T, H, W, C]
        'counterfactual_masks': alpha[:, 1:num_cf],
        'targets': {target: {name: values[:, row] for name, row in
                             zip(names, method_rows)}
                    for target, values in jax.tree.map(move,
                                                       besides).items()},
    }
    if decoded.rgb is not None:
      out['slot_rgb'] = move(decoded.rgb)[:, 0]  # [V, T, N, H, W, 3]
    out['observed_masks'], _, _ = self.slot_model.observe(
        slot_params, slots, video, None)
    frames = (None if decoded.recon is None
              else video.astype(jnp.float32) / 255.0)
    out['video_metrics'] = {
        name: self._rollout_metrics(pictures[:, row], alpha[:, row], frames,
                                    segmentation)
        for name, row in zip(names, method_rows)}
    return out

  def _rollout_metrics(self, recon, alpha, frames, segmentation):
    """{metric: [V, rollout]} of one method's rollout: every metric of
    `self.metrics` drawn per video (`Metric.per_video`: PSNR, SSIM,
    FG-ARI, ...) that it can be scored on: of its frames when it decodes frames
    (`frames` not None), of its masks when the data has them; NaN where a
    value is not valid."""
    burn_in = self.burn_in
    recon, alpha = recon[:, burn_in:], alpha[:, burn_in:]
    videos, steps = alpha.shape[:2]
    flat = lambda x: None if x is None else x.reshape(-1, *x.shape[2:])
    available = {rollout_metrics.FRAMES: frames is not None,
                 rollout_metrics.MASKS: segmentation is not None}
    names = [name for name, metric in rollout_metrics.METRICS.items()
             if name in self.metrics and metric.per_video
             and available[metric.needs]]
    if not names:
      return {}
    pred_ids = true_ids = table = None
    if rollout_metrics.needing(names, rollout_metrics.MASKS):
      pred_ids = metrics_lib.segmentation_from_alpha_masks(
          flat(alpha), bg_threshold=self.background_threshold)
      true_ids = flat(segmentation[:, burn_in:]).astype(jnp.int32)
      # One clustering per frame, as the evaluation's per-step metrics.
      table = metrics_lib.contingency_table(
          true_ids[:, None], pred_ids[:, None], self.num_true,
          alpha.shape[-3])
    step = rollout_metrics.Step(
        decoded=_Decoded(recon=flat(recon), alpha_masks=flat(alpha)[..., None]),
        frames=(flat(frames[:, burn_in:]) if frames is not None
                else flat(recon)),
        true_ids=true_ids, pred_ids=pred_ids, table=table, gt_boxes=None,
        num_true=self.num_true, num_slots=alpha.shape[-3])
    out = {}
    for name in names:
      scored = rollout_metrics.get(name).fn(step)
      if scored is not None:
        value, valid = scored
        out[name] = jnp.where(valid, value, jnp.nan).reshape(videos, steps)
    return out


@dataclasses.dataclass(frozen=True)
class _Decoded:
  """A method's decoded rollout as the metrics read it."""

  recon: jax.Array | None
  alpha_masks: jax.Array


# --------------------------------------------------------------------------
# The page
# --------------------------------------------------------------------------


def _png_uri(image: np.ndarray) -> str:
  """uint8 [H, W, 3] -> a PNG data URI."""
  buffer = io.BytesIO()
  Image.fromarray(image).save(buffer, format='PNG')
  return 'data:image/png;base64,' + base64.b64encode(
      buffer.getvalue()).decode('ascii')


def _strip(frames: np.ndarray) -> str:
  """[T, H, W, 3] in [0, 1] -> one data URI of the frames side by side
  (the page draws frame t from its t-th tile)."""
  frames = _to_uint8(np.asarray(frames))
  return _png_uri(np.concatenate(list(frames), axis=1))


def _alpha_view(alpha: np.ndarray, slot: int) -> np.ndarray:
  """alpha [T, H, W] -> [T, H, W, 3]: the slot's colour, weighted by its
  alpha, on black."""
  colour = _PALETTE[slot % len(_PALETTE)]
  return alpha[..., None] * colour


def _diff_view(intervened: np.ndarray, factual: np.ndarray) -> np.ndarray:
  """Per-pixel |intervened - factual| (mean over RGB, x DIFF_GAIN) as a
  grey image [T, H, W, 3]."""
  diff = np.abs(intervened - factual).mean(axis=-1, keepdims=True)
  return np.repeat(np.clip(diff * DIFF_GAIN, 0.0, 1.0), 3, axis=-1)


def run_curves(path: str, identity: dict[str, Any], labels: dict[str, str]
               ) -> tuple[dict[str, Any] | None, str]:
  """({metric: {method label: per-step values}}, note) of the evaluation's
  metrics.json at `path`, or (None, why not); `labels`: how the page names
  each method. See `metrics_file.read_curves`."""
  return metrics_file.read_curves(path, identity, labels)


def page_data(out: dict[str, Any], videos: np.ndarray, indices: list[int],
              *, slot_model: Any, title: str, burn_in: int, rollout: int,
              split: str, explore_config: ml_collections.ConfigDict,
              identity: dict[str, Any], curves: dict[str, Any] | None,
              curves_note: str, seconds: float,
              truth_targets: dict[str, np.ndarray] | None = None
              ) -> dict[str, Any]:
  """The page's JSON: every frame as strip data URIs, curves, identity.

  A slot model reconstructing flow / depth (`savi.targets`) is drawn as
  render/ draws it: flow in SAVi's colours, depth as a grey map with its
  range in the label; `truth_targets` ({name: [V, T, H, W, C]}, the data's
  flow / depth where it has them) adds their rows and sets depth's scale.
  """
  label = slot_model.label
  num_slots = out['slotformer_masks'].shape[2]
  truth_targets = truth_targets or {}
  # jax returns dicts sorted by key: the page's order is the table's.
  methods = [name for name in (*DYNAMICS, 'copy_last')
             if name in out['methods']]
  # The model the interventions act on (SlotFormer), drawn first.
  primary = dynamics_base.intervened(
      [name for name in methods if name in DYNAMICS])
  labels = visualize.method_labels(slot_model)
  first = primary_target(slot_model)
  # In the config's order (jax returns dicts sorted by key).
  besides = [target for target in targets_lib.besides_frames(slot_model)
             if target.name in out.get('targets', {})]
  palette = ['#%02x%02x%02x' % tuple(int(c * 255 + 0.5) for c in colour)
             for colour in _PALETTE]
  shown = (first, *besides)
  # A method's decoded values of a target: [V, T, H, W, C].
  decoded = lambda target, method: (
      out['methods'] if target == first
      else out['targets'][target.name])[method]
  entries = []
  for v, index in enumerate(indices):
    truth = videos[v].astype(np.float32) / 255.0
    # Depth on one grey scale per video: the data's, else SlotFormer's.
    ranges = {target.name: targets_lib.grey_scale(
        target, truth_targets[target.name][v] if target.name in truth_targets
        else decoded(target, primary)[v]) for target in shown}
    draw = lambda target, values: (
        np.asarray(values) if target == targets_lib.RGB
        else targets_lib.picture(target, values, ranges[target.name]))
    # Row labels: 'SlotFormer' (frames), 'SlotFormer flow', 'depth 2.1..3.1'.
    named = lambda target, text: targets_lib.labelled(
        text if target == targets_lib.RGB else f'{text} {target.label}',
        ranges[target.name])
    factual = draw(first, decoded(first, primary)[v])
    rows = [('truth', 'truth', truth)]
    rows += [(f'truth/{target.name}', targets_lib.labelled(
        target.label, ranges[target.name]),
              draw(target, truth_targets[target.name][v]))
             for target in shown if target.name in truth_targets]
    rows.append(('observed_masks', f'{label} masks',
                 frames_lib.mask_overlay(truth, out['observed_masks'][v])))
    for name in methods:
      rows += [(name if target == first else f'{name}/{target.name}',
                named(target, labels[name]),
                factual if (target, name) == (first, primary)
                else draw(target, decoded(target, name)[v]))
               for target in shown]
      if name == primary:
        rows.append(('slotformer_masks', f'{labels[primary]} masks',
                     frames_lib.mask_overlay(factual,
                                             out['slotformer_masks'][v])))
    slots = []
    for k in range(num_slots):
      alpha = out['slotformer_masks'][v, :, k]
      if 'slot_rgb' in out:
        rgb = out['slot_rgb'][v, :, k]
      else:  # STEVE, flow / depth: the whole picture where the slot's mask is
        rgb = factual
      view = rgb * alpha[..., None] + (1.0 - alpha[..., None])
      slots.append({'view': _strip(view),
                    'alpha': _strip(_alpha_view(alpha, k))})
    counterfactual = {}
    for i, kind in enumerate(INTERVENTIONS):
      kind_rows = slice(i * num_slots, (i + 1) * num_slots)
      frames = [draw(first, values)
                for values in out['counterfactual'][v, kind_rows]]
      masks = out['counterfactual_masks'][v, kind_rows]
      counterfactual[kind] = [
          {'frames': _strip(frames[k]),
           'masks': _strip(frames_lib.mask_overlay(frames[k], masks[k])),
           'diff': _strip(_diff_view(frames[k], factual)),
           'max_diff': round(float(np.abs(frames[k] - factual).max()), 4)}
          for k in range(num_slots)]
    per_video = out['video_metrics']
    metrics = {name: {labels[method]:
                          metrics_file.clean(per_video[method][name][v])
                      for method in methods}
               for name in rollout_metrics.METRICS
               if name in per_video[primary]}
    entries.append({
        'index': int(index),
        'rows': [{'key': key, 'label': row_label, 'strip': _strip(frames)}
                 for key, row_label, frames in rows],
        'slots': slots,
        'factual_masks': _strip(frames_lib.mask_overlay(
            factual, out['slotformer_masks'][v])),
        'counterfactual': counterfactual,
        'curves': metrics,
    })
  height, width = videos.shape[2:4]
  return {
      'title': title,
      'slot_model': label,
      # The charts' colour of the slot model's own reconstruction.
      'reference': {'label': slot_model.reference_label,
                    'colour': slot_model.colour},
      'slot_views': ('decoded reconstruction x alpha' if 'slot_rgb' in out
                     else f'decoded {first.label} x alpha'
                     if first != targets_lib.RGB
                     else 'generated frame x attention mask'),
      # The model the interventions act on, and every curve's colour.
      'primary': {'key': primary, 'label': labels[primary]},
      'method_colours': {
          labels[name]: colour
          for name, colour in visualize.method_colours(slot_model).items()
          if name in labels},
      # Every metric's label (the registry's: curves of any metric).
      'metric_labels': rollout_metrics.labels(),
      'burn_in': burn_in,
      'rollout': rollout,
      'num_slots': num_slots,
      'height': int(height), 'width': int(width),
      'scale': int(explore_config.scale),
      'fps': float(explore_config.fps),
      'split': split,
      'palette': palette,
      'diff_gain': DIFF_GAIN,
      'videos': entries,
      'run_curves': curves,
      'run_curves_note': curves_note,
      'identity': identity,
      'seconds': round(seconds, 1),
  }


def write_page(directory: str, data: dict[str, Any]) -> str:
  """index.html with `data` embedded; returns its path. Every text of
  `data` is shown as text (`page_text.page_safe`: no bidi override or
  control character acts on the page)."""
  data = page_text.page_safe(data)
  blob = json.dumps(data, separators=(',', ':'))
  # Inside <script>, '</script' would close the element early and '<!--'
  # change how the rest is parsed: no '<', '>' or '&' is left raw (they only
  # occur in JSON strings, where \\u003c is the same character).
  blob = (blob.replace('<', '\\u003c').replace('>', '\\u003e')
          .replace('&', '\\u0026'))
  page = explore_page.TEMPLATE.replace(
      '__TITLE__', html.escape(data['title'])).replace('__DATA__', blob)
  path = os.path.join(directory, 'index.html')
  write_atomic(path, page)
  return path


def write_outputs(directory: str, data: dict[str, Any],
                  identity: dict[str, Any], indices: list[int]) -> str:
  """index.html and identity.json; returns the page's path.

  Raises:
    UserError: a full disk, a quota, a read-only folder, in one line;
      nothing is left half written (`files.write_atomic`) and the rest of
      the run is intact.
  """
  try:
    path = write_page(directory, data)
    write_json_atomic(os.path.join(directory, 'identity.json'),
                      {'identity': identity, 'videos': indices,
                       'page': os.path.basename(path)})
  except OSError as error:
    raise UserError(
        f'explore: cannot write the page into {directory} '
        f'({error.strerror or error}); free space (or fix the folder) and '
        're-run --mode=explore') from None
  return path


def explore(explore_config: ml_collections.ConfigDict,
            eval_config: ml_collections.ConfigDict,
            dynamics_config: ml_collections.ConfigDict, *,
            slot_model: Any, slot_params: Any, dynamics: dict[str, Any],
            identity: dict[str, Any], open_slots: Any, num_true: int,
            metrics_path: str, output_dir: str, title: str) -> str | None:
  """Writes `output_dir`/index.html (and identity.json); returns the page's
  path (None on hosts other than the lead one). Runs on one device.

  Args:
    explore_config: the `explore` section; eval_config: the `evaluation`
      section (split, rollout length, background threshold);
      dynamics_config: SlotFormer's (burn-in, frame stride).
    slot_model, slot_params: the trained slot model.
    dynamics: {name: `dynamics.Loaded`} of every dynamics model (SlotFormer
      first; Slot-LSTM when trained).
    identity: what all of them are made from, recorded with the page.
    open_slots: fields -> the evaluation split's slots served with those
      video fields.
    num_true: ground-truth segmentation ids (`evaluate.num_true_ids`).
    metrics_path: the evaluation's metrics.json (the run's curves).
    title: the page's title.
  """
  if jax.process_index() != 0:
    return None
  besides = targets_lib.besides_frames(slot_model)
  if not slot_model.decodes_pixels and not besides:
    logger.info('explore skipped: %s decodes no pixels', slot_model.label)
    return None
  start = time.perf_counter()
  burn_in = dynamics_config.burn_in
  rollout = eval_config.rollout_steps
  stride = dynamics_config.frame_stride
  split = eval_config.split
  # The data's masks (FG-ARI) and flow / depth (their rows), where it has
  # them.
  fields = ['video', evaluate.SEGMENTATION_FIELD,
            *(target.field for target in besides)]
  while True:
    source = open_slots(tuple(fields))
    try:
      if len(source):
        source[0]
      break
    except KeyError as error:
      if error.args[0] not in fields[1:]:
        raise
      fields.remove(error.args[0])
  count = min(explore_config.num_videos, len(source))
  if not count:
    logger.warning('explore: the %s split has no videos; no page written',
                   split)
    return None
  frames_needed = (burn_in + rollout - 1) * stride + 1
  indices = list(range(count))
  items = [source[i] for i in indices]
  take = lambda key: np.stack([item[key][:frames_needed:stride]
                               for item in items])
  slots, videos = take('slots'), take('video')
  segmentation = (take(evaluate.SEGMENTATION_FIELD)
                  if evaluate.SEGMENTATION_FIELD in items[0] else None)
  truth_targets = {target.name: take(target.field) for target in besides
                   if target.field in items[0]}
  if slots.shape[1] < burn_in + rollout:
    raise ValueError(
        f'exploring needs {frames_needed} frames per video, the videos have '
        f'{len(items[0]["slots"])}; lower evaluation.rollout_steps')
  dynamics_params = jax.device_get(
      {name: model.params for name, model in dynamics.items()})
  explorer = Explorer(
      {name: model.module for name, model in dynamics.items()}, slot_model,
      burn_in=burn_in, rollout=rollout, num_true=num_true,
      background_threshold=eval_config.background_threshold,
      metrics=tuple(eval_config.metrics))
  num_rows = 1 + 2 * slots.shape[2] + len(dynamics) - 1
  progress.announce_decoding(
      'explore', slot_model, count * num_rows * (burn_in + rollout),
      f'--config.explore.num_videos (now {explore_config.num_videos}) or '
      '--config.evaluation.rollout_steps')
  slot_params = jax.device_get(slot_params)
  # One video at a time: the bar's rate tells how long the rest takes; the
  # frames decoded inside one video are lines of their own.
  progress.compiling('explore', 'video')
  per_video = []
  for v in progress.bar(range(count), desc='explore', unit='video'):
    with progress.ticking(progress.Steps(
        f'explore video {v + 1}/{count}', burn_in + rollout, 'frames')):
      per_video.append(jax.device_get(explorer(
          dynamics_params, slot_params, slots[v:v + 1], videos[v:v + 1],
          None if segmentation is None else segmentation[v:v + 1])))
  out = jax.tree.map(lambda *parts: np.concatenate(parts), *per_video)
  computed = time.perf_counter() - start
  curves, note = run_curves(metrics_path, identity,
                            visualize.method_labels(slot_model))
  directory = output_dir
  os.makedirs(directory, exist_ok=True)
  data = page_data(out, videos, indices, slot_model=slot_model, title=title,
                   burn_in=burn_in, rollout=rollout, split=split,
                   explore_config=explore_config, identity=identity,
                   curves=curves, curves_note=note, seconds=computed,
                   truth_targets=truth_targets)
  path = write_outputs(directory, data, identity, indices)
  print(f'wrote {path} ({count} videos x {2 * data["num_slots"]} '
        f'counterfactual rollouts, computed in {computed:.1f} s, page in '
        f'{time.perf_counter() - start - computed:.1f} s)')
  return path
