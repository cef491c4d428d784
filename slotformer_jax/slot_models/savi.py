"""SAVi (and stochastic / conditional SAVi) as the slot model:
`config.slot_model='savi'`, settings in `config.savi`.

Stage 1 is one part, `savi` (mode `train_savi`): reconstruction of its
targets (`savi.targets`: the frames, or SAVi's optical flow and depth; see
slotformer_jax/targets.py for their batch fields) (+ the KL of stochastic
SAVi) on clips of `savi.clip_length` frames. Slots decode through SAVi's
spatial-broadcast decoder, whose per-slot alpha masks are the segmentation
and whose frozen copy gives SlotFormer's image loss L_I (on the same
targets). The encoder is a CNN or SAVi++'s ResNet-34 (+ Transformer):
`savi.encoder.kind`.

Workdir (inside the stage-1 workdir)::

    savi/checkpoints/<step>/   savi/identity.json (parent: null)
    savi/model_config.json     savi/train_log.jsonl
    slots/<split>/             meta 'parent' = SAVi run id + step

Parameters (`Loaded.params`): {'savi': SAVi's}.
"""

from __future__ import annotations

import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import datasets
from slotformer_jax import losses
from slotformer_jax import targets as targets_lib
from slotformer_jax.data import augment
from slotformer_jax.data import flow_depth
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
from slotformer_jax.modules.encoders import ConvStack
from slotformer_jax.modules.encoders import FrameEncoder
from slotformer_jax.modules.resnet import ResNet
from slotformer_jax.modules.resnet import RESNET34_STAGES
from slotformer_jax.modules.transformer import TransformerEncoder
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


# Fields of `config.savi` added after workdirs were made (issue 51): at the
# value their absence stands for (identity.ADDED_FIELDS) they are left out
# of the run identity and model_config.json, which stay what they were.
_ADDED = ('targets', 'encoder.kind', 'encoder.mlp_size',
          'encoder.transformer', 'random_resized_crop',
          'slot_attention.qkv_size', 'predictor.qkv_size')


def target_names(savi: ml_collections.ConfigDict) -> tuple[str, ...]:
  """`savi.targets` (RGB frames for a config from before the field)."""
  return tuple(savi.get('targets', targets_lib.DEFAULT))


def build_decoder(decoder: ml_collections.ConfigDict,
                  resolution: tuple[int, int],
                  targets: tuple[str, ...] | None = None
                  ) -> SpatialBroadcastDecoder:
  """SAVi's spatial-broadcast decoder from `config.savi.decoder`, for frames
  of `resolution` (H, W), reconstructing `targets` (`config.savi.targets`;
  None: RGB frames). Alone (SlotFormer's frozen image decoder), its
  parameters are `savi_params['decoder']`."""
  return SpatialBroadcastDecoder(
      output_resolution=tuple(resolution),
      broadcast_resolution=tuple(decoder.broadcast_resolution),
      features=tuple(decoder.features),
      kernel_size=decoder.kernel_size,
      targets=targets_lib.channels(targets))


def build_encoder(encoder: ml_collections.ConfigDict,
                  layer_norm_epsilon: float) -> nn.Module:
  """The per-frame encoder from `config.savi.encoder`: today's CNNEncoder
  for a CNN without a Transformer (its parameter tree), else a FrameEncoder
  of the CNN's conv layers or SAVi++'s ResNet-34."""
  kind = encoder.get('kind', 'cnn')
  transformer = encoder.get('transformer')
  num_layers = transformer.num_layers if transformer is not None else 0
  if kind == 'cnn' and not num_layers:
    return CNNEncoder(
        features=tuple(encoder.features), kernel_size=encoder.kernel_size,
        strides=tuple(encoder.strides), output_size=encoder.output_size,
        padding=encoder.padding, layer_norm_epsilon=layer_norm_epsilon,
        mlp_size=encoder.get('mlp_size'))
  if kind == 'cnn':
    backbone = ConvStack(
        features=tuple(encoder.features), kernel_size=encoder.kernel_size,
        strides=tuple(encoder.strides), padding=encoder.padding)
  elif kind == 'resnet34':
    backbone = ResNet(stage_sizes=RESNET34_STAGES)
  else:
    raise ValueError(f"encoder kind must be 'cnn' or 'resnet34', got "
                     f'{kind!r}')
  return FrameEncoder(
      backbone=backbone, output_size=encoder.output_size,
      mlp_size=encoder.get('mlp_size'),
      transformer=TransformerEncoder(
          num_layers=num_layers, num_heads=transformer.num_heads,
          mlp_size=transformer.mlp_size, pre_norm=True,
          layer_norm_epsilon=layer_norm_epsilon) if num_layers else None,
      qkv_size=transformer.qkv_size if num_layers else encoder.output_size,
      layer_norm_epsilon=layer_norm_epsilon)


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
      encoder=build_encoder(savi.encoder, epsilon),
      initializer=slot_initializer(savi.initial_slots, savi.num_slots,
                                   savi.slot_size),
      frame_step=FrameStep(
          corrector=SlotAttention(savi.slot_attention.num_iterations,
                                  savi.slot_attention.mlp_size,
                                  qkv_size=savi.slot_attention.get('qkv_size'),
                                  layer_norm_epsilon=epsilon),
          predictor=build_predictor(
              predictor.kind, num_layers=predictor.num_layers,
              num_heads=predictor.num_heads, mlp_size=predictor.mlp_size,
              lstm_size=predictor.lstm_size, pre_norm=predictor.pre_norm,
              dropout_rate=predictor.dropout_rate,
              layer_norm_epsilon=epsilon,
              qkv_size=predictor.get('qkv_size')),
          posterior_head=posterior_head),
      decoder=build_decoder(savi.decoder, resolution, target_names(savi)))


def model_fields(savi: ml_collections.ConfigDict,
                 data: ml_collections.ConfigDict) -> dict[str, Any]:
  """The settings that determine SAVi's parameter shapes / behaviour."""
  section = _without_added_defaults(savi)
  fields = {key: section[key] for key in (
      'num_slots', 'slot_size', 'encoder', 'slot_attention', 'predictor',
      'decoder', 'stochastic', 'initial_slots', 'posterior_head',
      'layer_norm_epsilon')}
  if 'targets' in section:  # recorded only when not RGB (older workdirs)
    fields['targets'] = section['targets']
  fields['resolution'] = list(data.resolution)
  # A SAVi that saw BGR frames (the official CLEVRER ones) needs
  # BGR frames; recorded only when not RGB, so older workdirs still match.
  if data.channel_order != 'rgb':
    fields['channel_order'] = data.channel_order
  return identity_lib.plain(fields)


def _without_added_defaults(savi: ml_collections.ConfigDict
                            ) -> dict[str, Any]:
  """`savi.to_dict()` without the `_ADDED` fields that hold the value their
  absence stands for."""
  section = savi.to_dict()
  for name in _ADDED:
    *parents, field = name.split('.')
    node = section
    for key in parents:
      node = node.get(key, {})
    if (field in node and identity_lib.plain(node[field])
        == identity_lib.ADDED_FIELDS[f'{NAME}.{name}']):
      del node[field]
  return section


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
  def targets(self) -> tuple[targets_lib.Target, ...]:
    """What its decoder reconstructs (`savi.targets`)."""
    return targets_lib.of(target_names(self.section))

  @property
  def decodes_pixels(self) -> bool:
    """Frames only when RGB is one of its targets (SAVi reconstructing
    flow / depth alone is scored on its masks)."""
    return targets_lib.RGB in self.targets

  @property
  def image_loss_fields(self) -> tuple[str, ...]:
    return tuple(target.field for target in self.targets)

  @property
  def parts(self) -> tuple[Part, ...]:
    savi, config = self.section, self.config
    # The frames feed the encoder whatever the targets; the other targets'
    # fields are what the loss compares with. A cropped clip reads the
    # backward flow in pixels, rescaled with the crop, and gets `flow` after
    # (`_cropped`).
    crop = augment.from_config(savi.get('random_resized_crop'))
    target_fields = tuple(
        flow_depth.BACKWARD_FLOW if crop and t == targets_lib.FLOW
        else t.field for t in self.targets if t != targets_lib.RGB)
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
        batch_fields=('video',) + target_fields + self.conditioning_fields,
        clip_length=savi.clip_length,
        model_fields=model_fields(savi, config.data),
        identity_fields=identity_lib.stage_fields(
            config.seed, config.data.to_dict(), NAME,
            _without_added_defaults(savi)),
        init=savi.init,
        images=_training_images(self.model, self.targets),
        transform=None if crop is None else functools.partial(
            _cropped, crop=crop)),)

  def _missing_fields(self, fields: list[str], videos: str) -> str:
    """The line of target fields the videos lack, with the fix the dataset
    knows (MOVi: convert again; the OBJ3D-like family: generate them)."""
    data = self.config.data
    names = target_names(self.section)
    dataset = datasets.DATASETS.get(data.name)
    fixes = [] if dataset is None else [
        dataset.field_fix(data, field) for field in fields]
    line = (f'savi.targets={names!r} reconstructs '
            f'{", ".join(map(repr, fields))}, but {videos} of '
            f'data.name={data.name!r} have no such field')
    if fixes and all(fixes):
      return f'{line}: {"; ".join(dict.fromkeys(fixes))}'
    return (f'{line} (slotformer_jax/targets.py says what each must hold); '
            "use --config.savi.targets='(\"rgb\",)' or data that has them")

  def check_config(self, stages: frozenset[str]) -> list[str]:
    """At least one target, in the videos when the dataset knows their
    fields without the data (a generated one); the crop's settings; the
    encoder Transformer's width a multiple of its heads; the frame size the
    decoder can produce (known from the config alone; found at the first
    training step otherwise, after making the data)."""
    del stages
    problems = []
    names = target_names(self.section)
    if not names:
      problems.append(
          "savi.targets=() names no target; e.g. --config.savi.targets="
          "'(\"rgb\",)' or '(\"flow\", \"depth\")'")
    dataset = datasets.DATASETS.get(self.config.data.name)
    served = None
    if dataset is not None and names:
      try:
        served = dataset.served_fields(self.config.data)
      except (ValueError, TypeError):
        served = None  # bad generation parameters: the data checks say so
    if served is not None:
      missing = [targets_lib.TARGETS[name].field for name in names
                 if name in targets_lib.TARGETS
                 and targets_lib.TARGETS[name].field not in served]
      if missing:
        problems.append(self._missing_fields(missing, 'the videos'))
    problems += augment.config_problems(self.section.get(
        'random_resized_crop'), 'savi.random_resized_crop')
    transformer = self.section.encoder.get('transformer')
    if (transformer is not None and transformer.num_layers > 0
        and transformer.qkv_size % transformer.num_heads):
      problems.append(
          f'savi.encoder.transformer.qkv_size={transformer.qkv_size} must be '
          f'a multiple of its num_heads={transformer.num_heads}')
    predictor = self.section.predictor
    qkv_size = predictor.get('qkv_size')
    if (qkv_size and predictor.kind != 'residual_mlp'
        and qkv_size % predictor.num_heads):
      problems.append(
          f'savi.predictor.qkv_size={qkv_size} must be a multiple of its '
          f'num_heads={predictor.num_heads}')
    resolution, decoder = self.resolution, self.section.decoder
    sizes = decoder_resolutions(decoder.broadcast_resolution,
                                len(decoder.features))
    if resolution in sizes:
      return problems
    listed = ', '.join(f'{h}x{w}' for h, w in sizes)
    return problems + [
        f'data.resolution {resolution} is not a size the SAVi decoder can '
        f'produce: it doubles its {tuple(decoder.broadcast_resolution)} '
        f'broadcast grid (savi.decoder.broadcast_resolution) once per '
        f'layer, up to {len(decoder.features)} layers '
        f'(savi.decoder.features), so {listed} work; change '
        'data.resolution or savi.decoder.broadcast_resolution']

  def check_data(self, source: Any, split: str) -> None:
    """Its targets need their fields in the data; conditional SAVi needs
    boxes and a slot per box row plus the background slot."""
    if not len(source):
      return
    item = source[0]
    missing = [t.field for t in self.targets if t.field not in item]
    if missing:
      raise ConfigError(self._missing_fields(missing, f'the {split} videos'))
    if not is_conditional(self.section):
      return
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
    if decoded.recon is None:  # RGB is not one of its targets
      return Decoded(alpha_masks=decoded.alpha_masks,
                     targets=decoded.targets)
    return Decoded(recon=model_to_unit(decoded.recon),
                   alpha_masks=decoded.alpha_masks,
                   rgb=model_to_unit(decoded.rgb), targets=decoded.targets)

  def observe(self, params: Any, slots: jax.Array, video: jax.Array,
              carry: Any) -> tuple[jax.Array, jax.Array | None, Any]:
    """SAVi's account of the real frames is its extracted slots decoded (a
    frame at a time: one frame's decoder activations in memory)."""
    del video

    def frame(frame_slots):  # [B, N, D]
      decoded = self.decode(params, frame_slots)
      return decoded.alpha_masks[..., 0], decoded.recon

    alpha, recon = jax.lax.map(frame, jnp.swapaxes(slots, 0, 1))
    if recon is not None:  # None: RGB is not one of its targets
      recon = jnp.swapaxes(recon, 0, 1)
    return jnp.swapaxes(alpha, 0, 1), recon, carry

  def image_decoder(self, params: Any) -> tuple[Any, Any]:
    return self.decoder, params[NAME]['decoder']


def _cropped(clip: dict[str, np.ndarray], rng: np.random.Generator, *,
             crop: augment.RandomResizedCrop) -> dict[str, np.ndarray]:
  """A training clip through SAVi++'s random resized crop, then with its
  backward flow as the targets' `flow` (data/augment.py)."""
  return flow_depth.to_contract(crop(clip, rng))


def _training_images(model: SAVi, targets: tuple[targets_lib.Target, ...]):
  """TensorBoard pictures of the first clip of a training batch: its frames,
  SAVi's reconstruction of each target (the frames; flow in SAVi's colours;
  depth as a grey map with its range in the label, the data's above it) and
  the slot masks over the frames."""

  @jax.jit
  def run(params, video, boxes):
    output = model.apply({'params': params}, frames_to_model(video),
                         boxes=boxes)
    decoded = output.decoded
    recon = (None if decoded.recon is None
             else model_to_unit(decoded.recon))
    return recon, decoded.targets, decoded.alpha_masks[..., 0]

  def images(params, batch):
    video = batch['video'][:1]
    boxes = batch['boxes'][:1, 0] if 'boxes' in batch else None
    recon, others, alpha = jax.device_get(run(params, video, boxes))
    frames = np.asarray(video[0], np.float32) / 255.0
    rows = {'input': video[0]}
    if recon is not None:
      rows['reconstruction'] = to_uint8(recon[0])
    truth = {t.name: np.asarray(batch[t.field][0]) for t in targets
             if t != targets_lib.RGB and t.field in batch}
    decoded = {name: values[0] for name, values in (others or {}).items()}
    for label, row in targets_lib.picture_rows(targets, truth,
                                               decoded).items():
      rows[label] = to_uint8(row)
    rows['slot masks'] = to_uint8(mask_overlay(frames, alpha[0]))
    return {'reconstruction': labelled_grid(rows)}

  return images
