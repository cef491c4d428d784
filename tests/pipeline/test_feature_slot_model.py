"""A third slot model from this one file, without editing the package.

`FeatureSavi` is SAVi's parts (its CNN encoder, learned initial slots and
the corrector/predictor step) with an MLP feature decoder in the style of
DINOSAUR / VideoSAUR: every slot is broadcast over the feature grid, an MLP
gives each position a feature vector and an alpha logit, and the alpha-mixed
features are trained to reconstruct target features (here a frozen, randomly
initialised CNN stands in for DINO). It decodes no pixels. Registered below,
it runs through the tiny pipeline: training, slot extraction, SlotFormer on its
slots, and the evaluation, whose frame metrics (PSNR, SSIM,
LPIPS) are skipped and said so while the object metrics are scored on its
alpha masks; the pictures of frames are skipped with a line.
"""

from __future__ import annotations

import functools
import json
import os
import pathlib
from typing import Any

from flax import struct
import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections

from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from slotformer_jax import slot_models
from slotformer_jax import stages
from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.encoders import feature_grid
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.slot_models.base import Decoded
from slotformer_jax.slot_models.base import Part
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.slot_models.savi import build_savi
from slotformer_jax.workdir import identity as identity_lib

NAME = 'feature_savi'


@struct.dataclass
class FeatureDecoded:
  """features [..., M, C] (the alpha-mixed reconstruction of the feature
  grid), masks [..., N, h, w] (softmax over the N slots)."""

  features: jax.Array
  masks: jax.Array


class MLPFeatureDecoder(nn.Module):
  """slots [..., N, D] -> FeatureDecoded over a `grid` of positions."""

  grid: tuple[int, int]
  features: int
  hidden_size: int

  @nn.compact
  def __call__(self, slots: jax.Array,
               presence: jax.Array | None = None) -> FeatureDecoded:
    height, width = self.grid
    positions = self.param('positions', nn.initializers.normal(0.02),
                           (height * width, slots.shape[-1]))
    x = slots[..., :, None, :] + positions  # [..., N, M, D]
    x = nn.relu(nn.Dense(self.hidden_size, name='hidden')(x))
    out = nn.Dense(self.features + 1, name='out')(x)
    features, logits = out[..., :-1], out[..., -1]  # [..., N, M, C], [.., N, M]
    if presence is not None:  # absent slots leave the softmax
      logits = jnp.where(presence[..., None], logits, -1e9)
    alpha = jax.nn.softmax(logits, axis=-2)
    return FeatureDecoded(
        features=jnp.sum(alpha[..., None] * features, axis=-3),
        masks=alpha.reshape(*alpha.shape[:-1], height, width))


class FeatureSAViModule(nn.Module):
  """SAVi with the feature decoder, and the frozen target encoder."""

  savi: SAVi
  target: CNNEncoder

  def __call__(self, video: jax.Array, *, deterministic: bool = True
               ) -> tuple[jax.Array, jax.Array]:
    """video [B, T, H, W, 3] in [-1, 1] -> (reconstructed features, target
    features), both [B, T, M, C]; the target takes no gradient."""
    output = self.savi(video, deterministic=deterministic)
    batch, time = video.shape[:2]
    target = self.target(video.reshape(batch * time, *video.shape[2:]))
    target = jax.lax.stop_gradient(target.reshape(batch, time,
                                                  *target.shape[1:]))
    return output.decoded.features, target


def feature_loss(params: Any, batch: dict[str, jax.Array], frozen: Any,
                 rng: jax.Array, *, model: FeatureSAViModule,
                 to_model) -> tuple[jax.Array, dict[str, jax.Array]]:
  """MSE between the decoded and the target features."""
  del frozen
  recon, target = model.apply({'params': params}, to_model(batch['video']),
                              deterministic=False, rngs={'dropout': rng})
  loss = jnp.mean(jnp.square(recon - target))
  return loss, {'feature_loss': loss}


@slot_models.register
class FeatureSavi(SlotModel):
  """SAVi's parts + an MLP feature decoder (`config.feature_savi`)."""

  name = NAME
  label = 'FeatureSAVi'
  mask_source = 'MLP feature decoder alpha masks (feature grid, upsampled)'
  compute_dtypes = ('float32',)

  def __init__(self, config: ml_collections.ConfigDict):
    super().__init__(config)
    section = config.feature_savi
    self.section = section
    self.resolution = tuple(config.data.resolution)
    grid = feature_grid(self.resolution, section.encoder.strides)
    self.decoder = MLPFeatureDecoder(grid=grid, features=section.target_size,
                                     hidden_size=section.decoder_hidden)
    savi = build_savi(section, self.resolution).clone(decoder=self.decoder)
    self.model = FeatureSAViModule(savi=savi, target=CNNEncoder(
        features=tuple(section.encoder.features),
        kernel_size=section.encoder.kernel_size,
        strides=tuple(section.encoder.strides),
        output_size=section.target_size))

  @property
  def slot_shape(self) -> tuple[int, int]:
    return self.section.num_slots, self.section.slot_size

  @property
  def decodes_pixels(self) -> bool:
    return False

  @property
  def parts(self) -> tuple[Part, ...]:
    section, config = self.section, self.config
    clip = jnp.zeros((1, section.clip_length, *self.resolution, 3))
    return (Part(
        name=NAME, label=self.label, module=self.model, section=section,
        example=(clip,),
        loss=functools.partial(feature_loss, model=self.model,
                               to_model=self.to_model),
        batch_fields=('video',), clip_length=section.clip_length,
        model_fields=identity_lib.plain(dict(
            section.to_dict(), resolution=list(self.resolution))),
        identity_fields=identity_lib.stage_fields(
            config.seed, config.data.to_dict(), NAME, section.to_dict()),
        init=section.init),)

  def encode(self, params, video, rng, carry):
    del rng  # deterministic
    slots, _, carry = self.model.apply(
        {'params': params[NAME]}, self.to_model(video), carry,
        method=lambda module, video, carry: module.savi.encode(video, carry))
    return slots, carry

  def decode(self, params, slots, presence=None) -> Decoded:
    decoded = self.decoder.apply(
        {'params': params[NAME]['savi']['decoder']}, slots, presence)
    masks = jax.image.resize(
        decoded.masks, (*decoded.masks.shape[:-2], *self.resolution),
        'bilinear')
    return Decoded(alpha_masks=masks[..., None])  # no recon: no pixels

  def observe(self, params, slots, video, carry):
    """Its own masks of the real frames: its extracted slots decoded."""
    del video
    return self.decode(params, slots).alpha_masks[..., 0], None, carry


def feature_config(data_dir) -> ml_collections.ConfigDict:
  """The micro SAVi pipeline with `slot_model='feature_savi'`."""
  config = micro_config('savi', data_dir)
  config.slot_model = NAME
  config.feature_savi = ml_collections.ConfigDict(config.savi.to_dict())
  config.feature_savi.decoder_hidden = 16
  config.feature_savi.target_size = 8
  config.slotformer.image_loss_weight = 0.0  # no pixels: L_S alone
  config.slot_lstm.train = False
  return config


def test_a_slot_model_from_one_test_file_runs_the_pipeline(tmp_path, caplog):
  package = pathlib.Path(slot_models.__file__).parent.parent
  assert not any(NAME in path.read_text() for path in package.rglob('*.py'))
  assert slot_models.SLOT_MODELS[NAME] is FeatureSavi
  config = feature_config(tmp_path / 'data')
  workdir = str(tmp_path / 'run')
  mesh = sharding.make_mesh()
  table = stages.stage_table(Run.create(config, workdir, mesh))
  assert list(table)[:3] == ['prepare_data', 'train_feature_savi',
                             'extract_slots']
  with caplog.at_level('INFO'):
    results = run_stages(config, workdir, mesh)

  evaluated = results['evaluate']
  assert evaluated['slot_model'] == NAME
  methods = evaluated['rollout']
  assert list(methods) == ['slotformer', 'copy_last',
                           'feature_savi_reconstruction']
  for method, per_metric in methods.items():
    assert set(per_metric) == {'ari', 'fg_ari', 'fg_miou', 'ar'}, method
    assert len(per_metric['fg_ari']['per_step']) == (
        config.evaluation.rollout_steps)
  why = 'FeatureSAVi decodes no pixels'
  assert evaluated['protocol']['skipped_metrics'] == {
      'psnr': why, 'ssim': why, 'lpips': why}
  assert 'psnr' not in evaluated[NAME] and 'fg_ari' in evaluated[NAME]
  with open(os.path.join(workdir, 'eval', 'metrics.json')) as f:
    assert json.load(f)['protocol']['skipped_metrics']['psnr'] == why
  assert results['render'] == [] and results['explore'] is None
  assert 'render skipped: FeatureSAVi decodes no pixels' in caplog.text

  # One chain: its slots, and SlotFormer trained on them, descend from it.
  run = Run.create(config, workdir, mesh)
  encoder = identity_lib.read_identity(run.paths.model(NAME))
  assert run.stage1.slots_parent == {f'{NAME}_run_id': encoder['run_id'],
                                     f'{NAME}_step': 4}
  assert evaluated['identity']['slotformer']['parent'] == (
      run.stage1.slots_parent)
