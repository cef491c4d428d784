"""Pictures of rollouts: GIFs, PNG strips, metric curves, attention maps.

Written by `--mode=render` under `<workdir>/render/`, for any slot model:

* `rollout_<i>.gif` / `.png`: for a few held-out videos, side by side over
  time, one labelled row (PNG) or column (GIF) each: the ground truth; the
  slot model's own segmentation of it (each pixel tinted by its slot's
  colour); every method's frames -- SlotFormer, Slot-LSTM when trained,
  copy-last (during burn-in the slot model's reconstruction of the observed
  slots, the decoded prediction afterwards) -- with SlotFormer's predicted
  segmentation; and, for decoders with per-slot reconstructions (SAVi), each
  SlotFormer slot's reconstruction weighted by its alpha mask. A red border
  marks predicted (rollout) frames, a green one observed frames. A SAVi
  reconstructing flow or depth (`savi.targets`) gets a row per method and
  target instead: flow in SAVi's colours, depth as a grey map on one scale
  per video, its range in the label (targets.picture).
* `per_step.png`: every per-step rollout metric of `eval/metrics.json`
  against the rollout step, methods overlaid (the paper's per-step figure).
* `attention_<i>.png` (decoders with per-slot reconstructions): the paper's
  appendix attention analysis (see `attention_maps`).
* `identity.json`: what the pictures were made from.
"""

from __future__ import annotations

import io
import logging
import os
from typing import Any

import einops
import imageio.v2 as imageio
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from PIL import Image
from PIL import ImageDraw

from slotformer_jax import inference
from slotformer_jax import targets as targets_lib
from slotformer_jax.dynamics import base as dynamics_base
from slotformer_jax.evaluation import rollout_metrics
from slotformer_jax.files import read_json
from slotformer_jax.files import write_atomic
from slotformer_jax.files import write_json_atomic
from slotformer_jax.frames import labelled_rows
from slotformer_jax.frames import mask_overlay
from slotformer_jax.frames import to_uint8
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.runtime import progress

logger = logging.getLogger(__name__)

_BORDER = 2
ROLLOUT_COLOUR = (220, 40, 40)
OBSERVED_COLOUR = (60, 160, 60)



def framed_tile(image: np.ndarray, colour: tuple[int, int, int], scale: int
          ) -> np.ndarray:
  """[H, W, 3] uint8 -> upscaled (nearest) with a coloured border."""
  image = np.repeat(np.repeat(image, scale, axis=0), scale, axis=1)
  height, width = image.shape[:2]
  tile = np.empty((height + 2 * _BORDER, width + 2 * _BORDER, 3), np.uint8)
  tile[:] = colour
  tile[_BORDER:-_BORDER, _BORDER:-_BORDER] = image
  return tile


def compose_frame(columns: list[np.ndarray], labels: list[str], *,
                  is_rollout: bool, step_text: str, scale: int) -> np.ndarray:
  """One GIF frame: labelled tiles in a row. columns: [H, W, 3] uint8."""
  colour = ROLLOUT_COLOUR if is_rollout else OBSERVED_COLOUR
  tiles = [framed_tile(c, colour, scale) for c in columns]
  tile_h, tile_w = tiles[0].shape[:2]
  label_h = 14
  canvas = Image.new('RGB', (tile_w * len(tiles), tile_h + 2 * label_h),
                     (255, 255, 255))
  draw = ImageDraw.Draw(canvas)
  for i, (tile, label) in enumerate(zip(tiles, labels)):
    canvas.paste(Image.fromarray(tile), (i * tile_w, label_h))
    draw.text((i * tile_w + 3, 1), label, fill=(0, 0, 0))
  draw.text((3, tile_h + label_h + 1), step_text, fill=colour)
  return np.asarray(canvas)


# Copy-last's colour in every curve (the dynamics models': their own).
COPY_LAST_COLOUR = '#ff7f0e'


def method_colours(slot_model: Any) -> dict[str, str]:
  """Every method's colour, by name, in every curve (per_step.png, the
  explorer): the dynamics models' (registry), copy-last's, the reference's."""
  return {**{model.name: model.colour for model in dynamics_base.registered()},
          'copy_last': COPY_LAST_COLOUR,
          slot_model.reference_method: slot_model.colour}


def method_labels(slot_model: Any) -> dict[str, str]:
  """How pictures name each method: every registered dynamics model's
  label, copy-last, and the slot model's reference ('savi_reconstruction':
  'SAVi recon.')."""
  return {**{model.name: model.label for model in dynamics_base.registered()},
          'copy_last': 'copy-last',
          slot_model.reference_method: slot_model.reference_label}


def make_renderer(dynamics_modules: dict[str, Any], slot_model: Any, *,
                  burn_in: int, rollout: int):
  """Jitted (dynamics_params, slot_params, slots [B, T, N, D], video uint8
  [B, T, H, W, 3]) -> pictures.

  Returns {method: recon [B, T, H, W, 3]} for every dynamics model and
  copy-last (burn-in frames: the slot model's reconstruction of the observed
  slots), 'slotformer_masks' [B, T, N, H, W] (SlotFormer's alpha masks),
  'observed_masks' [B, T, N, H, W] (the slot model's own masks of the real
  frames) and, for decoders with per-slot reconstructions, 'slot_views'
  [B, T, N, H, W, 3] (SlotFormer's slots on white).
  """
  dynamics = dict(dynamics_modules)
  with_masks = dynamics_base.intervened(dynamics)

  @jax.jit
  def render(dynamics_params, slot_params, slots, video):
    history = slots[:, :burn_in]
    futures = inference.rollouts(dynamics_params, dynamics, history, rollout)
    time_major = lambda x: jnp.swapaxes(x, 0, 1)
    out = {}
    for name, future in futures.items():
      whole = jnp.concatenate([history, future], axis=1)
      # One frame of every video at a time (STEVE generates token by token).
      decoded = jax.tree.map(time_major, jax.lax.map(
          lambda frame: slot_model.decode(slot_params, frame),
          time_major(whole)))
      out[name] = decoded.recon
      if decoded.targets:  # flow / depth composites [B, T, H, W, C]
        out[f'{name} targets'] = decoded.targets
      if name == with_masks:
        out['slotformer_masks'] = decoded.alpha_masks[..., 0]
        if decoded.rgb is not None:
          # Each slot's content where it is visible: rgb * alpha (+ white).
          out['slot_views'] = (decoded.rgb * decoded.alpha_masks
                               + (1.0 - decoded.alpha_masks))
    out['observed_masks'], _, _ = slot_model.observe(
        slot_params, slots, video, None)
    return out

  return render


def last_layer_attention(params: Any, history: jax.Array, *,
                         model: SlotFormer) -> jax.Array:
  """SlotFormer's last-layer attention from the predicted slots.

  history [B, T, N, D] -> a [B, N, T, N]: a[b, i, t, j] is the attention
  (averaged over heads) of the token predicting slot i of frame T + 1 to
  slot j of input frame t; it sums to 1 over (t, j).
  """
  _, variables = model.apply({'params': params}, history,
                             method=model.predict_next,
                             mutable=['intermediates'])
  blocks = variables['intermediates']['predictor']['transformer']
  last = blocks[f'block_{model.num_layers - 1}']
  weights = last['attention']['attention_weights'][0]  # [B, H, Q, K]
  num_frames, num_slots = history.shape[1:3]
  from_predicted = jnp.mean(weights[:, :, -num_slots:], axis=1)  # [B, N, TN]
  # Keys are the input tokens, frame-major: (frame t, slot j).
  return einops.rearrange(from_predicted, 'b i (t j) -> b i t j',
                          t=num_frames, j=num_slots)


def attention_maps(attention: jax.Array, slot_rgb: jax.Array,
                   slot_alpha: jax.Array) -> jax.Array:
  """The paper's spatial attention maps o^i_t = sum_j a^i_{t,j} m^j_t y^j_t.

  attention [B, N, T, N]; slot_rgb [B, T, N, H, W, 3] and slot_alpha
  [B, T, N, H, W, 1]: SAVi's per-slot reconstructions of the input frames.
  Returns o [B, N, T, H, W, 3].
  """
  views = slot_alpha * slot_rgb  # [B, T, N, H, W, 3]
  return jnp.einsum('bitj,btjhwc->bithwc', attention, views)


def make_attention_renderer(model: SlotFormer, slot_model: Any):
  """Jitted (params, slot_params, history [B, T, N, D]) -> arrays of the
  attention figure: 'maps' [B, N, T, H, W, 3], 'frames_recon' [B, T, H, W,
  3], 'predicted_views' [B, N, H, W, 3] (each predicted slot's
  reconstruction on black) and 'predicted_recon' [B, H, W, 3]; None for a
  slot model whose decoder has no per-slot reconstructions. `model`:
  SlotFormer."""

  @jax.jit
  def render(params, slot_params, history):
    attention = last_layer_attention(params, history, model=model)
    inputs = slot_model.decode(slot_params, history)
    predicted = slot_model.decode(
        slot_params, model.apply({'params': params}, history,
                                 method=model.predict_next))
    if inputs.rgb is None:
      return None
    return {
        'maps': attention_maps(attention, inputs.rgb, inputs.alpha_masks),
        'frames_recon': inputs.recon,
        'predicted_views': predicted.rgb * predicted.alpha_masks,
        'predicted_recon': predicted.recon,
    }

  return render


def render(render_config: ml_collections.ConfigDict,
           eval_config: ml_collections.ConfigDict,
           dynamics_config: ml_collections.ConfigDict, *,
           slot_model: Any, slot_params: Any, dynamics: dict[str, Any],
           identity: dict[str, Any], source: Any, metrics_path: str,
           output_dir: str) -> list[str]:
  """Writes GIFs, PNG strips, attention maps and the per-step curves of a few
  held-out rollouts to `output_dir`; returns the paths. Rendered on one
  device of the lead host.

  Args:
    render_config: the `render` section; eval_config: the `evaluation`
      section (its rollout length); dynamics_config: SlotFormer's (burn-in,
      frame stride).
    slot_model, slot_params: the trained slot model (as for
      `evaluate.evaluate`).
    dynamics: {name: `dynamics.Loaded`} of every dynamics model shown.
    identity: what all of them are made from, recorded with the pictures.
    source: the evaluation split's slots with their 'video'.
    metrics_path: the evaluation's metrics.json (the per-step curves).
  """
  if jax.process_index() != 0:
    return []
  other_targets = targets_lib.besides_frames(slot_model)
  if not slot_model.decodes_pixels and not other_targets:
    logger.info('render skipped: %s decodes no pixels', slot_model.label)
    return []
  dynamics_names = tuple(dynamics)
  dynamics_params = jax.device_get(
      {name: model.params for name, model in dynamics.items()})
  slot_params = jax.device_get(slot_params)
  burn_in = dynamics_config.burn_in
  rollout = eval_config.rollout_steps
  stride = dynamics_config.frame_stride
  labels = method_labels(slot_model)
  count = min(render_config.num_videos, len(source))
  frames_needed = (burn_in + rollout - 1) * stride + 1
  items = [source[i] for i in range(count)]
  slots = np.stack([item['slots'][:frames_needed:stride] for item in items])
  videos = np.stack([item['video'][:frames_needed:stride] for item in items])
  # The data's flow / depth where the source serves them (their rows).
  truth_targets = {
      target.name: np.stack([item[target.field][:frames_needed:stride]
                             for item in items])
      for target in other_targets if target.field in items[0]}
  if slots.shape[1] < burn_in + rollout:
    raise ValueError(
        f'rendering needs {frames_needed} frames per video, the videos have '
        f'{len(items[0]["slots"])}; lower evaluation.rollout_steps')
  renderer = make_renderer(
      {name: model.module for name, model in dynamics.items()}, slot_model,
      burn_in=burn_in, rollout=rollout)
  # The attention figure needs per-slot reconstructions; a decoder without
  # them (STEVE) would generate frames only to be thrown away.
  has_slot_views = jax.eval_shape(
      lambda: slot_model.decode(slot_params, slots[:1, :1])).rgb is not None
  # The model the masks, slot views and attention are drawn of (SlotFormer).
  primary = dynamics_base.intervened(dynamics)
  attention_renderer = (make_attention_renderer(
      dynamics[primary].module, slot_model) if has_slot_views else None)
  methods = [*dynamics_names, 'copy_last']
  progress.announce_decoding(
      'render', slot_model, count * (burn_in + rollout) * len(methods),
      f'--config.render.num_videos (now {render_config.num_videos}) or '
      '--config.evaluation.rollout_steps')

  directory = output_dir
  os.makedirs(directory, exist_ok=True)
  written = []
  label = slot_model.label
  for v in progress.bar(range(count), desc='render', unit='video'):
    # One video at a time: the bar's rate tells how long the rest takes.
    out = jax.tree.map(lambda x: x[0], jax.device_get(renderer(
        dynamics_params, slot_params, slots[v:v + 1], videos[v:v + 1])))
    truth = videos[v].astype(np.float32) / 255.0
    rows = {'truth': truth,
            f'{label} masks': mask_overlay(truth, out['observed_masks'])}
    if out[primary] is not None:
      for method in methods:
        rows[labels[method]] = out[method]
    rows.update(target_rows(
        other_targets, out, methods, labels,
        {name: values[v] for name, values in truth_targets.items()}))
    rows[f'{labels[primary]} masks'] = mask_overlay(
        truth if out[primary] is None else out[primary],
        out['slotformer_masks'])
    if 'slot_views' in out:
      for n in range(out['slot_views'].shape[1]):
        rows[f'slot {n}'] = out['slot_views'][:, n]
    rows = {name: to_uint8(np.asarray(frames))
            for name, frames in rows.items()}
    gif_frames = []
    for t in range(burn_in + rollout):
      is_rollout = t >= burn_in
      text = (f'rollout step {t - burn_in + 1}/{rollout}' if is_rollout
              else f'burn-in frame {t + 1}/{burn_in}')
      gif_frames.append(compose_frame(
          [row[t] for row in rows.values()], list(rows),
          is_rollout=is_rollout, step_text=text, scale=render_config.scale))
    gif_path = os.path.join(directory, f'rollout_{v:03d}.gif')
    gif = io.BytesIO()
    imageio.mimsave(gif, gif_frames, format='GIF',
                    duration=1.0 / render_config.fps, loop=0)
    write_atomic(gif_path, gif.getvalue())
    png_path = os.path.join(directory, f'rollout_{v:03d}.png')
    write_strip(png_path, rows, burn_in, render_config)
    written += [gif_path, png_path]
    if attention_renderer is not None:
      attention = jax.tree.map(lambda x: x[0], jax.device_get(
          attention_renderer(dynamics_params[primary], slot_params,
                             slots[v:v + 1, :burn_in])))
      attention_path = os.path.join(directory, f'attention_{v:03d}.png')
      _write_attention_figure(attention_path, videos[v, :burn_in + 1],
                              attention,
                              render_config.scale,
                              f'{eval_config.split} video {v}')
      written.append(attention_path)
  curves = write_per_step_figure(metrics_path, directory, labels,
                                 slot_model.reference_method, identity,
                                 method_colours(slot_model))
  if curves:
    written.append(curves)
  write_json_atomic(os.path.join(directory, 'identity.json'),
                    {'identity': identity, 'pictures': sorted(
                        os.path.basename(p) for p in written)})
  print(f'wrote {len(written)} pictures to {directory}')
  return written


_LABEL_WIDTH = 92


def target_rows(targets: list[Any], out: dict[str, Any], methods: list[str],
                labels: dict[str, str],
                truth: dict[str, np.ndarray] | None = None
                ) -> dict[str, np.ndarray]:
  """{row label: float RGB [T, H, W, 3] in [0, 1]}: the data's flow / depth
  of one video where `truth` ({name: [T, H, W, C]}) has it, then every
  method's decoded one (`out`: the renderer's, batch dim removed). Depth:
  one grey scale for all rows, the range of the data's depth over the video
  (without it, of the first method's, SlotFormer's), written under the
  labels."""
  truth = truth or {}
  rows = {}
  for target in targets:
    decoded = {m: np.asarray(out[f'{m} targets'][target.name])
               for m in methods}
    value_range = targets_lib.grey_scale(
        target, truth.get(target.name, decoded[methods[0]]))
    scale = targets_lib.labelled('', value_range, '\n')  # a line of its own
    if target.name in truth:
      rows[f'{target.label}{scale}'] = targets_lib.picture(
          target, truth[target.name], value_range)
    for method in methods:
      rows[f'{labels[method]} {target.label}{scale}'] = targets_lib.picture(
          target, decoded[method], value_range)
  return rows


def write_strip(path: str, rows: dict[str, np.ndarray], burn_in: int,
                render_config: ml_collections.ConfigDict) -> None:
  """A PNG grid: one row per entry of `rows` ({label: uint8 [T, H, W, 3]}),
  its label drawn at the left; columns are every `strip_every`-th frame,
  green-bordered while observed (burn-in), red-bordered when predicted."""
  num_frames = next(iter(rows.values())).shape[0]
  columns = list(range(0, num_frames, max(1, render_config.strip_every)))
  strips = {name: np.concatenate([
      framed_tile(row[t],
                  ROLLOUT_COLOUR if t >= burn_in else OBSERVED_COLOUR,
                  render_config.scale)
      for t in columns], axis=1) for name, row in rows.items()}
  write_png(path, labelled_rows(strips, _LABEL_WIDTH))


def _column_header(labels: list[str], tile_width: int, label_width: int,
                   height: int = 14) -> np.ndarray:
  """A white band with `labels[c]` over column c of tiles `tile_width`
  wide, after a `label_width` margin."""
  canvas = Image.new('RGB', (label_width + tile_width * len(labels), height),
                     (255, 255, 255))
  draw = ImageDraw.Draw(canvas)
  for c, label in enumerate(labels):
    draw.text((label_width + c * tile_width + 3, 1), label, fill=(0, 0, 0))
  return np.asarray(canvas)


def titled(image: np.ndarray, lines: list[str]) -> np.ndarray:
  """`image` [H, W, 3] uint8 under a white band with one text line each."""
  lines = [printable(line) for line in lines]
  band = 14 * len(lines) + 4
  measure = ImageDraw.Draw(Image.new('RGB', (1, 1)))
  width = max([image.shape[1]] + [int(measure.textlength(line)) + 6
                                  for line in lines])
  canvas = Image.new('RGB', (width, image.shape[0] + band), (255, 255, 255))
  draw = ImageDraw.Draw(canvas)
  for i, line in enumerate(lines):
    draw.text((3, 2 + 14 * i), line, fill=(0, 0, 0))
  canvas.paste(Image.fromarray(image), (0, band))
  return np.asarray(canvas)


def printable(text: str, limit: int = 160) -> str:
  """`text` as drawn on a picture: non-printable and non-ASCII characters
  escaped (names come from files made elsewhere), cut to `limit`."""
  text = str(text).encode('ascii', 'backslashreplace').decode('ascii')
  text = ''.join(c if c.isprintable() else '?' for c in text)
  return text if len(text) <= limit else text[:limit - 3] + '...'


def labelled_tile_grid(rows: dict[str, list[np.ndarray]],
                       column_labels: list[str]) -> np.ndarray:
  """{row label: [tile uint8 [h, w, 3], ...]} (equal tiles, one per column)
  -> the grid with each row's label at its left and `column_labels` above
  the columns."""
  strips = {name: np.concatenate(tiles, axis=1)
            for name, tiles in rows.items()}
  tile_width = next(iter(rows.values()))[0].shape[1]
  grid = labelled_rows(strips, _LABEL_WIDTH)
  header = _column_header(column_labels, tile_width, _LABEL_WIDTH)
  return np.concatenate([header, grid], axis=0)


def _write_attention_figure(path: str, frames: np.ndarray,
                            attention: dict[str, np.ndarray],
                            scale: int, title: str) -> None:
  """The appendix figure for one video, labelled.

  Top row: the T input frames and the predicted frame T + 1. Row i: the
  spatial attention maps o^i_t of predicted slot i over the input frames,
  then slot i's predicted reconstruction. Each row's maps are scaled by that
  row's maximum so weak and strong rows are both visible.
  """
  maps = attention['maps']  # [N, T, H, W, 3]
  num_slots, num_frames = maps.shape[:2]
  white = (255, 255, 255)
  rows = {'input frames': [
      *[framed_tile(frames[t], OBSERVED_COLOUR, scale)
        for t in range(num_frames)],
      framed_tile(to_uint8(attention['predicted_recon']), ROLLOUT_COLOUR,
                  scale)]}
  for i in range(num_slots):
    row_maps = maps[i] / max(float(maps[i].max()), 1e-8)
    rows[f'slot {i} attends'] = [
        *[framed_tile(to_uint8(row_maps[t]), white, scale)
          for t in range(num_frames)],
        framed_tile(to_uint8(attention['predicted_views'][i]), ROLLOUT_COLOUR,
              scale)]
  columns = [f't={t + 1}' for t in range(num_frames)]
  columns.append(f't={num_frames + 1} predicted')
  grid = labelled_tile_grid(rows, columns)
  write_png(path, titled(grid, [
      title, "SlotFormer's last-layer attention from each predicted slot of "
      f"frame {num_frames + 1} to the input frames' slots (row-normalised)",
      "last column: the slot's predicted reconstruction"]))


def write_png(path: str, image: np.ndarray) -> None:
  """uint8 [H, W, 3] as a PNG, atomically (files.py)."""
  buffer = io.BytesIO()
  Image.fromarray(image).save(buffer, format='PNG')
  write_atomic(path, buffer.getvalue())


def write_per_step_figure(metrics_path: str, directory: str,
                          labels: dict[str, str], reference_method: str,
                          identity: dict[str, Any] | None = None,
                          colours: dict[str, str] | None = None
                          ) -> str | None:
  """`<directory>/per_step.png` from the evaluation's `metrics_path`: one
  panel per metric, value against rollout step, methods overlaid (named by
  `labels`, in `colours` where given, the reference method dashed). None
  (and a log line) when the
  evaluation has not been run, or (given `identity`, what the other
  pictures were made from) was made from other models."""
  if not os.path.exists(metrics_path):
    logger.warning('no %s: run --mode=evaluate first for the per-step '
                   'figure', metrics_path)
    return None
  import matplotlib  # pylint: disable=g-import-not-at-top
  matplotlib.use('Agg')
  from matplotlib import pyplot as plt  # pylint: disable=g-import-not-at-top

  metrics = read_json(metrics_path, fix='Re-run --mode=evaluate.')
  if identity is not None and metrics.get('identity') != identity:
    logger.warning('%s is from other models than the ones rendered (%s vs '
                   '%s): re-run --mode=evaluate for the per-step figure',
                   metrics_path, metrics.get('identity'), identity)
    return None
  rollout = metrics['rollout']
  names = rollout_metrics.ordered(
      n for per_metric in rollout.values() for n in per_metric)
  columns = min(3, len(names))
  rows = -(-len(names) // columns)
  figure, axes = plt.subplots(rows, columns,
                              figsize=(3.4 * columns, 2.8 * rows),
                              squeeze=False)
  for axis in axes.flat[len(names):]:
    axis.set_visible(False)
  for axis, name in zip(axes.flat, names):
    for method, per_metric in rollout.items():
      if name not in per_metric:
        continue
      values = [np.nan if v is None else v
                for v in per_metric[name]['per_step']]
      axis.plot(np.arange(1, len(values) + 1), values,
                label=labels.get(method, method),
                color=(colours or {}).get(method),
                linestyle='--' if method == reference_method else '-')
    axis.set_title(rollout_metrics.get(name).label)
    axis.set_xlabel('rollout step')
    axis.grid(alpha=0.3)
  axes[0][0].legend(fontsize=7)
  figure.tight_layout()
  path = os.path.join(directory, 'per_step.png')
  os.makedirs(directory, exist_ok=True)
  buffer = io.BytesIO()
  figure.savefig(buffer, dpi=120, format='png')
  write_atomic(path, buffer.getvalue())
  plt.close(figure)
  return path
