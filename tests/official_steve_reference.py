"""An independent NumPy implementation of the official dVAE / STEVE layers,
and official-format STEVE state dicts (official key names and shapes, random
values).

Written from the PyTorch definitions (F.group_norm, nn.PixelShuffle, the
SLATE attention, STEVE's slot encoder), in float64 and NCHW like PyTorch,
so a mapping error in the converter cannot cancel out against the same
error here. Reuses the layer definitions of official_reference.py (Linear,
LayerNorm, Conv2d, GRUCell, LSTM, nn.TransformerEncoderLayer). Used by
test_convert_steve.py.
"""

from __future__ import annotations

import numpy as np

import official_reference as ref

GN_EPS = 1e-5  # F.group_norm's default


# --------------------------------------------------------------------------
# dVAE
# --------------------------------------------------------------------------


def group_norm_one_group(x, weight, bias, eps=GN_EPS):
  """F.group_norm(x, 1, weight, bias): statistics over C, H, W of each
  image, then a per-channel affine."""
  mean = x.mean(axis=(1, 2, 3), keepdims=True)
  var = ((x - mean) ** 2).mean(axis=(1, 2, 3), keepdims=True)
  x = (x - mean) / np.sqrt(var + eps)
  return x * weight[None, :, None, None] + bias[None, :, None, None]


def pixel_shuffle(x, factor):
  """nn.PixelShuffle on NCHW: out[b, c, h*f + i, w*f + j] =
  in[b, c*f*f + i*f + j, h, w], written as explicit index loops."""
  batch, channels, height, width = x.shape
  out_ch = channels // (factor * factor)
  out = np.zeros((batch, out_ch, height * factor, width * factor))
  for c in range(out_ch):
    for i in range(factor):
      for j in range(factor):
        out[:, c, i::factor, j::factor] = x[:, c * factor * factor
                                            + i * factor + j]
  return out


def conv_block(x, sd, prefix, stride=1, padding=0):
  """Conv2dBlock: conv (no bias) -> GroupNorm(1) -> ReLU."""
  weight = sd[f'{prefix}.m.weight']
  x = ref.conv2d(x, weight, np.zeros(weight.shape[0]), stride, padding)
  return np.maximum(group_norm_one_group(x, sd[f'{prefix}.weight'],
                                         sd[f'{prefix}.bias']), 0)


def dvae_logits(img, sd):
  """img [B, 3, H, W] -> logits [B, V, H/4, W/4]."""
  x = conv_block(img, sd, 'encoder.0', stride=4)
  for i in range(1, 7):
    x = conv_block(x, sd, f'encoder.{i}')
  return ref.conv2d(x, sd['encoder.7.weight'], sd['encoder.7.bias'])


def dvae_decode(z, sd):
  """(relaxed) one-hot z [B, V, h, w] -> recon [B, 3, 4h, 4w]."""
  x = z
  for i in range(5):
    x = conv_block(x, sd, f'decoder.{i}', padding=1 if i == 1 else 0)
  x = pixel_shuffle(x, 2)
  for i in range(6, 10):
    x = conv_block(x, sd, f'decoder.{i}', padding=1 if i == 6 else 0)
  x = pixel_shuffle(x, 2)
  return ref.conv2d(x, sd['decoder.11.weight'], sd['decoder.11.bias'])


# --------------------------------------------------------------------------
# STEVE's token decoder (SLATE's Transformer decoder)
# --------------------------------------------------------------------------


def slate_attention(q, kv, sd, prefix, num_heads, causal=False):
  """MultiHeadAttention: bias-free projections, q scaled by d^-1/2, masked
  entries -inf (strict upper triangle when causal), softmax, proj_o."""
  batch, length, dim = q.shape
  head = dim // num_heads
  split = lambda t: t.reshape(batch, -1, num_heads, head).transpose(0, 2, 1, 3)
  q = split(q @ sd[f'{prefix}.proj_q.weight'].T) * head ** -0.5
  k = split(kv @ sd[f'{prefix}.proj_k.weight'].T)
  v = split(kv @ sd[f'{prefix}.proj_v.weight'].T)
  logits = q @ k.transpose(0, 1, 3, 2)
  if causal:
    mask = np.triu(np.ones((length, length), bool), k=1)
    logits = np.where(mask, -np.inf, logits)
  out = ref.softmax(logits, -1) @ v
  out = out.transpose(0, 2, 1, 3).reshape(batch, length, dim)
  return out @ sd[f'{prefix}.proj_o.weight'].T


def token_decoder(slots, idx, sd, num_heads, num_layers):
  """STEVETransformerDecoder.forward: slots [B, N, D], input token ids
  idx [B, T] (without BOS) -> logits [B, 1 + T, V]."""
  p = 'trans_decoder'
  slots = ref.linear(slots, sd, f'{p}.in_proj')
  vocab = sd[f'{p}.head.weight'].shape[0]
  idx = np.concatenate([np.full((idx.shape[0], 1), vocab), idx], 1)
  x = sd[f'{p}.tok_emb.weight'][idx] + sd[f'{p}.pos_emb.pe'][:, :idx.shape[1]]
  for i in range(num_layers):
    b = f'{p}.tf_dec.blocks.{i}'
    normed = ref.layer_norm(x, sd, f'{b}.self_attn_layer_norm')
    if i == 0:  # is_first: the input itself is replaced by its norm
      x = normed
    x = x + slate_attention(normed, normed, sd, f'{b}.self_attn', num_heads,
                            causal=True)
    normed = ref.layer_norm(x, sd, f'{b}.encoder_decoder_attn_layer_norm')
    x = x + slate_attention(normed, slots, sd, f'{b}.encoder_decoder_attn',
                            num_heads)
    hidden = np.maximum(ref.linear(
        ref.layer_norm(x, sd, f'{b}.ffn_layer_norm'), sd, f'{b}.ffn.0'), 0)
    x = x + ref.linear(hidden, sd, f'{b}.ffn.2')
  x = ref.layer_norm(x, sd, f'{p}.tf_dec.layer_norm')
  return x @ sd[f'{p}.head.weight'].T


# --------------------------------------------------------------------------
# STEVE's slot encoder
# --------------------------------------------------------------------------


def slot_attention_with_masks(inputs, slots, sd, num_iterations, eps=1e-6):
  """SlotAttentionWMask: as SAVi's, plus the last iteration's attention
  (softmax over slots) [B, N, M] as the masks."""
  p = 'slot_attention'
  size = slots.shape[-1]
  inputs = ref.layer_norm(inputs, sd, f'{p}.norm_inputs')
  k = ref.linear(inputs, sd, f'{p}.project_k', bias=False)
  v = ref.linear(inputs, sd, f'{p}.project_v', bias=False)
  for _ in range(num_iterations):
    q = ref.linear(ref.layer_norm(slots, sd, f'{p}.project_q.0'), sd,
                   f'{p}.project_q.1', bias=False)
    attn = ref.softmax(np.einsum('bnc,bmc->bnm', k, q) * size ** -0.5, -1)
    masks = attn.transpose(0, 2, 1)
    attn = attn + eps
    attn = attn / attn.sum(1, keepdims=True)
    updates = np.einsum('bnm,bnc->bmc', attn, v)
    slots = ref.gru_cell(updates, slots, sd, f'{p}.gru')
    hidden = ref.layer_norm(slots, sd, f'{p}.mlp.0')
    hidden = np.maximum(ref.linear(hidden, sd, f'{p}.mlp.1'), 0)
    slots = slots + ref.linear(hidden, sd, f'{p}.mlp.3')
  return slots, masks


def steve_encode(img, sd, *, first_stride, num_iterations, num_heads,
                 num_layers, lstm_size):
  """STEVE.encode over img [B, T, 3, H, W] -> (slots [B, T, N, D], masks
  [B, T, N, h'*w']): learned initial slots at t = 0, then the predictor
  (Transformer -> LSTM -> Linear) of the previous frame's slots."""
  batch, time = img.shape[:2]
  features = ref.savi_encoder(img.reshape(batch * time, *img.shape[2:]), sd,
                              first_stride=first_stride)
  features = features.reshape(batch, time, *features.shape[1:])
  latents = np.repeat(sd['init_latents'], batch, axis=0)
  num_slots = latents.shape[1]
  state = (np.zeros((batch * num_slots, lstm_size)),) * 2
  all_slots, all_masks = [], []
  slots = None  # the previous frame's
  for t in range(time):
    if t:
      latents, state = ref.transformer_lstm_predictor(
          slots, state, sd, num_layers, num_heads)
    slots, masks = slot_attention_with_masks(features[:, t], latents, sd,
                                             num_iterations)
    all_slots.append(slots)
    all_masks.append(masks)
  return np.stack(all_slots, 1), np.stack(all_masks, 1)


# --------------------------------------------------------------------------
# Official-format state dicts
# --------------------------------------------------------------------------


def _add_block(sd, r, prefix, n_in, n_out, k):
  sd[f'{prefix}.m.weight'] = r.matrix(n_out, n_in, k, k)
  sd[f'{prefix}.weight'] = r.vector(n_out, offset=1.0)
  sd[f'{prefix}.bias'] = r.vector(n_out)


def dvae_state_dict(seed, *, vocab_size, hidden=64):
  """The official dVAE's keys (hidden 64 there; any size here)."""
  r = ref._Random(seed)  # pylint: disable=protected-access
  sd = {}
  _add_block(sd, r, 'encoder.0', 3, hidden, 4)
  for i in range(1, 7):
    _add_block(sd, r, f'encoder.{i}', hidden, hidden, 1)
  sd['encoder.7.weight'] = r.matrix(vocab_size, hidden, 1, 1)
  sd['encoder.7.bias'] = r.vector(vocab_size)
  for i, (n_in, n_out, k) in {
      0: (vocab_size, hidden, 1), 1: (hidden, hidden, 3),
      2: (hidden, hidden, 1), 3: (hidden, hidden, 1),
      4: (hidden, 4 * hidden, 1), 6: (hidden, hidden, 3),
      7: (hidden, hidden, 1), 8: (hidden, hidden, 1),
      9: (hidden, 4 * hidden, 1)}.items():
    _add_block(sd, r, f'decoder.{i}', n_in, n_out, k)
  sd['decoder.11.weight'] = r.matrix(3, hidden, 1, 1)
  sd['decoder.11.bias'] = r.vector(3)
  return sd


def token_decoder_state_dict(r, sd, *, vocab_size, dim, num_tokens,
                             num_layers, prefix='trans_decoder'):
  ref.add_linear(sd, r, f'{prefix}.in_proj', dim, dim)
  sd[f'{prefix}.tok_emb.weight'] = r.rng.standard_normal((vocab_size + 1, dim))
  sd[f'{prefix}.pos_emb.pe'] = r.rng.standard_normal((1, num_tokens, dim))
  for i in range(num_layers):
    b = f'{prefix}.tf_dec.blocks.{i}'
    for norm in ('self_attn_layer_norm', 'encoder_decoder_attn_layer_norm',
                 'ffn_layer_norm'):
      ref.add_layer_norm(sd, r, f'{b}.{norm}', dim)
    for attn in ('self_attn', 'encoder_decoder_attn'):
      for proj in 'qkvo':
        sd[f'{b}.{attn}.proj_{proj}.weight'] = r.matrix(dim, dim)
    sd[f'{b}.self_attn_mask'] = np.triu(
        np.ones((num_tokens, num_tokens), bool), k=1)
    ref.add_linear(sd, r, f'{b}.ffn.0', dim, 4 * dim)
    ref.add_linear(sd, r, f'{b}.ffn.2', 4 * dim, dim)
  ref.add_layer_norm(sd, r, f'{prefix}.tf_dec.layer_norm', dim)
  sd[f'{prefix}.head.weight'] = r.matrix(vocab_size, dim)


def steve_state_dict(seed, *, dvae, num_slots, slot_size, encoder_features,
                     feature_resolution, slot_mlp_size, predictor_layers,
                     predictor_ffn, vocab_size, num_tokens, decoder_layers,
                     kernel=5):
  """An official STEVE state dict (with its frozen dVAE copy `dvae`)."""
  savi = ref.savi_state_dict(
      seed, num_slots=num_slots, slot_size=slot_size,
      encoder_features=encoder_features, encoder_size=slot_size,
      feature_resolution=feature_resolution, slot_mlp_size=slot_mlp_size,
      decoder_features=(8,), broadcast=(2, 2),
      predictor_layers=predictor_layers, predictor_ffn=predictor_ffn,
      lstm_size=slot_mlp_size, kernel=kernel)
  # STEVE has SAVi's encoder, Slot Attention and predictor, none of its
  # posterior / prior heads or pixel decoder.
  sd = {k: v for k, v in savi.items() if not k.startswith(
      ('kernel_dist_layer', 'prior_slot_layer', 'decoder'))}
  r = ref._Random(seed + 100)  # pylint: disable=protected-access
  token_decoder_state_dict(r, sd, vocab_size=vocab_size, dim=slot_size,
                           num_tokens=num_tokens, num_layers=decoder_layers)
  sd.update({f'dvae.{k}': v.copy() for k, v in dvae.items()})
  return sd


def steve_slotformer_state_dict(seed, *, dvae, steve, slot_size, d_model,
                                num_layers, ffn, history_len):
  """An official STEVESlotFormer state dict: the rollouter, and copies of
  the dVAE and of STEVE's token decoder (as `decoder.*`)."""
  sd = ref.slotformer_state_dict(seed, slot_size=slot_size, d_model=d_model,
                                 num_layers=num_layers, ffn=ffn,
                                 history_len=history_len, decoder_from={})
  sd.update({f'dvae.{k}': v.copy() for k, v in dvae.items()})
  sd.update({'decoder.' + k[len('trans_decoder.'):]: v.copy()
             for k, v in steve.items() if k.startswith('trans_decoder.')})
  return sd
