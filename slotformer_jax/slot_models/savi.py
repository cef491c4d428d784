"""SAVi (and stochastic / conditional SAVi) as the slot model:
`config.slot_model='savi'`, settings in `config.savi`.

Stage 1 is one part, `savi` (mode `train_savi`): frame reconstruction (+ the
KL of stochastic SAVi) on clips of `savi.clip_length` frames. Slots decode
through SAVi's spatial-broadcast decoder, whose per-slot alpha masks are the
segmentation and whose frozen copy gives SlotFormer's image loss L_I.

Workdir (inside the stage-1 workdir)::

    savi/checkpoints/<step>/   savi/identity.json (parent: null)
    savi/model_config.json     savi/train_log.jsonl
    slots/<split>/             meta 'parent' = SAVi run id + step

Parameters (`Loaded.params`): {'savi': SAVi's}.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import losses
from slotformer_jax.errors import ConfigError
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import labelled_grid
from slotformer_jax.frames import mask_overlay
from slotformer_jax.frames import model_to_unit
from slotformer_jax.frames import to_uint8
from slotformer_jax.modules import slot_init
from slotformer_jax.modules.slot_init import slot_initializer
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.savi import FrameStep
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.stochastic_savi import GaussianSlotSampler
from slotformer_jax.modules.stochastic_savi import NO_HEAD
from slotformer_jax.modules.stochastic_savi import POSTERIOR_HEADS
from slotformer_jax.modules.transitions import build_predictor
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.runtime import precision
from slotformer_jax.slot_models.base import Decoded
from slotformer_jax.slot_models.base import Part
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.workdir import identity as identity_lib

NAME = 'savi'


# --------------------------------------------------------------------------
# Building the modules from `config.savi`
# --------------------------------------------------------------------------


def build_decoder(decoder: ml_collections.ConfigDict,
                  resolution: tuple[int, int]) -> SpatialBroadcastDecoder:
  """SAVi's spatial-broadcast decoder from `config.savi.decoder`, for frames
  of `resolution` (H, W). Alone (SlotFormer's frozen image decoder), its
  parameters are `savi_params['decoder']`."""
  return SpatialBroadcastDecoder(
      output_resolution=tuple(resolution),
      broadcast_resolution=tuple(decoder.broadcast_resolution),
      features=tuple(decoder.features),
      kernel_size=decoder.kernel_size)


def build_savi(savi: ml_collections.ConfigDict,
               resolution: tuple[int, int]) -> SAVi:
  """SAVi (stochastic when `savi.stochastic`, conditional when
  `savi.initial_slots` is 'boxes' / 'points') from `config.savi`, for frames
  of `resolution` (H, W)."""
  if savi.posterior_head not in POSTERIOR_HEADS:
    raise ValueError(f'posterior_head must be one of {POSTERIOR_HEADS}, '
                     f'got {savi.posterior_head!r}')
  if savi.stochastic and savi.posterior_head == NO_HEAD:
    raise ValueError("stochastic SAVi samples from its posterior head: set "
                     "posterior_head to 'linear' or 'mlp'")
  epsilon = savi.layer_norm_epsilon
  posterior_head = None
  if savi.posterior_head != NO_HEAD:
    posterior_head = GaussianSlotSampler(
        savi.prior_sigma, kind=savi.posterior_head,
        stochastic=savi.stochastic, layer_norm_epsilon=epsilon)
  predictor = savi.predictor
  return SAVi(
      encoder=CNNEncoder(
          features=tuple(savi.encoder.features),
          kernel_size=savi.encoder.kernel_size,
          strides=tuple(savi.encoder.strides),
          output_size=savi.encoder.output_size,
          padding=savi.encoder.padding, layer_norm_epsilon=epsilon),
      initializer=slot_initializer(savi.initial_slots, savi.num_slots,
                                   savi.slot_size),
      frame_step=FrameStep(
          corrector=SlotAttention(savi.slot_attention.num_iterations,
                                  savi.slot_attention.mlp_size,
                                  layer_norm_epsilon=epsilon),
          predictor=build_predictor(
              predictor.kind, num_layers=predictor.num_layers,
              num_heads=predictor.num_heads, mlp_size=predictor.mlp_size,
              lstm_size=predictor.lstm_size, pre_norm=predictor.pre_norm,
              dropout_rate=predictor.dropout_rate,
              layer_norm_epsilon=epsilon),
          posterior_head=posterior_head),
      decoder=build_decoder(savi.decoder, resolution))


def model_fields(savi: ml_collections.ConfigDict,
                 data: ml_collections.ConfigDict) -> dict[str, Any]:
  """The settings that determine SAVi's parameter shapes / behaviour."""
  section = savi.to_dict()
  fields = {key: section[key] for key in (
      'num_slots', 'slot_size', 'encoder', 'slot_attention', 'predictor',
      'decoder', 'stochastic', 'initial_slots', 'posterior_head',
      'layer_norm_epsilon')}
  fields['resolution'] = list(data.resolution)
  # A SAVi that saw BGR frames (the official CLEVRER ones) needs
  # BGR frames; recorded only when not RGB, so older workdirs still match.
  if data.channel_order != 'rgb':
    fields['channel_order'] = data.channel_order
  return identity_lib.plain(fields)


def is_conditional(savi: ml_collections.ConfigDict) -> bool:
  """Conditional SAVi: slots start from the first frame's boxes / points."""
  return savi.initial_slots in slot_init.CONDITIONAL


def decoder_resolutions(broadcast: tuple[int, int], num_layers: int
                        ) -> list[tuple[int, int]]:
  """The frame sizes SpatialBroadcastDecoder can produce: its layers double
  the broadcast grid until the frame height is reached (the rest keep the
  size), so (h * 2^k, w * 2^k) for k = 0 .. num_layers."""
  height, width = broadcast
  return [(height * 2**k, width * 2**k) for k in range(num_layers + 1)]


# --------------------------------------------------------------------------
# The slot model
# --------------------------------------------------------------------------


class Savi(SlotModel):
  """SAVi / stochastic SAVi / conditional SAVi (`config.savi`)."""

  name = NAME
  label = 'SAVi'
  mask_source = 'decoder alpha masks'

  def __init__(self, config: ml_collections.ConfigDict):
    super().__init__(config)
    self.section = config.savi
    self.resolution = tuple(config.data.resolution)

  # Built on first use, so that the config checks (`check_config`,
  # config/checks.py) report a bad value as one line before any module is.
  @functools.cached_property
  def model(self) -> Any:
    return build_savi(self.section, self.resolution)

  @property
  def decoder(self) -> Any:
    return self.model.decoder  # alone: params['savi']['decoder']

  @property
  def slot_shape(self) -> tuple[int, int]:
    return self.section.num_slots, self.section.slot_size

  @property
  def conditioning_fields(self) -> tuple[str, ...]:
    return ('boxes',) if is_conditional(self.section) else ()

  @property
  def parts(self) -> tuple[Part, ...]:
    savi, config = self.section, self.config
    clip = np.zeros((1, savi.clip_length, *self.resolution, 3), np.float32)
    # The shapes of the conditional initialiser do not depend on the number
    # of box rows.
    boxes = ({'boxes': np.zeros((1, savi.num_slots - 1, 4), np.float32)}
             if is_conditional(savi) else {})
    loss = functools.partial(
        losses.savi_loss, model=self.model,
        kl_weight=savi.kl_weight if savi.stochastic else 0.0)
    return (Part(
        name=NAME, label=self.label, module=self.model, section=savi,
        example=(clip,), example_kwargs=boxes,
        loss=precision.with_compute_dtype(loss, config.compute_dtype),
        batch_fields=('video',) + self.conditioning_fields,
        clip_length=savi.clip_length,
        model_fields=model_fields(savi, config.data),
        identity_fields=identity_lib.stage_fields(
            config.seed, config.data.to_dict(), NAME, savi.to_dict()),
        init=savi.init, images=_training_images(self.model)),)

  def check_config(self, stages: frozenset[str]) -> list[str]:
    """The frame size the decoder can produce (known from the config alone;
    found at the first training step otherwise, after making the data)."""
    del stages
    resolution, decoder = self.resolution, self.section.decoder
    sizes = decoder_resolutions(decoder.broadcast_resolution,
                                len(decoder.features))
    if resolution in sizes:
      return []
    listed = ', '.join(f'{h}x{w}' for h, w in sizes)
    return [
        f'data.resolution {resolution} is not a size the SAVi decoder can '
        f'produce: it doubles its {tuple(decoder.broadcast_resolution)} '
        f'broadcast grid (savi.decoder.broadcast_resolution) once per '
        f'layer, up to {len(decoder.features)} layers '
        f'(savi.decoder.features), so {listed} work; change '
        'data.resolution or savi.decoder.broadcast_resolution']

  def check_data(self, source: Any, split: str) -> None:
    """Conditional SAVi needs boxes in the data and a slot per box row plus
    the background slot."""
    if not is_conditional(self.section) or not len(source):
      return
    item = source[0]
    option = f'savi.initial_slots={self.section.initial_slots!r}'
    if 'boxes' not in item:
      raise ConfigError(
          f'{option} conditions the slots on boxes, but the {split} videos '
          f'of data.name={self.config.data.name!r} have none; use '
          "--config.savi.initial_slots=learned")
    rows = item['boxes'].shape[1]
    if rows + 1 > self.section.num_slots:
      raise ConfigError(
          f'{option}: the data has {rows} box rows, which with the '
          f'background slot need savi.num_slots >= {rows + 1} (it is '
          f'{self.section.num_slots}); set --config.savi.num_slots='
          f'{rows + 1}')

  def encode(self, params: Any, video: jax.Array, rng: jax.Array,
             carry: Any) -> tuple[jax.Array, Any]:
    boxes = None
    if isinstance(carry, dict):  # a fresh start, conditioned on these
      boxes, carry = carry.get('boxes'), None
    slots, _, carry = self.model.apply(
        {'params': params[NAME]}, self.to_model(video), carry,
        method=SAVi.encode, rngs={'sample': rng}, boxes=boxes)
    return slots, carry

  def decode(self, params: Any, slots: jax.Array,
             presence: jax.Array | None = None) -> Decoded:
    decoded = self.decoder.apply({'params': params[NAME]['decoder']}, slots,
                                 presence)
    return Decoded(recon=model_to_unit(decoded.recon),
                   alpha_masks=decoded.alpha_masks,
                   rgb=model_to_unit(decoded.rgb))

  def observe(self, params: Any, slots: jax.Array, video: jax.Array,
              carry: Any) -> tuple[jax.Array, jax.Array, Any]:
    """SAVi's account of the real frames is its extracted slots decoded (a
    frame at a time: one frame's decoder activations in memory)."""
    del video

    def frame(frame_slots):  # [B, N, D]
      decoded = self.decode(params, frame_slots)
      return decoded.alpha_masks[..., 0], decoded.recon

    alpha, recon = jax.lax.map(frame, jnp.swapaxes(slots, 0, 1))
    return jnp.swapaxes(alpha, 0, 1), jnp.swapaxes(recon, 0, 1), carry

  def image_decoder(self, params: Any) -> tuple[Any, Any]:
    return self.decoder, params[NAME]['decoder']


def _training_images(model: SAVi):
  """TensorBoard pictures of the first clip of a training batch: its frames,
  SAVi's reconstruction and the slot masks over the frames."""

  @jax.jit
  def run(params, video, boxes):
    output = model.apply({'params': params}, frames_to_model(video),
                         boxes=boxes)
    return (model_to_unit(output.decoded.recon),
            output.decoded.alpha_masks[..., 0])

  def images(params, batch):
    video = batch['video'][:1]
    boxes = batch['boxes'][:1, 0] if 'boxes' in batch else None
    recon, alpha = jax.device_get(run(params, video, boxes))
    frames = np.asarray(video[0], np.float32) / 255.0
    return {'reconstruction': labelled_grid({
        'input': video[0],
        'reconstruction': to_uint8(recon[0]),
        'slot masks': to_uint8(mask_overlay(frames, alpha[0])),
    })}

  return images
