"""Pictures of rollouts: GIFs and PNG strips.

For each rendered held-out video, every frame shows side by side: the ground
truth, SlotFormer's frame (SAVi's reconstruction during burn-in, the decoded
prediction afterwards), the copy-last baseline, and each slot's
reconstruction weighted by its alpha mask. A red border marks predicted
(rollout) frames.
"""

from __future__ import annotations

import functools
import os
from typing import Any

import imageio.v2 as imageio
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
from PIL import Image
from PIL import ImageDraw

from slotformer_jax import models
from slotformer_jax import stages
from slotformer_jax.train import steps

_BORDER = 2
_ROLLOUT_COLOUR = (220, 40, 40)
_BURN_IN_COLOUR = (60, 160, 60)


def render_dir(workdir: str) -> str:
  return os.path.join(workdir, 'render')


def _to_uint8(frames: np.ndarray) -> np.ndarray:
  return (np.clip(frames, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _tile(image: np.ndarray, colour: tuple[int, int, int], scale: int
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
  colour = _ROLLOUT_COLOUR if is_rollout else _BURN_IN_COLOUR
  tiles = [_tile(c, colour, scale) for c in columns]
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


def make_renderer(config: ml_collections.ConfigDict):
  """Jitted (params, decoder_params, slots [B, T, N, D]) -> picture arrays."""
  model = models.build_slotformer(config)
  decoder = models.build_decoder(config)
  burn_in = config.slotformer.burn_in
  rollout = config.evaluation.rollout_steps

  @jax.jit
  def render(params, decoder_params, slots):
    history = slots[:, :burn_in]
    predicted = steps.rollout_slots(params, history, model=model,
                                    num_steps=rollout)
    copy_last = steps.copy_last_rollout(history, rollout)
    with_history = lambda future: jnp.concatenate([history, future], axis=1)
    decode = functools.partial(steps.decode_slots, decoder_params,
                               decoder=decoder)
    slotformer = decode(with_history(predicted))
    baseline = decode(with_history(copy_last))
    return {
        'slotformer': slotformer.recon,
        'copy_last': baseline.recon,
        # Each slot's content where it is visible: rgb * alpha (+ white).
        'slot_views': slotformer.rgb * slotformer.alpha_masks
                      + (1.0 - slotformer.alpha_masks),
    }

  return render


def render(config: ml_collections.ConfigDict, workdir: str,
           mesh: Mesh) -> list[str]:
  """Writes GIFs and PNG strips of a few held-out rollouts; returns paths.

  The handful of videos is rendered on one device of the lead host.
  """
  render_config = config.render
  savi_params, _ = stages.load_savi_params(config, workdir, mesh)
  params, _ = stages.load_slotformer_params(config, workdir, mesh)
  if jax.process_index() != 0:
    return []
  burn_in = config.slotformer.burn_in
  rollout = config.evaluation.rollout_steps
  stride = config.slotformer.frame_stride
  source = stages.slot_source_for(config, workdir, config.evaluation.split,
                                  ('video',))
  count = min(render_config.num_videos, len(source))
  frames_needed = (burn_in + rollout - 1) * stride + 1
  items = [source[i] for i in range(count)]
  slots = np.stack([item['slots'][:frames_needed:stride] for item in items])
  videos = np.stack([item['video'][:frames_needed:stride] for item in items])
  out = jax.device_get(make_renderer(config)(
      jax.device_get(params), jax.device_get(savi_params['decoder']), slots))

  directory = render_dir(workdir)
  os.makedirs(directory, exist_ok=True)
  written = []
  num_slots = config.savi.num_slots
  labels = ['truth', 'SlotFormer', 'copy-last'] + [
      f'slot {n}' for n in range(num_slots)]
  for video_index in range(count):
    gif_frames = []
    for t in range(burn_in + rollout):
      columns = [videos[video_index, t],
                 _to_uint8(out['slotformer'][video_index, t]),
                 _to_uint8(out['copy_last'][video_index, t])]
      columns += [_to_uint8(out['slot_views'][video_index, t, n])
                  for n in range(num_slots)]
      is_rollout = t >= burn_in
      text = (f'rollout step {t - burn_in + 1}/{rollout}' if is_rollout
              else f'burn-in frame {t + 1}/{burn_in}')
      gif_frames.append(compose_frame(columns, labels, is_rollout=is_rollout,
                                      step_text=text,
                                      scale=render_config.scale))
    gif_path = os.path.join(directory, f'rollout_{video_index:03d}.gif')
    imageio.mimsave(gif_path, gif_frames, duration=1.0 / render_config.fps,
                    loop=0)
    png_path = os.path.join(directory, f'rollout_{video_index:03d}.png')
    _write_strip(png_path, videos[video_index], out, video_index, burn_in,
                 render_config)
    written += [gif_path, png_path]
  print(f'wrote {len(written)} pictures to {directory}')
  return written


def _write_strip(path: str, video: np.ndarray, out: dict[str, Any],
                 video_index: int, burn_in: int,
                 render_config: ml_collections.ConfigDict) -> None:
  """Rows: truth, SlotFormer, copy-last, then each slot; columns: time."""
  num_frames = video.shape[0]
  columns = list(range(0, num_frames, max(1, render_config.strip_every)))
  rows = [[video[t] for t in columns],
          [_to_uint8(out['slotformer'][video_index, t]) for t in columns],
          [_to_uint8(out['copy_last'][video_index, t]) for t in columns]]
  for n in range(out['slot_views'].shape[2]):
    rows.append([_to_uint8(out['slot_views'][video_index, t, n])
                 for t in columns])
  grid = np.concatenate([
      np.concatenate([
          _tile(image, _ROLLOUT_COLOUR if t >= burn_in else _BURN_IN_COLOUR,
                render_config.scale)
          for image, t in zip(row, columns)], axis=1)
      for row in rows], axis=0)
  Image.fromarray(grid).save(path)
