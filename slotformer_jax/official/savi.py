"""The official SAVi / stochastic SAVi family
(slotformer/base_slots/models/savi.py: StoSAVi) -> the `savi/` stage."""

from __future__ import annotations

from typing import Any

import ml_collections
import numpy as np

from slotformer_jax.modules import transitions
from slotformer_jax.modules.stochastic_savi import LINEAR_HEAD
from slotformer_jax.modules.stochastic_savi import MLP_HEAD
from slotformer_jax.official import common
from slotformer_jax.official import layers
from slotformer_jax.official.common import Converted
from slotformer_jax.official.common import Family
from slotformer_jax.official.layers import StateDictMapper
from slotformer_jax.slot_models import chain
from slotformer_jax.slot_models.savi import NAME as SAVI
from slotformer_jax.slot_models.savi import Savi


def abstract_params(config: ml_collections.ConfigDict) -> Any:
  return chain.param_shapes(Savi(config).part(SAVI))


def _map_savi_predictor(m: StateDictMapper, config: ml_collections.ConfigDict,
                        target: str):
  """The official predictors (slotformer/base_slots/models/predictor.py).

  The config decides which parts to read, so a checkpoint part the config
  lacks is reported as unknown keys with the field to change.
  """
  predictor = config.savi.predictor
  field = 'config.savi.predictor (kind / num_layers / mlp_size / lstm_size)'
  if predictor.kind == transitions.RESIDUAL_MLP:  # ResidualMLPPredictor
    layers.layer_norm(m, 'predictor.ln', f'{target}/norm', field)
    layers.linear(m, 'predictor.mlp.0', f'{target}/hidden', field)
    layers.linear(m, 'predictor.mlp.2', f'{target}/out', field)
    return
  if predictor.kind == transitions.TRANSFORMER_LSTM:  # RNNPredictorWrapper
    transformer = 'predictor.base_predictor.transformer_encoder'
    layers.lstm(m, 'predictor.rnn', f'{target}/lstm', field)
    layers.linear(m, 'predictor.out_projector', f'{target}/lstm_out', field)
  else:
    transformer = 'predictor.transformer_encoder'
  # Read as many layers as the config builds: extra ones stay unknown keys.
  for i in range(predictor.num_layers):
    layers.transformer_encoder_layer(
        m, f'{transformer}.layers.{i}', f'{target}/transformer/block_{i}',
        field, num_heads=predictor.num_heads)


def _map_posterior_head(m: StateDictMapper, config: ml_collections.ConfigDict,
                        target: str):
  """`kernel_dist_layer`: (mean, log-variance) of the initial slots, applied
  before Slot Attention in every official SAVi (the deterministic ones keep
  the mean)."""
  head = config.savi.posterior_head
  field = 'config.savi.posterior_head'
  if head == MLP_HEAD:  # kernel_mlp=True
    layers.linear(m, 'kernel_dist_layer.0', f'{target}/hidden', field)
    layers.layer_norm(m, 'kernel_dist_layer.1', f'{target}/norm', field)
    layers.linear(m, 'kernel_dist_layer.3', f'{target}/statistics', field)
  elif head == LINEAR_HEAD:  # kernel_mlp=False
    layers.linear(m, 'kernel_dist_layer.0', f'{target}/statistics', field)
  # 'none': the head's keys stay unknown, naming the field.


def convert_savi(state_dict: dict[str, np.ndarray],
                 config: ml_collections.ConfigDict) -> Converted:
  """Official StoSAVi (deterministic when trained with kld_method='none')."""
  common.require(config, 'slot_model', 'savi', 'is a SAVi')
  common.require(config, 'savi.initial_slots', 'learned',
          'starts from one learned vector per slot (init_latents)')
  common.require(config, 'savi.layer_norm_epsilon', common.PYTORCH_LN_EPSILON,
          "uses PyTorch's LayerNorm epsilon")
  common.require(config, 'savi.targets', ('rgb',), 'reconstructs RGB frames')
  common.require(config, 'savi.encoder.kind', 'cnn', 'encodes with a CNN')
  common.require(config, 'savi.encoder.strides', common.official_encoder_strides(config),
          f'strides its encoder so at {tuple(config.data.resolution)}')
  if max(config.savi.encoder.strides) > 1:
    common.require(config, 'savi.encoder.padding', 'pytorch',
            'pads its strided convolution by K // 2 on every side')
  m = StateDictMapper(state_dict)
  latents = m.take('init_latents')  # [1, N, D]
  if latents is not None:
    m.put('initial_slots', latents[0], 'init_latents', latents.shape,
          'config.savi.num_slots / slot_size')
  common.map_cnn_encoder(m, config)
  _map_posterior_head(m, config, 'frame_step/posterior_head')
  common.map_slot_attention(m, 'frame_step/corrector')
  _map_savi_predictor(m, config, 'frame_step/predictor')
  common.map_spatial_broadcast_decoder(m, config)
  # The official code builds it "just for compatibility" and never uses it.
  m.skip_prefix('prior_slot_layer.')
  params = common.assemble(m, abstract_params(config), hints={
      'predictor.rnn': 'config.savi.predictor.kind / lstm_size',
      'predictor.out_projector': 'config.savi.predictor.kind / lstm_size',
      'predictor.': 'config.savi.predictor.kind',
      'kernel_dist_layer': 'config.savi.posterior_head',
      'encoder': 'config.savi.encoder.features',
      'decoder': 'config.savi.decoder.features',
  })
  return Converted('savi', common.SAVI_STAGE, params)


def _is_savi(keys: set[str]) -> bool:
  return ('slot_attention.project_k.weight' in keys
          and 'init_latents' in keys and 'encoder_out_layer.1.weight' in keys)


FAMILY = Family('savi', _is_savi, convert_savi)
