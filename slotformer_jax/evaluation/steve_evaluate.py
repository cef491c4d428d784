"""Evaluation and pictures with STEVE as the slot model.

The protocol of `evaluate.py` (burn-in slots -> rollout -> per-step metrics
averaged over videos, then over steps), with STEVE in place of SAVi's pixel
decoder:
* frames of predicted slots are *generated*: greedy decoding of all h*w
  tokens with a key/value cache, then the frozen dVAE's decoder;
* the slot masks of a generated frame are the token decoder's last-layer
  cross-attention of every token over the slots (mean over heads), upsampled
  bilinearly to the frame; their argmax is the predicted segmentation
  (FG-ARI, FG-mIoU, ARI, AR as with SAVi);
* STEVE's own segmentation of the held-out videos uses its Slot Attention
  masks (the last iteration's softmax over slots), upsampled bilinearly as
  the official code does.

Methods: the dynamics model(s), copy-last, and `steve_reconstruction`
(STEVE's slots of the real future frames generated: the reference).
"""

from __future__ import annotations

import functools
import logging
import os
import time
from typing import Any

from flax import struct
import imageio
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import tqdm

from slotformer_jax import inference
from slotformer_jax import models
from slotformer_jax import steve_inference
from slotformer_jax import steve_workdir
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import pipeline
from slotformer_jax.evaluation import evaluate as savi_evaluate
from slotformer_jax.evaluation import metrics as metrics_lib
from slotformer_jax.evaluation import visualize
from slotformer_jax.files import write_json_atomic
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.modules.token_decoder import TokenDecoder
from slotformer_jax.train import sharding

logger = logging.getLogger(__name__)

SEGMENTATION_FIELD = savi_evaluate.SEGMENTATION_FIELD
REFERENCE = 'steve_reconstruction'


@struct.dataclass
class GeneratedFrames:
  """What the frame/object metrics read: recon [..., H, W, 3] in [0, 1] and
  alpha_masks [..., N, H, W, 1] (softmax over slots)."""

  recon: jax.Array
  alpha_masks: jax.Array


def upsample_masks(masks: jax.Array, resolution: tuple[int, int]
                   ) -> jax.Array:
  """[..., N, h, w] (softmax over N) -> [..., N, H, W] bilinear (half-pixel
  centres, PyTorch's align_corners=False)."""
  shape = (*masks.shape[:-2], *resolution)
  return jax.image.resize(masks, shape, 'bilinear', antialias=False)


def make_generator(config: ml_collections.ConfigDict):
  """(steve_params, dvae_params, slots [B, N, D]) -> GeneratedFrames [B]."""
  steve = models.build_steve(config)
  dvae = models.build_dvae(config)
  height, width = steve.token_grid
  token_decoder = _token_decoder(config)
  resolution = tuple(config.data.resolution)

  def generate(steve_params, dvae_params, slots):
    frames, masks = steve_inference.generate_frames(
        steve_params['decoder'], dvae_params, slots, decoder=token_decoder,
        dvae=dvae, token_grid=(height, width))
    return GeneratedFrames(
        recon=frames, alpha_masks=upsample_masks(masks, resolution)[..., None])

  return generate


def _token_decoder(config: ml_collections.ConfigDict) -> TokenDecoder:
  """STEVE's token decoder alone; its parameters are steve_params['decoder']."""
  steve = models.build_steve(config)
  height, width = steve.token_grid
  return TokenDecoder(
      vocab_size=steve.vocab_size, num_tokens=height * width,
      dim=steve.slot_size, num_layers=steve.decoder_layers,
      num_heads=steve.decoder_heads, dropout_rate=steve.decoder_dropout)


def make_rollout_evaluator(config: ml_collections.ConfigDict, mesh: Mesh,
                           names: tuple[str, ...], lpips_fn: Any,
                           dynamics_names: tuple[str, ...]):
  """Jitted (dynamics_params, steve_params, dvae_params, batch) -> {method:
  {name: (value [R, B], valid [R, B])}}, as `evaluate.make_rollout_evaluator`
  but with generated frames and cross-attention masks."""
  models_by_name = {name: models.build_dynamics(config, name)
                    for name in dynamics_names}
  generate = make_generator(config)
  burn_in = config.slotformer.burn_in
  rollout = config.evaluation.rollout_steps
  step_metrics = functools.partial(
      savi_evaluate._frame_step_metrics, names=names,  # pylint: disable=protected-access
      num_true=savi_evaluate.num_true_ids(config.data),
      num_slots=config.steve.num_slots, lpips_fn=lpips_fn,
      background_threshold=config.evaluation.get('background_threshold'))
  needs_segmentation = any(n in savi_evaluate.OBJECT_METRICS for n in names)

  def evaluate_batch(dynamics_params, steve_params, dvae_params, batch):
    history = batch['slots'][:, :burn_in]
    predictions = {
        name: inference.rollout_slots(dynamics_params[name], history,
                                  model=model, num_steps=rollout)
        for name, model in models_by_name.items()}
    predictions[REFERENCE] = batch['slots'][:, burn_in:burn_in + rollout]
    frames = batch['video'][:, burn_in:burn_in + rollout]
    if needs_segmentation:
      segmentation = batch[SEGMENTATION_FIELD][:, burn_in:burn_in + rollout]
    else:
      segmentation = jnp.zeros(frames.shape[:2], jnp.int32)
    time_major = lambda x: jnp.swapaxes(x, 0, 1)
    score = lambda generated, frame, seg: step_metrics(
        generated, model_to_unit(
            frames_to_model(frame)), seg)

    def one_step(inputs):
      slots, frame, seg = inputs
      return score(generate(steve_params, dvae_params, slots), frame, seg)

    out = {method: jax.lax.map(one_step, (time_major(slots),
                                          time_major(frames),
                                          time_major(segmentation)))
           for method, slots in predictions.items()}
    # Copy-last predicts the same slots at every step: generate them once.
    copied = generate(steve_params, dvae_params, history[:, -1])
    out['copy_last'] = jax.lax.map(
        lambda inputs: score(copied, *inputs),
        (time_major(frames), time_major(segmentation)))
    return out

  replicated = sharding.replicated_sharding(mesh)
  return jax.jit(evaluate_batch, in_shardings=(
      replicated, replicated, replicated, sharding.batch_sharding(mesh)))


def make_segmentation_evaluator(config: ml_collections.ConfigDict,
                                mesh: Mesh):
  """Jitted STEVE segmentation of a chunk of frames.

  (steve_params, video uint8 [B, T, H, W, 3], segmentations [B, T, H, W],
  frame_valid bool [B, T], carry) -> ({'table' [B, C, K] summed over the
  valid frames, 'fg_ari_frame_sum' / '_count' [B], 'iou' [B, T, C-1, K],
  'present' [B, T, C-1]}, carry).
  """
  model = models.build_steve(config)
  num_true = savi_evaluate.num_true_ids(config.data)
  num_slots = config.steve.num_slots
  resolution = tuple(config.data.resolution)

  def evaluate_chunk(steve_params, video, segmentation, frame_valid, carry):
    _, masks, carry = model.apply(
        {'params': steve_params}, frames_to_model(video),
        carry, method=STEVE.encode)
    pred_ids = jnp.argmax(upsample_masks(masks, resolution), axis=2)
    # Ids outside [0, C) are not counted: that drops the padded frames.
    true_ids = jnp.where(frame_valid[..., None, None],
                         segmentation.astype(jnp.int32), -1)
    per_frame = metrics_lib.contingency_table(
        true_ids.reshape(-1, 1, *resolution),
        pred_ids.reshape(-1, 1, *resolution), num_true, num_slots)
    fg_ari = metrics_lib.ari_from_contingency(per_frame,
                                              ignore_background=True)
    batch, time = video.shape[:2]
    iou, present = metrics_lib.fg_iou_matrix(
        true_ids.reshape(-1, 1, *resolution),
        pred_ids.reshape(-1, 1, *resolution), num_true, num_slots)
    out = {
        'table': per_frame.reshape(batch, time, *per_frame.shape[1:]).sum(1),
        'fg_ari_frame_sum': jnp.where(fg_ari.valid, fg_ari.value, 0.0
                                      ).reshape(batch, time).sum(1),
        'fg_ari_frame_count': fg_ari.valid.reshape(batch, time).sum(1),
        'iou': iou.reshape(batch, time, *iou.shape[1:]),
        'present': present.reshape(batch, time, *present.shape[1:])
                   & frame_valid[..., None],
    }
    return out, carry

  replicated = sharding.replicated_sharding(mesh)
  batched = sharding.batch_sharding(mesh)
  return jax.jit(evaluate_chunk,
                 in_shardings=(replicated,) + (batched,) * 4,
                 out_shardings=(batched, batched))


def evaluate_segmentation(config: ml_collections.ConfigDict, mesh: Mesh,
                          steve_params: Any, source: Any, num_frames: int,
                          **batch_args) -> dict[str, Any]:
  """STEVE's attention-mask segmentation of the first `num_frames` frames of
  every held-out video: FG-ARI pooled per video (as SAVi's) and per frame,
  ARI per video, FG-mIoU per frame."""
  evaluator = make_segmentation_evaluator(config, mesh)
  chunk = config.evaluation.chunk_length
  fg_ari_video, ari_video, miou_frames = [], [], []
  fg_ari_sum, fg_ari_count = 0.0, 0
  for batch in tqdm.tqdm(
      pipeline.eval_batches(source, num_frames=num_frames, **batch_args),
      desc='evaluate STEVE masks', leave=False,
      disable=jax.process_index() != 0):
    mask = sharding.gather_to_host(
        sharding.to_global_batch({'mask': batch['mask']}, mesh))['mask']
    totals, carry = {}, None
    for start in range(0, num_frames, chunk):
      pieces = {field: savi_evaluate._padded_time_slice(batch[field], start,  # pylint: disable=protected-access
                                                         chunk)
                for field in ('video', SEGMENTATION_FIELD)}
      frame_valid = np.arange(start, start + chunk) < num_frames
      pieces['frame_valid'] = np.broadcast_to(
          frame_valid, (len(batch['mask']), chunk)).copy()
      pieces = sharding.to_global_batch(pieces, mesh)
      out, carry = evaluator(steve_params, pieces['video'],
                             pieces[SEGMENTATION_FIELD],
                             pieces['frame_valid'], carry)
      out = sharding.gather_to_host(out)
      for key in ('table', 'fg_ari_frame_sum', 'fg_ari_frame_count'):
        totals[key] = totals.get(key, 0) + out[key]
      # present is False on padded frames, so those frames are not valid.
      score = metrics_lib.hungarian_mean_iou(out['iou'][mask],
                                             out['present'][mask])
      miou_frames += list(np.asarray(score.value)[np.asarray(score.valid)])
    table = totals['table'][mask]
    fg_ari_video += list(np.asarray(metrics_lib.ari_from_contingency(
        table, ignore_background=True).value))
    ari_video += list(np.asarray(metrics_lib.ari_from_contingency(table).value))
    fg_ari_sum += float(totals['fg_ari_frame_sum'][mask].sum())
    fg_ari_count += int(totals['fg_ari_frame_count'][mask].sum())
  return {
      'fg_ari': float(np.nanmean(fg_ari_video)),
      'ari': float(np.nanmean(ari_video)),
      'fg_ari_per_frame': fg_ari_sum / max(fg_ari_count, 1),
      'fg_miou_per_frame': float(np.mean(miou_frames)) if miou_frames
                           else None,
      'num_videos': len(fg_ari_video), 'num_frames': num_frames,
  }


def evaluate(config: ml_collections.ConfigDict, workdir: str,
             mesh: Mesh) -> dict[str, Any]:
  """STEVE masks on the held-out videos + rollouts; writes eval/metrics.json
  and eval/per_step.csv like the SAVi evaluation."""
  steve_workdir.check_float32(config)
  started = time.time()
  eval_config = config.evaluation
  names = tuple(eval_config.metrics)
  with_segmentation = any(n in savi_evaluate.OBJECT_METRICS for n in names)
  lpips_fn = savi_evaluate._lpips_or_none(names)  # pylint: disable=protected-access
  steve_params, steve_step = steve_inference.load_steve_params(
      config, workdir, mesh)
  dvae_params, dvae_step = steve_inference.load_dvae_params(config, workdir, mesh)
  dynamics_names = savi_evaluate.dynamics_to_evaluate(config)
  dynamics_params, dynamics_steps = {}, {}
  for name in dynamics_names:
    dynamics_params[name], dynamics_steps[name] = (
        steve_inference.load_dynamics_params(config, workdir, mesh, name))
  # Never mix: the dVAE, STEVE, its slots and every dynamics model descend
  # from each other, and the metrics record which ones they are.
  identity = steve_workdir.evaluation_identity(
      config, workdir, eval_config.split, dvae_step, steve_step,
      dynamics_steps)
  burn_in = config.slotformer.burn_in
  rollout = eval_config.rollout_steps
  stride = config.slotformer.frame_stride
  video_fields = ('video',) + ((SEGMENTATION_FIELD,) if with_segmentation
                               else ())
  source = workdir_lib.slot_source_for(config, workdir, eval_config.split,
                                  video_fields)
  if with_segmentation:
    savi_evaluate._check_has_segmentations(source, names)  # pylint: disable=protected-access
  num_videos = min(len(source), eval_config.num_videos or len(source))
  source = savi_evaluate.evaluation_clips(
      config, source, ('slots',) + video_fields, num_videos)
  local_batch_size = sharding.per_host_batch_size(eval_config.batch_size, mesh)
  shared = dict(batch_size=local_batch_size, fields=('slots',) + video_fields,
                process_index=jax.process_index(),
                process_count=jax.process_count(), max_videos=len(source))
  needed = (burn_in + rollout - 1) * stride + 1

  segmentation_started = time.time()
  steve_results = {}
  if with_segmentation and eval_config.savi_metrics:
    steve_results = evaluate_segmentation(config, mesh, steve_params, source,
                                          needed, **shared)
  steve_results['seconds'] = time.time() - segmentation_started

  rollout_started = time.time()
  evaluator = make_rollout_evaluator(config, mesh, names, lpips_fn,
                                     dynamics_names)
  averager = savi_evaluate._StepAverager()  # pylint: disable=protected-access
  for batch in tqdm.tqdm(
      pipeline.eval_batches(source, num_frames=needed, **shared),
      desc='evaluate rollouts', disable=jax.process_index() != 0):
    mask = batch.pop('mask')
    batch.pop('index')
    for field in batch:
      batch[field] = batch[field][:, ::stride]
    out = sharding.gather_to_host(evaluator(
        dynamics_params, steve_params, dvae_params,
        sharding.to_global_batch(batch, mesh)))
    mask = sharding.gather_to_host(
        sharding.to_global_batch({'mask': mask}, mesh))['mask']
    for method, per_metric in out.items():
      for name, (values, valid) in per_metric.items():
        if name == 'fg_miou':
          score = metrics_lib.hungarian_mean_iou(values, valid)
          values, valid = score.value, score.valid
        averager.add(method, name, np.asarray(values),
                     np.asarray(valid) & mask[None, :])
  results = {
      'slot_model': 'steve',
      'steve': steve_results,
      'savi': {},
      'rollout': averager.results(),
      'protocol': {'split': eval_config.split, 'num_videos': num_videos,
                   'num_clips': len(source), 'clips': eval_config.clips,
                   'burn_in': burn_in, 'rollout_steps': rollout,
                   'frame_stride': stride,
                   'masks': 'decoder cross-attention (rollouts), Slot '
                            'Attention (STEVE on the videos)'},
      'checkpoints': {'dvae_step': dvae_step, 'steve_step': steve_step, **{
          f'{name}_step': step for name, step in dynamics_steps.items()}},
      'identity': identity,
      'seconds': {'steve_segmentation': steve_results.pop('seconds'),
                  'rollout': time.time() - rollout_started,
                  'total': time.time() - started},
  }
  if jax.process_index() == 0:
    savi_evaluate._write_results(savi_evaluate.eval_dir(workdir), results)  # pylint: disable=protected-access
    print(format_table(results))
  return results


def format_table(results: dict[str, Any]) -> str:
  lines = savi_evaluate.format_table(results).splitlines()[:-1]
  steve = results['steve']
  if 'fg_ari' in steve:
    lines.append(
        f'STEVE masks on the whole videos: FG-ARI {steve["fg_ari"]:.4f} (per '
        f'frame {steve["fg_ari_per_frame"]:.4f}), FG-mIoU per frame '
        f'{steve["fg_miou_per_frame"]:.4f}, ARI {steve["ari"]:.4f}')
  return '\n'.join(lines)


# --------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------

_LABELS = {'slotformer': 'SlotFormer', 'slot_lstm': 'Slot-LSTM',
           'copy_last': 'copy-last', REFERENCE: 'STEVE recon.'}


def _mask_overlay(frames: np.ndarray, masks: np.ndarray) -> np.ndarray:
  """frames [..., H, W, 3] in [0, 1], masks [..., N, H, W] -> frames tinted
  by each pixel's argmax slot colour."""
  palette = np.array([[230, 25, 75], [60, 180, 75], [255, 225, 25],
                      [0, 130, 200], [245, 130, 48], [145, 30, 180],
                      [70, 240, 240], [240, 50, 230], [210, 245, 60],
                      [250, 190, 212]], np.float32) / 255.0
  ids = np.argmax(masks, axis=-3)
  colours = palette[ids % len(palette)]
  return 0.5 * frames + 0.5 * colours


def render(config: ml_collections.ConfigDict, workdir: str,
           mesh: Mesh) -> list[str]:
  """Per held-out video: a GIF and a PNG strip of the truth, the generated
  rollouts and their cross-attention segmentation, and STEVE's own
  Slot-Attention segmentation of the real frames."""
  render_config = config.render
  steve_params, steve_step = steve_inference.load_steve_params(
      config, workdir, mesh)
  dvae_params, dvae_step = steve_inference.load_dvae_params(
      config, workdir, mesh)
  dynamics_names = savi_evaluate.dynamics_to_evaluate(config)
  loaded = {
      name: steve_inference.load_dynamics_params(config, workdir, mesh, name)
      for name in dynamics_names}
  dynamics_params = {name: params for name, (params, _) in loaded.items()}
  identity = steve_workdir.evaluation_identity(
      config, workdir, config.evaluation.split, dvae_step, steve_step,
      {name: step for name, (_, step) in loaded.items()})
  if jax.process_index() != 0:
    return []
  burn_in = config.slotformer.burn_in
  rollout = config.evaluation.rollout_steps
  stride = config.slotformer.frame_stride
  source = workdir_lib.slot_source_for(config, workdir, config.evaluation.split,
                                  ('video',))
  count = min(render_config.num_videos, len(source))
  needed = (burn_in + rollout - 1) * stride + 1
  items = [source[i] for i in range(count)]
  slots = np.stack([item['slots'][:needed:stride] for item in items])
  videos = np.stack([item['video'][:needed:stride] for item in items])
  model = models.build_steve(config)
  dynamics = {name: models.build_dynamics(config, name)
              for name in dynamics_names}
  generate = make_generator(config)
  resolution = tuple(config.data.resolution)

  @jax.jit
  def pictures(dynamics_params, steve_params, dvae_params, slots, videos):
    history = slots[:, :burn_in]
    futures = {name: inference.rollout_slots(dynamics_params[name], history,
                                         model=m, num_steps=rollout)
               for name, m in dynamics.items()}
    futures['copy_last'] = inference.copy_last_rollout(history, rollout)
    out = {}
    for name, future in futures.items():
      whole = jnp.concatenate([history, future], axis=1)
      generated = jax.lax.map(
          lambda s: generate(steve_params, dvae_params, s),
          jnp.swapaxes(whole, 0, 1))
      out[name] = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), generated)
    _, masks, _ = model.apply(
        {'params': steve_params}, frames_to_model(videos),
        method=STEVE.encode)
    out['steve_masks'] = upsample_masks(masks, resolution)
    return out

  out = jax.device_get(pictures(jax.device_get(dynamics_params),
                                jax.device_get(steve_params),
                                jax.device_get(dvae_params), slots, videos))
  directory = workdir_lib.render_dir(workdir)
  os.makedirs(directory, exist_ok=True)
  methods = (*dynamics_names, 'copy_last')
  written = []
  for v in range(count):
    truth = videos[v].astype(np.float32) / 255.0
    rows = {'truth': truth,
            'STEVE masks': _mask_overlay(truth, out['steve_masks'][v])}
    for name in methods:
      generated = out[name]
      rows[_LABELS[name]] = generated.recon[v]
      rows[f'{_LABELS[name]} masks'] = _mask_overlay(
          generated.recon[v], generated.alpha_masks[v][..., 0])
    rows = {k: visualize._to_uint8(np.asarray(x)) for k, x in rows.items()}  # pylint: disable=protected-access
    gif_frames = []
    for t in range(burn_in + rollout):
      is_rollout = t >= burn_in
      text = (f'rollout step {t - burn_in + 1}/{rollout}' if is_rollout
              else f'burn-in frame {t + 1}/{burn_in}')
      gif_frames.append(visualize.compose_frame(
          [row[t] for row in rows.values()], list(rows), is_rollout=is_rollout,
          step_text=text, scale=render_config.scale))
    gif_path = os.path.join(directory, f'steve_rollout_{v:03d}.gif')
    imageio.mimsave(gif_path, gif_frames, duration=1.0 / render_config.fps,
                    loop=0)
    png_path = os.path.join(directory, f'steve_rollout_{v:03d}.png')
    visualize._write_strip(png_path, list(rows.values()), burn_in,  # pylint: disable=protected-access
                           render_config)
    written += [gif_path, png_path]
  curves = visualize.write_per_step_figure(workdir, identity)
  if curves:
    written.append(curves)
  write_json_atomic(os.path.join(directory, 'identity.json'),
                    {'identity': identity, 'pictures': sorted(
                        os.path.basename(p) for p in written)})
  print(f'wrote {len(written)} pictures to {directory}')
  return written
