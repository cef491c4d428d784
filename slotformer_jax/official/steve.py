"""The official Physion families: dVAE, STEVE, STEVESlotFormer.

Official modules (pairlab/SlotFormer): `base_slots/models/dVAE.py` (dVAE),
`base_slots/models/steve.py` + `steve_transformer.py` (STEVE and its
SLATE-style token decoder), `video_prediction/models/steve_slotformer.py`
(SlotFormer over STEVE slots). Each official STEVE / STEVESlotFormer
state dict also holds frozen copies of the modules it was trained with:

* STEVE: `dvae.*`, the dVAE it was trained on (loaded from
  `dvae_physion_params/model_20.pth`, `requires_grad=False`);
* STEVESlotFormer: `dvae.*` again, and `decoder.*`, a copy of STEVE's
  `trans_decoder.*` (loaded from `steve_physion_params/model_10.pth`).

Here the pipeline reads those modules from the dVAE / STEVE stages of the
workdir, so the copies are converted into `extras` and the writer
(convert.py) requires them to equal, bit for bit, what the workdir
already holds (convert in the order dVAE, STEVE, SlotFormer; one command
with all three files does that).
"""

from __future__ import annotations

from typing import Any

import ml_collections
import numpy as np

from slotformer_jax import dynamics
from slotformer_jax.dynamics.slotformer import NAME as SLOTFORMER
from slotformer_jax.official import common
from slotformer_jax.official import layers
from slotformer_jax.official.common import ConversionError
from slotformer_jax.official.common import Converted
from slotformer_jax.official.common import Family
from slotformer_jax.official.layers import StateDictMapper
from slotformer_jax.slot_models import chain
from slotformer_jax.slot_models.steve import DVAE_NAME
from slotformer_jax.slot_models.steve import NAME as STEVE_NAME
from slotformer_jax.slot_models.steve import Steve

# dVAE: official `nn.Sequential` index -> this project's layer. Pixel
# shuffles (decoder.5, decoder.10) have no weights.
_DVAE_ENCODER_BLOCKS = 7  # encoder.0 (k4 s4) + six 1x1 blocks; encoder.7 conv
_DVAE_DECODER_BLOCKS = {  # official index -> (stage, layer)
    0: (0, 0), 1: (0, 1), 2: (0, 2), 3: (0, 3), 4: (0, 4),
    6: (1, 0), 7: (1, 1), 8: (1, 2), 9: (1, 3),
}
_DVAE_OUT = 11


def _require_steve(config: ml_collections.ConfigDict, why: str) -> None:
  common.require(config, 'slot_model', 'steve', why)


def _copy(state_dict: dict[str, np.ndarray], prefix: str,
          new_prefix: str = '') -> dict[str, np.ndarray]:
  """The tensors under `prefix`, renamed to start with `new_prefix`."""
  return {new_prefix + key[len(prefix):]: value
          for key, value in state_dict.items() if key.startswith(prefix)}


# --------------------------------------------------------------------------
# dVAE (base_slots/models/dVAE.py)
# --------------------------------------------------------------------------


def map_dvae(m: StateDictMapper) -> None:
  """`encoder.*` / `decoder.*` of the official dVAE -> `DVAE` parameters.

  A Conv2dBlock is `m` (Conv2d without bias) then F.group_norm(x, 1,
  weight, bias) then ReLU: `<i>.m.weight` -> `conv/kernel`, `<i>.weight`,
  `<i>.bias` -> `norm/scale`, `norm/bias`.
  """
  field = 'config.dvae (vocab_size / hidden_size)'

  def block(source: str, target: str) -> None:
    layers.conv(m, f'{source}.m', f'{target}/conv', field, bias=False)
    layers.group_norm(m, source, f'{target}/norm', field)

  for i in range(_DVAE_ENCODER_BLOCKS):
    block(f'encoder.{i}', f'encoder/layers_{i}')
  layers.conv(m, f'encoder.{_DVAE_ENCODER_BLOCKS}',
              f'encoder/layers_{_DVAE_ENCODER_BLOCKS}', field)
  for index, (stage, layer) in _DVAE_DECODER_BLOCKS.items():
    block(f'decoder.{index}', f'decoder_stages_{stage}/layers_{layer}')
  layers.conv(m, f'decoder.{_DVAE_OUT}', 'decoder_out', field)


def _assemble_dvae(state_dict: dict[str, np.ndarray],
                   config: ml_collections.ConfigDict, what: str) -> Any:
  m = StateDictMapper(state_dict)
  map_dvae(m)
  try:
    return common.assemble(m, chain.param_shapes(Steve(config).part(DVAE_NAME)),
                             hints={'': 'config.dvae'})
  except ConversionError as error:
    raise ConversionError(f'{what}: {error}') from error


def convert_dvae(state_dict: dict[str, np.ndarray],
                 config: ml_collections.ConfigDict) -> Converted:
  """Official dVAE (`dvae_physion_params/model_20.pth`) -> `dvae/`."""
  _require_steve(config, 'is the tokenizer of STEVE')
  return Converted('dvae', common.DVAE_STAGE,
                   _assemble_dvae(state_dict, config, 'dVAE'))


# --------------------------------------------------------------------------
# STEVE (base_slots/models/steve.py, steve_transformer.py)
# --------------------------------------------------------------------------


def map_token_decoder(m: StateDictMapper, config: ml_collections.ConfigDict,
                      source: str = 'trans_decoder',
                      target: str = 'decoder') -> None:
  """STEVETransformerDecoder -> `TokenDecoder`.

  Its fixed causal masks (`tf_dec.blocks.i.self_attn_mask`, saved as a
  non-trainable parameter) are checked to be the strict upper triangle.
  """
  field = 'config.steve (slot_size / decoder) / config.dvae.vocab_size'
  heads = config.steve.decoder.num_heads
  layers.linear(m, f'{source}.in_proj', f'{target}/slot_projection', field)
  layers.embedding(m, f'{source}.tok_emb', f'{target}/token_embedding', field)
  position = m.take(f'{source}.pos_emb.pe')  # [1, max_len + 1, D]
  if position is not None:
    m.put(f'{target}/position_embedding', position[0],
          f'{source}.pos_emb.pe', position.shape,
          'config.data.resolution (tokens per frame) / config.steve.slot_size')
  for i in range(config.steve.decoder.num_layers):
    block = f'{source}.tf_dec.blocks.{i}'
    out = f'{target}/blocks_{i}'
    layers.layer_norm(m, f'{block}.self_attn_layer_norm', f'{out}/norm_self',
                      field)
    layers.slate_attention(m, f'{block}.self_attn', f'{out}/self_attention',
                           field, num_heads=heads)
    layers.layer_norm(m, f'{block}.encoder_decoder_attn_layer_norm',
                      f'{out}/norm_cross', field)
    layers.slate_attention(m, f'{block}.encoder_decoder_attn',
                           f'{out}/cross_attention', field, num_heads=heads)
    layers.layer_norm(m, f'{block}.ffn_layer_norm', f'{out}/norm_ffn', field)
    layers.linear(m, f'{block}.ffn.0', f'{out}/ffn_hidden', field)
    layers.linear(m, f'{block}.ffn.2', f'{out}/ffn_out', field)
    mask = m.take(f'{block}.self_attn_mask')
    if mask is not None:
      length = mask.shape[0]
      causal = np.triu(np.ones((length, length)), k=1)
      if mask.shape != (length, length) or not np.array_equal(mask, causal):
        raise ConversionError(
            f'{block}.self_attn_mask is not the causal mask of '
            f'{length} tokens; only the causal decoder is implemented')
  layers.layer_norm(m, f'{source}.tf_dec.layer_norm', f'{target}/final_norm',
                    field)
  layers.linear(m, f'{source}.head', f'{target}/head', field, bias=False)


def _require_official_steve(config: ml_collections.ConfigDict) -> None:
  _require_steve(config, 'is a STEVE')
  common.require(config, 'steve.layer_norm_epsilon',
                   common.PYTORCH_LN_EPSILON,
                   "uses PyTorch's LayerNorm epsilon")
  common.require(
      config, 'steve.encoder.strides',
      common.official_encoder_strides(config, 'steve'),
      f'strides its encoder so at {tuple(config.data.resolution)}')
  if max(config.steve.encoder.strides) > 1:
    common.require(config, 'steve.encoder.padding', 'pytorch',
                     'pads its strided convolution by K // 2 on every side')


def _map_steve_predictor(m: StateDictMapper,
                         config: ml_collections.ConfigDict,
                         target: str) -> None:
  """RNNPredictorWrapper(TransformerPredictor): the only official STEVE
  predictor (`pred_rnn=True`, LSTM of slot_mlp_size units)."""
  predictor = config.steve.predictor
  field = 'config.steve.predictor (num_layers / mlp_size / lstm_size)'
  for i in range(predictor.num_layers):
    layers.transformer_encoder_layer(
        m, f'predictor.base_predictor.transformer_encoder.layers.{i}',
        f'{target}/transformer/block_{i}', field,
        num_heads=predictor.num_heads)
  layers.lstm(m, 'predictor.rnn', f'{target}/lstm', field)
  layers.linear(m, 'predictor.out_projector', f'{target}/lstm_out', field)


def convert_steve(state_dict: dict[str, np.ndarray],
                  config: ml_collections.ConfigDict) -> Converted:
  """Official STEVE (`steve_physion_params/model_10.pth`) -> `steve/`; its
  dVAE copy goes to `extras['dvae']`."""
  _require_official_steve(config)
  m = StateDictMapper(state_dict)
  latents = m.take('init_latents')  # [1, N, D]
  if latents is not None:
    m.put('initial_slots', latents[0], 'init_latents', latents.shape,
          'config.steve.num_slots / slot_size')
  common.map_cnn_encoder(m, config, 'steve')
  common.map_slot_attention(m, 'frame_step/corrector', 'steve')
  _map_steve_predictor(m, config, 'frame_step/predictor')
  map_token_decoder(m, config)
  m.skip_prefix('dvae.')
  params = common.assemble(m, chain.param_shapes(Steve(config).part(STEVE_NAME)),
                             hints={
                                 'predictor.': 'config.steve.predictor',
                                 'trans_decoder.tf_dec.blocks':
                                     'config.steve.decoder.num_layers',
                                 'encoder': 'config.steve.encoder.features',
                             })
  extras = {}
  if any(key.startswith('dvae.') for key in state_dict):
    extras['dvae'] = _assemble_dvae(_copy(state_dict, 'dvae.'), config,
                                    "STEVE's dVAE copy (dvae.*)")
  return Converted('steve', common.STEVE_STAGE, params, extras=extras)


# --------------------------------------------------------------------------
# SlotFormer over STEVE slots (video_prediction/models/steve_slotformer.py)
# --------------------------------------------------------------------------


def convert_steve_slotformer(state_dict: dict[str, np.ndarray],
                             config: ml_collections.ConfigDict) -> Converted:
  """Official STEVESlotFormer (`slotformer_physion_params/model_25.pth`)
  -> `slotformer/`; its dVAE copy and token-decoder copy go to `extras`
  ('dvae', 'steve_decoder')."""
  _require_steve(config, 'runs on STEVE slots')
  m = StateDictMapper(state_dict)
  common.map_rollouter(m, config)
  m.skip_prefix('dvae.')
  m.skip_prefix('decoder.')
  params = common.assemble(
      m, dynamics.param_shapes(
          config.slotformer, SLOTFORMER,
          (config.steve.num_slots, config.steve.slot_size)),
      hints={'rollouter.transformer_encoder': 'config.slotformer.num_layers'})
  extras = {}
  if any(key.startswith('dvae.') for key in state_dict):
    extras['dvae'] = _assemble_dvae(_copy(state_dict, 'dvae.'), config,
                                    "SlotFormer's dVAE copy (dvae.*)")
  if any(key.startswith('decoder.') for key in state_dict):
    decoder = StateDictMapper(_copy(state_dict, 'decoder.', 'trans_decoder.'))
    map_token_decoder(decoder, config)
    abstract = {'decoder': chain.param_shapes(Steve(config).part(STEVE_NAME))['decoder']}
    try:
      extras['steve_decoder'] = common.assemble(
          decoder, abstract, hints={})['decoder']
    except ConversionError as error:
      raise ConversionError(
          f"SlotFormer's token-decoder copy (decoder.*, named "
          f'trans_decoder.* above): {error}') from error
  return Converted('steve_slotformer', common.SLOTFORMER_STAGE, params,
                   extras=extras)


def _is_steve_slotformer(keys: set[str]) -> bool:
  """STEVESlotFormer: the rollouter plus copies of the dVAE and of STEVE's
  token decoder."""
  return 'rollouter.in_proj.weight' in keys and any(
      k.startswith('dvae.') for k in keys)


def _is_steve(keys: set[str]) -> bool:
  """STEVE: SAVi's encoder and Slot Attention, a token decoder and a dVAE
  copy (before 'savi', whose keys it also has)."""
  return 'init_latents' in keys and any(
      k.startswith(('dvae.', 'trans_decoder.')) for k in keys)


def _is_dvae(keys: set[str]) -> bool:
  """The dVAE: only `encoder.*` / `decoder.*`, with GroupNorm conv blocks
  (`<i>.m.weight`, the bias-free conv of a Conv2dBlock)."""
  return (bool(keys) and any(k.endswith('.m.weight') for k in keys)
          and all(k.startswith(('encoder.', 'decoder.')) for k in keys))


STEVE_SLOTFORMER_FAMILY = Family('steve_slotformer', _is_steve_slotformer,
                                 convert_steve_slotformer)
STEVE_FAMILY = Family('steve', _is_steve, convert_steve)
DVAE_FAMILY = Family('dvae', _is_dvae, convert_dvae)
