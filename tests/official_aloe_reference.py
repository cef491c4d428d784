"""An independent NumPy implementation of the official Aloe and readouts,
and official-format state dicts for them (official key names and shapes,
random values).

Written from the official module definitions (pairlab/SlotFormer:
clevrer_vqa/models/transformer.py `CLEVRERTransformerModel`,
physion_vqa/models/readout.py `PhysionReadout`,
phyre_planning/models/readout.py `PHYREReadout`) and PyTorch's layer
documentation, in float64: the official layout (flags read from the state
dict, as the official model does; question / choice split at
`question_len`; key-padding mask) is built here without this project's
modules. Used by test_convert_aloe.py.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

import official_reference as ref

ALOE = 'transformer_model.'
# The official fixed flags (nn.Parameter(requires_grad=False)).
OFFICIAL_FLAGS = {'text_token': (1.0, 0.0), 'vision_token': (0.0, 1.0),
                  'cls_token': (0.0, 1.0), 'mc_question_token': (1.0, 0.0),
                  'mc_choice_token': (0.0, 1.0)}


def masked_attention(x, sd, prefix, num_heads, key_padding):
  """nn.MultiheadAttention(batch_first=True) self-attention with
  `key_padding_mask` (bool [B, L], True: this key is never attended to)."""
  dim = x.shape[-1]
  head_dim = dim // num_heads
  qkv = x @ sd[f'{prefix}.in_proj_weight'].T + sd[f'{prefix}.in_proj_bias']
  q, k, v = np.split(qkv, 3, axis=-1)
  split = lambda t: t.reshape(*t.shape[:-1], num_heads, head_dim)
  q, k, v = split(q), split(k), split(v)
  logits = np.einsum('blhd,bmhd->bhlm', q, k) / np.sqrt(head_dim)
  logits = np.where(key_padding[:, None, None, :], -np.inf, logits)
  weights = ref.softmax(logits, -1)
  out = np.einsum('bhlm,bmhd->blhd', weights, v).reshape(x.shape)
  return ref.linear(out, sd, f'{prefix}.out_proj')


def masked_transformer_layer(x, sd, prefix, num_heads, key_padding):
  """nn.TransformerEncoderLayer(norm_first=True, ReLU), eval mode, with
  src_key_padding_mask."""
  x = x + masked_attention(ref.layer_norm(x, sd, f'{prefix}.norm1'), sd,
                           f'{prefix}.self_attn', num_heads, key_padding)
  hidden = np.maximum(ref.linear(ref.layer_norm(x, sd, f'{prefix}.norm2'),
                                 sd, f'{prefix}.linear1'), 0)
  return x + ref.linear(hidden, sd, f'{prefix}.linear2')


def _cat_flag(x, flag):
  return np.concatenate(
      [x, np.broadcast_to(flag, x.shape[:-1] + (len(flag),))], -1)


def aloe_cls(slots, tokens, pad, sd, *, num_heads, num_layers,
             question_len=None):
  """CLEVRERTransformerModel up to the [CLS] output [B, d_model].

  slots [B, T, N, C]; tokens int [B, L]; pad bool [B, L] (True = padding).
  question_len None: descriptive questions (`_cls_forward`); else
  multiple-choice rows question + choice (`_mc_forward`)."""
  p = ALOE
  words = sd[f'{p}q_embedding.weight'][tokens]  # [B, L, E]
  if question_len is None:
    words = _cat_flag(words, sd[f'{p}cls_token'])
  else:
    words = np.concatenate([
        _cat_flag(words[:, :question_len], sd[f'{p}mc_question_token']),
        _cat_flag(words[:, question_len:], sd[f'{p}mc_choice_token'])], 1)
  words = ref.linear(_cat_flag(words, sd[f'{p}text_token']), sd,
                     f'{p}q_in_proj')
  batch, time, num_slots, size = slots.shape
  vision = _cat_flag(slots.reshape(batch, time * num_slots, size),
                     sd[f'{p}vision_token'])
  vision = ref.linear(vision, sd, f'{p}vision_in_proj')
  cls = np.repeat(sd[f'{p}CLS'], batch, axis=0)
  x = np.concatenate([cls, vision, words], 1)
  key_padding = np.concatenate(
      [np.zeros((batch, 1 + time * num_slots), bool), pad], 1)
  x = x + sd[f'{p}transformer_encoder.pos_embedding']
  for i in range(num_layers):
    x = masked_transformer_layer(
        x, sd, f'{p}transformer_encoder.layers.{i}', num_heads, key_padding)
  return x[:, 0]


def _mlp(x, sd, prefix):
  return ref.linear(np.maximum(ref.linear(x, sd, f'{prefix}.0'), 0), sd,
                    f'{prefix}.2')


def aloe_open_logits(slots, tokens, pad, sd, **kwargs):
  """[B, num_answers] (`cls_answer_mlp`)."""
  return _mlp(aloe_cls(slots, tokens, pad, sd, **kwargs), sd,
              f'{ALOE}cls_answer_mlp')


def aloe_choice_logits(slots, tokens, pad, sd, *, question_len, **kwargs):
  """slots [Bn, T, N, C] (one row per choice, as mc_flag repeats them),
  tokens [Bn, L] -> [Bn] (`mc_answer_mlp`)."""
  cls = aloe_cls(slots, tokens, pad, sd, question_len=question_len, **kwargs)
  return _mlp(cls, sd, f'{ALOE}mc_answer_mlp')[:, 0]


def physion_readout_logits(slots, sd):
  """PhysionReadout (agg_func='max'): slots [B, T, N, C] -> [B]."""
  batch, time = slots.shape[:2]
  pairs = sd['comb_idx'].reshape(-1, 2)
  features = np.concatenate([slots[:, :, pairs[:, 0]],
                             slots[:, :, pairs[:, 1]]], -1)
  relation = ref.linear(features, sd, 'linear1').max(2)
  return ref.linear(relation, sd, 'linear2')[..., 0].max(1)


def phyre_readout_logits(slots, sd, *, sel_slots, num_heads, num_layers):
  """PHYREReadout: slots [B, T, N, C] -> [B]."""
  x = ref.linear(slots[:, list(sel_slots)], sd, 'in_proj')  # [B, S, N, D]
  batch, steps, num_slots, dim = x.shape
  x = x + sd['enc_t_pe'][:, :, None]
  x = x.reshape(batch, steps * num_slots, dim)
  x = np.concatenate([np.repeat(sd['CLS'], batch, axis=0), x], 1)
  no_padding = np.zeros(x.shape[:2], bool)
  for i in range(num_layers):
    x = masked_transformer_layer(x, sd, f'transformer_encoder.layers.{i}',
                                 num_heads, no_padding)
  return _mlp(x[:, 0], sd, 'cls_mlp')[:, 0]


# --------------------------------------------------------------------------
# Official-format state dicts, random values
# --------------------------------------------------------------------------


def aloe_state_dict(seed, *, vocab_size, num_answers, input_dim, num_heads,
                    slot_size, input_len, num_layers, ffn_dim, cls_mlp_size):
  """CLEVRERAloe's state dict, built as the official __init__ sizes it:
  word embedding input_dim - 2, token width input_dim + 2, d_model =
  (input_dim + 2) * num_heads, positions input_len + 1 (with [CLS])."""
  r = ref._Random(seed)  # pylint: disable=protected-access
  token_dim = input_dim + 2
  d_model = token_dim * num_heads
  p = ALOE
  sd = {f'{p}{name}': np.array(value)
        for name, value in OFFICIAL_FLAGS.items()}
  sd[f'{p}CLS'] = r.rng.standard_normal((1, 1, d_model)) * 0.5
  sd[f'{p}transformer_encoder.pos_embedding'] = 0.5 * r.rng.standard_normal(
      (1, input_len + 1, d_model))
  for i in range(num_layers):
    ref.add_transformer_layer(sd, r, f'{p}transformer_encoder.layers.{i}',
                              d_model, ffn_dim)
  sd[f'{p}q_embedding.weight'] = r.rng.standard_normal(
      (vocab_size, input_dim - 2))
  ref.add_linear(sd, r, f'{p}q_in_proj', token_dim, d_model)
  ref.add_linear(sd, r, f'{p}cls_answer_mlp.0', d_model, cls_mlp_size)
  ref.add_linear(sd, r, f'{p}cls_answer_mlp.2', cls_mlp_size, num_answers)
  ref.add_linear(sd, r, f'{p}mc_answer_mlp.0', d_model, cls_mlp_size)
  ref.add_linear(sd, r, f'{p}mc_answer_mlp.2', cls_mlp_size, 1)
  ref.add_linear(sd, r, f'{p}vision_in_proj', slot_size + 2, d_model)
  return sd


def physion_readout_state_dict(seed, *, num_slots, slot_size, feats_dim):
  r = ref._Random(seed)  # pylint: disable=protected-access
  sd = {'comb_idx': np.array(list(combinations(range(num_slots), 2)),
                             np.int64).reshape(-1)}
  ref.add_linear(sd, r, 'linear1', 2 * slot_size, feats_dim)
  ref.add_linear(sd, r, 'linear2', feats_dim, 1)
  return sd


def phyre_readout_state_dict(seed, *, slot_size, d_model, num_layers,
                             ffn_dim, num_selected):
  r = ref._Random(seed)  # pylint: disable=protected-access
  sd = {}
  ref.add_linear(sd, r, 'in_proj', slot_size, d_model)
  sd['CLS'] = 0.5 * r.rng.standard_normal((1, 1, d_model))
  for i in range(num_layers):
    ref.add_transformer_layer(sd, r, f'transformer_encoder.layers.{i}',
                              d_model, ffn_dim)
  sd['enc_t_pe'] = ref.sin_pos_enc(num_selected, d_model)
  ref.add_linear(sd, r, 'cls_mlp.0', d_model, d_model)
  ref.add_linear(sd, r, 'cls_mlp.2', d_model, 1)
  return sd
