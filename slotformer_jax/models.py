"""Builds the linen modules from config sections (the only place that reads
both): each builder takes the section(s) it needs and passes plain values /
modules to the modules, which never read a config."""

from __future__ import annotations

import ml_collections

from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.dvae import DOWNSAMPLING as DVAE_DOWNSAMPLING
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.encoders import feature_grid
from slotformer_jax.modules.savi import FrameStep
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.slot_init import LearnedSlots
from slotformer_jax.modules.slot_init import slot_initializer
from slotformer_jax.modules.slot_lstm import SlotLSTM
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.modules.stochastic_savi import GaussianSlotSampler
from slotformer_jax.modules.stochastic_savi import NO_HEAD
from slotformer_jax.modules.stochastic_savi import POSTERIOR_HEADS
from slotformer_jax.modules.token_decoder import TokenDecoder
from slotformer_jax.modules.transitions import SlotTransition
from slotformer_jax.modules.transitions import build_predictor

SLOTFORMER = 'slotformer'
SLOT_LSTM = 'slot_lstm'
DYNAMICS_MODELS = (SLOTFORMER, SLOT_LSTM)


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


def build_dvae(dvae: ml_collections.ConfigDict) -> DVAE:
  """STEVE's tokenizer from `config.dvae`."""
  return DVAE(vocab_size=dvae.vocab_size, hidden_size=dvae.hidden_size)


def build_steve(steve: ml_collections.ConfigDict, resolution: tuple[int, int],
                vocab_size: int) -> STEVE:
  """STEVE from `config.steve` for frames of `resolution` (H, W), predicting
  the tokens of a dVAE with `vocab_size` codes (`config.dvae.vocab_size`).

  Its slot encoder is SAVi's (learned initial slots, Slot Attention keeping
  its masks, Transformer + per-slot LSTM, no pixel decoder); the token
  decoder's size is `slot_size`, as officially.
  """
  epsilon = steve.layer_norm_epsilon
  predictor = steve.predictor
  slot_encoder = SAVi(
      encoder=CNNEncoder(
          features=tuple(steve.encoder.features),
          kernel_size=steve.encoder.kernel_size,
          strides=tuple(steve.encoder.strides),
          output_size=steve.encoder.output_size,
          padding=steve.encoder.padding, layer_norm_epsilon=epsilon),
      initializer=LearnedSlots(steve.num_slots, steve.slot_size),
      frame_step=FrameStep(
          corrector=SlotAttention(steve.slot_attention.num_iterations,
                                  steve.slot_attention.mlp_size,
                                  layer_norm_epsilon=epsilon,
                                  return_attention=True),
          predictor=SlotTransition(
              num_layers=predictor.num_layers, num_heads=predictor.num_heads,
              mlp_size=predictor.mlp_size, lstm_size=predictor.lstm_size,
              layer_norm_epsilon=epsilon)),
      decoder=None)
  height, width = resolution
  token_grid = (height // DVAE_DOWNSAMPLING, width // DVAE_DOWNSAMPLING)
  return STEVE(
      slot_encoder=slot_encoder,
      decoder=TokenDecoder(
          vocab_size=vocab_size, num_tokens=token_grid[0] * token_grid[1],
          dim=steve.slot_size, num_layers=steve.decoder.num_layers,
          num_heads=steve.decoder.num_heads,
          dropout_rate=steve.decoder.dropout_rate),
      token_grid=token_grid,
      feature_grid=feature_grid(resolution, steve.encoder.strides))


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
