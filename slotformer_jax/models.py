"""Builds the linen modules from a config (the only place that reads both)."""

from __future__ import annotations

import ml_collections

from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.slot_lstm import SlotLSTM
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.modules.steve import STEVE

SLOTFORMER = 'slotformer'
SLOT_LSTM = 'slot_lstm'
DYNAMICS_MODELS = (SLOTFORMER, SLOT_LSTM)


def build_savi(config: ml_collections.ConfigDict) -> SAVi:
  """SAVi (or stochastic SAVi when `config.savi.stochastic`)."""
  savi = config.savi
  return SAVi(
      resolution=tuple(config.data.resolution),
      num_slots=savi.num_slots,
      slot_size=savi.slot_size,
      encoder_features=tuple(savi.encoder.features),
      encoder_kernel_size=savi.encoder.kernel_size,
      encoder_strides=tuple(savi.encoder.strides),
      encoder_size=savi.encoder.output_size,
      encoder_padding=savi.encoder.padding,
      num_iterations=savi.slot_attention.num_iterations,
      slot_mlp_size=savi.slot_attention.mlp_size,
      predictor_kind=savi.predictor.kind,
      predictor_layers=savi.predictor.num_layers,
      predictor_heads=savi.predictor.num_heads,
      predictor_mlp_size=savi.predictor.mlp_size,
      predictor_lstm_size=savi.predictor.lstm_size,
      predictor_pre_norm=savi.predictor.pre_norm,
      predictor_dropout_rate=savi.predictor.dropout_rate,
      posterior_head=savi.posterior_head,
      decoder_broadcast_resolution=tuple(savi.decoder.broadcast_resolution),
      decoder_features=tuple(savi.decoder.features),
      decoder_kernel_size=savi.decoder.kernel_size,
      stochastic=savi.stochastic,
      prior_sigma=savi.prior_sigma,
      initial_slots=savi.initial_slots,
      layer_norm_epsilon=savi.layer_norm_epsilon,
  )


def build_dvae(config: ml_collections.ConfigDict) -> DVAE:
  """STEVE's tokenizer (`config.dvae`)."""
  return DVAE(vocab_size=config.dvae.vocab_size,
              hidden_size=config.dvae.hidden_size)


def build_steve(config: ml_collections.ConfigDict) -> STEVE:
  """STEVE (`config.steve`); its vocabulary is the dVAE's."""
  steve = config.steve
  return STEVE(
      resolution=tuple(config.data.resolution),
      num_slots=steve.num_slots,
      slot_size=steve.slot_size,
      encoder_features=tuple(steve.encoder.features),
      encoder_kernel_size=steve.encoder.kernel_size,
      encoder_strides=tuple(steve.encoder.strides),
      encoder_size=steve.encoder.output_size,
      encoder_padding=steve.encoder.padding,
      num_iterations=steve.slot_attention.num_iterations,
      slot_mlp_size=steve.slot_attention.mlp_size,
      predictor_layers=steve.predictor.num_layers,
      predictor_heads=steve.predictor.num_heads,
      predictor_mlp_size=steve.predictor.mlp_size,
      predictor_lstm_size=steve.predictor.lstm_size,
      vocab_size=config.dvae.vocab_size,
      decoder_layers=steve.decoder.num_layers,
      decoder_heads=steve.decoder.num_heads,
      decoder_dropout=steve.decoder.dropout_rate,
      layer_norm_epsilon=steve.layer_norm_epsilon,
  )


def build_decoder(config: ml_collections.ConfigDict) -> SpatialBroadcastDecoder:
  """SAVi's decoder alone; its parameters are `savi_params['decoder']`."""
  decoder = config.savi.decoder
  return SpatialBroadcastDecoder(
      output_resolution=tuple(config.data.resolution),
      broadcast_resolution=tuple(decoder.broadcast_resolution),
      features=tuple(decoder.features),
      kernel_size=decoder.kernel_size)


def _transformer_fields(dynamics: ml_collections.ConfigDict) -> dict:
  """The constructor fields SlotFormer and Slot-LSTM share."""
  return dict(
      burn_in=dynamics.burn_in,
      embed_dim=dynamics.embed_dim,
      num_layers=dynamics.num_layers,
      num_heads=dynamics.num_heads,
      mlp_size=dynamics.mlp_ratio * dynamics.embed_dim,
      dropout_rate=dynamics.dropout_rate,
      residual=dynamics.residual,
  )


def build_slotformer(config: ml_collections.ConfigDict) -> SlotFormer:
  dynamics = config.slotformer
  return SlotFormer(positional_encoding=dynamics.positional_encoding,
                    max_context=dynamics.max_context,
                    layer_norm_epsilon=dynamics.layer_norm_epsilon,
                    **_transformer_fields(dynamics))


def dynamics_config(config: ml_collections.ConfigDict,
                    name: str) -> ml_collections.ConfigDict:
  """The stage-2 hyper-parameters of dynamics model `name`.

  SlotFormer reads `config.slotformer`. Slot-LSTM is trained "with the same
  setup": `config.slotformer` with the fields set in `config.slot_lstm`
  (all but `train`) overriding it.
  """
  if name == SLOTFORMER:
    return config.slotformer
  if name != SLOT_LSTM:
    raise ValueError(f'unknown dynamics model {name!r}; one of '
                     f'{DYNAMICS_MODELS}')
  merged = ml_collections.ConfigDict(config.slotformer.to_dict())
  for key, value in config.slot_lstm.items():
    if key != 'train' and value is not None:
      merged[key] = value
  return merged


def build_slot_lstm(config: ml_collections.ConfigDict) -> SlotLSTM:
  return SlotLSTM(**_transformer_fields(dynamics_config(config, SLOT_LSTM)))


def build_dynamics(config: ml_collections.ConfigDict,
                   name: str) -> SlotFormer | SlotLSTM:
  """The stage-2 model `name` ('slotformer' or 'slot_lstm')."""
  if name == SLOTFORMER:
    return build_slotformer(config)
  if name == SLOT_LSTM:
    return build_slot_lstm(config)
  raise ValueError(f'unknown dynamics model {name!r}; one of '
                   f'{DYNAMICS_MODELS}')


def build_aloe(config: ml_collections.ConfigDict, vocab_size: int,
               num_answers: int, *, num_slots: int) -> 'Aloe':
  """Aloe for `config.vqa` over `num_slots` slots per frame."""
  # Imported here: the VQA model is optional for the video pipeline.
  from slotformer_jax.modules.aloe import Aloe  # pylint: disable=g-import-not-at-top
  vqa = config.vqa
  return Aloe(
      vocab_size=vocab_size, num_answers=num_answers,
      num_frames=vqa.num_frames, num_slots=num_slots,
      text_length=vqa.max_question_len + vqa.max_choice_len,
      question_length=vqa.max_question_len, d_model=vqa.d_model,
      word_dim=vqa.word_dim, num_layers=vqa.num_layers,
      num_heads=vqa.num_heads, mlp_size=vqa.mlp_size,
      head_size=vqa.head_size, dropout_rate=vqa.dropout_rate,
      positions=vqa.positions,
      layer_norm_epsilon=vqa.get('layer_norm_epsilon', 1e-6))
