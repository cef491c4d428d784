"""Tiny SAVi / STEVE for module and training tests, built the way the
pipeline builds them: `slotformer_jax.models`' builders on config sections of
the defaults, with small sizes (16x16 frames)."""

import ml_collections

from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.slot_models import steve as steve_slots
from slotformer_jax.config.defaults import base_config

RESOLUTION = (16, 16)

_TINY_SAVI = dict(
    num_slots=3, slot_size=16,
    encoder=dict(features=(8, 8), kernel_size=3, strides=(1, 1),
                 output_size=16),
    slot_attention=dict(mlp_size=16),
    predictor=dict(num_layers=1, num_heads=2, mlp_size=32),
    decoder=dict(broadcast_resolution=(4, 4), features=(8, 8), kernel_size=3),
)

_TINY_STEVE = dict(
    num_slots=3, slot_size=16,
    encoder=dict(features=(8, 8), kernel_size=3, strides=(2, 1),
                 output_size=16),
    slot_attention=dict(mlp_size=32),
    predictor=dict(num_layers=1, num_heads=2, mlp_size=32, lstm_size=32),
    decoder=dict(num_layers=1, num_heads=2, dropout_rate=0.0),
)


def _section(name: str, tiny: dict, updates: dict) -> ml_collections.ConfigDict:
  section = base_config()[name]
  section.update(tiny)
  section.update(updates)  # nested dicts update sub-sections
  return section


def savi_section(**updates) -> ml_collections.ConfigDict:
  """A tiny `config.savi`; `updates` as nested dicts, e.g.
  `predictor=dict(kind='transformer_lstm', lstm_size=8)`."""
  return _section('savi', _TINY_SAVI, updates)


def tiny_savi(resolution=RESOLUTION, **updates):
  return savi_slots.build_savi(savi_section(**updates), resolution)


def tiny_steve(resolution=RESOLUTION, vocab_size=16, **updates):
  return steve_slots.build_steve(_section('steve', _TINY_STEVE, updates),
                            resolution, vocab_size)
