"""An independent NumPy implementation of the official PyTorch layers, and
official-format state dicts (official key names and shapes, random values).

Written from the PyTorch layer definitions (documentation formulas), in
float64 and NCHW like PyTorch, so a mapping error in the converter cannot
cancel out against the same error here. Used by test_convert_official.py.
"""

from __future__ import annotations

import numpy as np

LN_EPS = 1e-5  # nn.LayerNorm's default


def sigmoid(x):
  return 1.0 / (1.0 + np.exp(-x))


def softmax(x, axis):
  x = x - x.max(axis=axis, keepdims=True)
  e = np.exp(x)
  return e / e.sum(axis=axis, keepdims=True)


def linear(x, sd, prefix, bias=True):
  """nn.Linear: y = x W^T + b."""
  y = x @ sd[f'{prefix}.weight'].T
  return y + sd[f'{prefix}.bias'] if bias else y


def layer_norm(x, sd, prefix, eps=LN_EPS):
  mean = x.mean(-1, keepdims=True)
  var = ((x - mean) ** 2).mean(-1, keepdims=True)
  return ((x - mean) / np.sqrt(var + eps) * sd[f'{prefix}.weight']
          + sd[f'{prefix}.bias'])


def conv2d(x, weight, bias, stride=1, padding=0):
  """nn.Conv2d on NCHW: out[o, y, x] = b[o] + sum_{c,i,j}
  w[o, c, i, j] * in_padded[c, stride*y + i, stride*x + j]."""
  batch, _, height, width = x.shape
  out_ch, _, kh, kw = weight.shape
  xp = np.pad(x, ((0, 0), (0, 0), (padding, padding), (padding, padding)))
  out_h = (height + 2 * padding - kh) // stride + 1
  out_w = (width + 2 * padding - kw) // stride + 1
  out = np.zeros((batch, out_ch, out_h, out_w))
  for i in range(kh):
    for j in range(kw):
      patch = xp[:, :, i:i + stride * (out_h - 1) + 1:stride,
                 j:j + stride * (out_w - 1) + 1:stride]
      out += np.einsum('bchw,oc->bohw', patch, weight[:, :, i, j])
  return out + bias[None, :, None, None]


def conv_transpose2d(x, weight, bias, stride=1, padding=0, output_padding=0):
  """nn.ConvTranspose2d on NCHW, by its scatter definition:
  full[o, stride*y + i, stride*x + j] += in[c, y, x] * w[c, o, i, j], then
  `padding` cropped from the top/left; output size
  (H - 1) * stride - 2 * padding + k + output_padding."""
  batch, _, height, width = x.shape
  _, out_ch, kh, kw = weight.shape
  full_h = (height - 1) * stride + kh + output_padding
  full_w = (width - 1) * stride + kw + output_padding
  full = np.zeros((batch, out_ch, full_h, full_w))
  for i in range(kh):
    for j in range(kw):
      full[:, :, i:i + stride * (height - 1) + 1:stride,
           j:j + stride * (width - 1) + 1:stride] += np.einsum(
               'bchw,co->bohw', x, weight[:, :, i, j])
  out_h = (height - 1) * stride - 2 * padding + kh + output_padding
  out_w = (width - 1) * stride - 2 * padding + kw + output_padding
  out = full[:, :, padding:padding + out_h, padding:padding + out_w]
  return out + bias[None, :, None, None]


def gru_cell(x, h, sd, prefix):
  """nn.GRUCell (gates r, z, n)."""
  gi = x @ sd[f'{prefix}.weight_ih'].T + sd[f'{prefix}.bias_ih']
  gh = h @ sd[f'{prefix}.weight_hh'].T + sd[f'{prefix}.bias_hh']
  i_r, i_z, i_n = np.split(gi, 3, axis=-1)
  h_r, h_z, h_n = np.split(gh, 3, axis=-1)
  r = sigmoid(i_r + h_r)
  z = sigmoid(i_z + h_z)
  n = np.tanh(i_n + r * h_n)
  return (1 - z) * n + z * h


def lstm_step(x, h, c, sd, prefix, suffix='_l0'):
  """One step of nn.LSTM's layer 0 (gates i, f, g, o); returns (h, c)."""
  gates = (x @ sd[f'{prefix}.weight_ih{suffix}'].T
           + sd[f'{prefix}.bias_ih{suffix}']
           + h @ sd[f'{prefix}.weight_hh{suffix}'].T
           + sd[f'{prefix}.bias_hh{suffix}'])
  i, f, g, o = np.split(gates, 4, axis=-1)
  c = sigmoid(f) * c + sigmoid(i) * np.tanh(g)
  h = sigmoid(o) * np.tanh(c)
  return h, c


def multihead_attention(x, sd, prefix, num_heads):
  """nn.MultiheadAttention(batch_first=True) self-attention, x [B, L, E]."""
  dim = x.shape[-1]
  head_dim = dim // num_heads
  qkv = x @ sd[f'{prefix}.in_proj_weight'].T + sd[f'{prefix}.in_proj_bias']
  q, k, v = np.split(qkv, 3, axis=-1)
  split = lambda t: t.reshape(*t.shape[:-1], num_heads, head_dim)
  q, k, v = split(q), split(k), split(v)
  logits = np.einsum('blhd,bmhd->bhlm', q, k) / np.sqrt(head_dim)
  weights = softmax(logits, -1)
  out = np.einsum('bhlm,bmhd->blhd', weights, v).reshape(x.shape)
  return linear(out, sd, f'{prefix}.out_proj')


def transformer_layer(x, sd, prefix, num_heads):
  """nn.TransformerEncoderLayer(norm_first=True, ReLU), eval mode."""
  x = x + multihead_attention(layer_norm(x, sd, f'{prefix}.norm1'), sd,
                              f'{prefix}.self_attn', num_heads)
  hidden = np.maximum(linear(layer_norm(x, sd, f'{prefix}.norm2'), sd,
                             f'{prefix}.linear1'), 0)
  return x + linear(hidden, sd, f'{prefix}.linear2')


def build_grid(height, width):
  """[H, W, 4]: (y, x, 1 - y, 1 - x), each from 0 to 1."""
  ys, xs = np.meshgrid(np.linspace(0, 1, height), np.linspace(0, 1, width),
                       indexing='ij')
  grid = np.stack([ys, xs], -1)
  return np.concatenate([grid, 1 - grid], -1)


def soft_position_embed(x, sd, prefix):
  """x [B, C, H, W] + dense(grid) permuted to channels-first."""
  grid = build_grid(*x.shape[2:])
  return x + linear(grid, sd, f'{prefix}.dense').transpose(2, 0, 1)[None]


# --------------------------------------------------------------------------
# Official model pieces
# --------------------------------------------------------------------------


def savi_encoder(img, sd, first_stride=1):
  """img [B, 3, H, W] -> [B, H'*W', D_enc] (conv stack, PE, LN + MLP)."""
  num_layers = sum(1 for k in sd if k.startswith('encoder.')
                   and k.endswith('.0.weight'))
  x = img
  for i in range(num_layers):
    weight = sd[f'encoder.{i}.0.weight']
    x = conv2d(x, weight, sd[f'encoder.{i}.0.bias'],
               stride=first_stride if i == 0 else 1,
               padding=weight.shape[-1] // 2)
    if i < num_layers - 1:
      x = np.maximum(x, 0)
  x = soft_position_embed(x, sd, 'encoder_pos_embedding')
  x = x.reshape(*x.shape[:2], -1).transpose(0, 2, 1)
  x = layer_norm(x, sd, 'encoder_out_layer.0')
  x = np.maximum(linear(x, sd, 'encoder_out_layer.1'), 0)
  return linear(x, sd, 'encoder_out_layer.3')


def slot_attention(inputs, slots, sd, num_iterations, eps=1e-6):
  prefix = 'slot_attention'
  size = slots.shape[-1]
  inputs = layer_norm(inputs, sd, f'{prefix}.norm_inputs')
  k = linear(inputs, sd, f'{prefix}.project_k', bias=False)
  v = linear(inputs, sd, f'{prefix}.project_v', bias=False)
  for _ in range(num_iterations):
    q = linear(layer_norm(slots, sd, f'{prefix}.project_q.0'), sd,
               f'{prefix}.project_q.1', bias=False)
    attn = softmax(np.einsum('bnc,bmc->bnm', k, q) * size ** -0.5, -1)
    attn = attn + eps
    attn = attn / attn.sum(1, keepdims=True)
    updates = np.einsum('bnm,bnc->bmc', attn, v)
    slots = gru_cell(updates, slots, sd, f'{prefix}.gru')
    hidden = layer_norm(slots, sd, f'{prefix}.mlp.0')
    hidden = np.maximum(linear(hidden, sd, f'{prefix}.mlp.1'), 0)
    slots = slots + linear(hidden, sd, f'{prefix}.mlp.3')
  return slots


def savi_decoder(slots, sd, resolution, broadcast):
  """slots [B, N, D] -> (recon [B, 3, H, W], masks [B, N, 1, H, W])."""
  batch, num_slots, size = slots.shape
  x = np.broadcast_to(slots.reshape(-1, size, 1, 1),
                      (batch * num_slots, size, *broadcast)).copy()
  x = soft_position_embed(x, sd, 'decoder_pos_embedding')
  num_layers = sum(1 for k in sd if k.startswith('decoder.')
                   and k.endswith('.0.weight'))
  out_size = broadcast[0]
  for i in range(num_layers):
    stride = 1 if out_size == resolution[0] else 2
    weight = sd[f'decoder.{i}.0.weight']
    pad = weight.shape[-1] // 2
    x = np.maximum(conv_transpose2d(x, weight, sd[f'decoder.{i}.0.bias'],
                                    stride, pad, stride - 1), 0)
    out_size = x.shape[-1]
  x = conv2d(x, sd[f'decoder.{num_layers}.weight'],
             sd[f'decoder.{num_layers}.bias'])
  x = x.reshape(batch, num_slots, 4, *resolution)
  masks = softmax(x[:, :, 3:], 1)
  return (x[:, :, :3] * masks).sum(1), masks


def transformer_lstm_predictor(slots, state, sd, num_layers, num_heads):
  """The OBJ3D / PHYRE SAVi predictor: Transformer -> per-slot LSTM ->
  Linear; returns (next slots, (h, c))."""
  x = slots
  for i in range(num_layers):
    x = transformer_layer(
        x, sd, f'predictor.base_predictor.transformer_encoder.layers.{i}',
        num_heads)
  batch, num_slots, size = x.shape
  h, c = state
  h, c = lstm_step(x.reshape(-1, size), h, c, sd, 'predictor.rnn')
  out = linear(h, sd, 'predictor.out_projector').reshape(batch, num_slots,
                                                         size)
  return out, (h, c)


def residual_mlp_predictor(slots, sd):
  """The CLEVRER StoSAVi predictor (norm_first): LN, MLP, + the normalised
  input."""
  normed = layer_norm(slots, sd, 'predictor.ln')
  hidden = np.maximum(linear(normed, sd, 'predictor.mlp.0'), 0)
  return linear(hidden, sd, 'predictor.mlp.2') + normed


def kernel_linear_mean(slots, sd):
  """The linear posterior head (kernel_mlp=False), mean half."""
  return linear(slots, sd, 'kernel_dist_layer.0')[..., :slots.shape[-1]]


def kernel_mlp_mean(slots, sd):
  """The MLP posterior head, mean half (the deterministic SAVi's input)."""
  hidden = linear(slots, sd, 'kernel_dist_layer.0')
  hidden = np.maximum(layer_norm(hidden, sd, 'kernel_dist_layer.1'), 0)
  return linear(hidden, sd, 'kernel_dist_layer.3')[..., :slots.shape[-1]]


def savi_forward(img, sd, *, num_iterations, num_heads=0, num_layers=0,
                 lstm_size=0, predictor='transformer_lstm', head='mlp'):
  """Official (deterministic) SAVi over a video img [B, T, 3, H, W]:
  per frame, the head's mean of the initial slots goes into Slot Attention,
  whose output the predictor turns into the next frame's initial slots.
  Returns slots [B, T, N, D]."""
  batch, time = img.shape[:2]
  features = savi_encoder(img.reshape(batch * time, *img.shape[2:]), sd)
  features = features.reshape(batch, time, *features.shape[1:])
  latents = np.repeat(sd['init_latents'], batch, axis=0)
  num_slots = latents.shape[1]
  state = (np.zeros((batch * num_slots, lstm_size)),) * 2
  all_slots = []
  for t in range(time):
    if t:
      if predictor == 'residual_mlp':
        latents = residual_mlp_predictor(slots, sd)
      else:
        latents, state = transformer_lstm_predictor(slots, state, sd,
                                                    num_layers, num_heads)
    kernels = (kernel_mlp_mean(latents, sd) if head == 'mlp'
               else kernel_linear_mean(latents, sd))
    slots = slot_attention(features[:, t], kernels, sd, num_iterations)
    all_slots.append(slots)
  return np.stack(all_slots, 1)


def single_step_rollouter(slots, sd, num_steps, num_heads, num_layers):
  """The PHYRE rollouter: from 1 frame, the context grows to cond_len
  (the length of enc_t_pe) frames, then slides; the newest frames get the
  last positions of the encoding."""
  batch, history, num_slots, size = slots.shape
  cond_len = sd['rollouter.enc_t_pe'].shape[1]
  pe = np.repeat(sd['rollouter.enc_t_pe'][0], num_slots, axis=0)
  tokens = slots.reshape(batch, history * num_slots, size)
  predictions = []
  for _ in range(num_steps):
    window = tokens[:, -cond_len * num_slots:]
    x = linear(window, sd, 'rollouter.in_proj') + pe[-window.shape[1]:]
    for i in range(num_layers):
      x = transformer_layer(x, sd, f'rollouter.transformer_encoder.layers.{i}',
                            num_heads)
    predicted = linear(x[:, -num_slots:], sd, 'rollouter.out_proj')
    predictions.append(predicted)
    tokens = np.concatenate([tokens, predicted], 1)
  return np.stack(predictions, 1)


def slot_rollouter(slots, sd, num_steps, num_heads, num_layers):
  """SlotFormer's rollouter: slots [B, T, N, D] -> [B, num_steps, N, D]."""
  batch, history, num_slots, size = slots.shape
  pe = np.repeat(sd['rollouter.enc_t_pe'][0], num_slots, axis=0)
  tokens = slots.reshape(batch, history * num_slots, size)
  predictions = []
  for _ in range(num_steps):
    x = linear(tokens, sd, 'rollouter.in_proj') + pe
    for i in range(num_layers):
      x = transformer_layer(x, sd, f'rollouter.transformer_encoder.layers.{i}',
                            num_heads)
    predicted = linear(x[:, -num_slots:], sd, 'rollouter.out_proj')
    predictions.append(predicted)
    tokens = np.concatenate([tokens[:, num_slots:], predicted], 1)
  return np.stack(predictions, 1)


def sin_pos_enc(length, dim):
  """The official sinusoidal encoding, newest position 0, [1, L, dim]."""
  inv_freq = 1.0 / (10000 ** (np.arange(0.0, dim, 2.0) / dim))
  pos = np.arange(length - 1, -1, -1.0)
  angles = np.outer(pos, inv_freq)
  return np.concatenate([np.sin(angles), np.cos(angles)], -1)[None]


# --------------------------------------------------------------------------
# Official-format state dicts, random values
# --------------------------------------------------------------------------


class _Random:

  def __init__(self, seed):
    self.rng = np.random.default_rng(seed)

  def matrix(self, *shape):
    fan_in = int(np.prod(shape[1:])) if len(shape) > 1 else shape[0]
    return self.rng.uniform(-1, 1, shape) / np.sqrt(fan_in)

  def transposed(self, in_ch, out_ch, k):
    return self.rng.uniform(-1, 1, (in_ch, out_ch, k, k)) / np.sqrt(
        out_ch * k * k)

  def vector(self, n, scale=0.1, offset=0.0):
    return offset + scale * self.rng.standard_normal(n)


def add_linear(sd, r, prefix, n_in, n_out, bias=True):
  sd[f'{prefix}.weight'] = r.matrix(n_out, n_in)
  if bias:
    sd[f'{prefix}.bias'] = r.vector(n_out)


def add_layer_norm(sd, r, prefix, n):
  sd[f'{prefix}.weight'] = r.vector(n, offset=1.0)
  sd[f'{prefix}.bias'] = r.vector(n)


def add_transformer_layer(sd, r, prefix, dim, ffn):
  sd[f'{prefix}.self_attn.in_proj_weight'] = r.matrix(3 * dim, dim)
  sd[f'{prefix}.self_attn.in_proj_bias'] = r.vector(3 * dim)
  add_linear(sd, r, f'{prefix}.self_attn.out_proj', dim, dim)
  add_linear(sd, r, f'{prefix}.linear1', dim, ffn)
  add_linear(sd, r, f'{prefix}.linear2', ffn, dim)
  add_layer_norm(sd, r, f'{prefix}.norm1', dim)
  add_layer_norm(sd, r, f'{prefix}.norm2', dim)


def add_decoder(sd, r, slot_size, features, broadcast, kernel=5):
  channels = (slot_size, *features)
  for i in range(len(features)):
    sd[f'decoder.{i}.0.weight'] = r.transposed(channels[i], channels[i + 1],
                                               kernel)
    sd[f'decoder.{i}.0.bias'] = r.vector(channels[i + 1])
  sd[f'decoder.{len(features)}.weight'] = r.matrix(4, features[-1], 1, 1)
  sd[f'decoder.{len(features)}.bias'] = r.vector(4)
  sd['decoder_pos_embedding.grid'] = build_grid(*broadcast)[None]
  add_linear(sd, r, 'decoder_pos_embedding.dense', 4, slot_size)


def savi_state_dict(seed, *, num_slots, slot_size, encoder_features,
                    encoder_size, feature_resolution, slot_mlp_size,
                    decoder_features, broadcast, predictor_layers=0,
                    predictor_ffn=0, lstm_size=0, kernel=5,
                    predictor='transformer_lstm', head='mlp'):
  """An official StoSAVi state dict. Defaults: a Transformer + LSTM
  predictor and the MLP posterior head (the OBJ3D / PHYRE layout);
  predictor='residual_mlp', head='linear': the CLEVRER layout."""
  r = _Random(seed)
  sd = {}
  channels = (3, *encoder_features)
  for i in range(len(encoder_features)):
    sd[f'encoder.{i}.0.weight'] = r.matrix(channels[i + 1], channels[i],
                                           kernel, kernel)
    sd[f'encoder.{i}.0.bias'] = r.vector(channels[i + 1])
  sd['encoder_pos_embedding.grid'] = build_grid(*feature_resolution)[None]
  add_linear(sd, r, 'encoder_pos_embedding.dense', 4, encoder_features[-1])
  add_layer_norm(sd, r, 'encoder_out_layer.0', encoder_features[-1])
  add_linear(sd, r, 'encoder_out_layer.1', encoder_features[-1], encoder_size)
  add_linear(sd, r, 'encoder_out_layer.3', encoder_size, encoder_size)
  sd['init_latents'] = r.rng.standard_normal((1, num_slots, slot_size))
  add_linear(sd, r, 'kernel_dist_layer.0', slot_size, 2 * slot_size)
  if head == 'mlp':
    add_layer_norm(sd, r, 'kernel_dist_layer.1', 2 * slot_size)
    add_linear(sd, r, 'kernel_dist_layer.3', 2 * slot_size, 2 * slot_size)
  add_linear(sd, r, 'prior_slot_layer.0', slot_size, slot_size)
  add_layer_norm(sd, r, 'prior_slot_layer.1', slot_size)
  add_linear(sd, r, 'prior_slot_layer.3', slot_size, slot_size)
  sa = 'slot_attention'
  add_layer_norm(sd, r, f'{sa}.norm_inputs', encoder_size)
  add_layer_norm(sd, r, f'{sa}.project_q.0', slot_size)
  add_linear(sd, r, f'{sa}.project_q.1', slot_size, slot_size, bias=False)
  add_linear(sd, r, f'{sa}.project_k', encoder_size, slot_size, bias=False)
  add_linear(sd, r, f'{sa}.project_v', encoder_size, slot_size, bias=False)
  sd[f'{sa}.gru.weight_ih'] = r.matrix(3 * slot_size, slot_size)
  sd[f'{sa}.gru.weight_hh'] = r.matrix(3 * slot_size, slot_size)
  sd[f'{sa}.gru.bias_ih'] = r.vector(3 * slot_size)
  sd[f'{sa}.gru.bias_hh'] = r.vector(3 * slot_size)
  add_layer_norm(sd, r, f'{sa}.mlp.0', slot_size)
  add_linear(sd, r, f'{sa}.mlp.1', slot_size, slot_mlp_size)
  add_linear(sd, r, f'{sa}.mlp.3', slot_mlp_size, slot_size)
  add_decoder(sd, r, slot_size, decoder_features, broadcast, kernel)
  if predictor == 'residual_mlp':
    add_layer_norm(sd, r, 'predictor.ln', slot_size)
    add_linear(sd, r, 'predictor.mlp.0', slot_size, 2 * slot_size)
    add_linear(sd, r, 'predictor.mlp.2', 2 * slot_size, slot_size)
    return sd
  for i in range(predictor_layers):
    add_transformer_layer(
        sd, r, f'predictor.base_predictor.transformer_encoder.layers.{i}',
        slot_size, predictor_ffn)
  sd['predictor.rnn.weight_ih_l0'] = r.matrix(4 * lstm_size, slot_size)
  sd['predictor.rnn.weight_hh_l0'] = r.matrix(4 * lstm_size, lstm_size)
  sd['predictor.rnn.bias_ih_l0'] = r.vector(4 * lstm_size)
  sd['predictor.rnn.bias_hh_l0'] = r.vector(4 * lstm_size)
  add_linear(sd, r, 'predictor.out_projector', lstm_size, slot_size)
  return sd


def slotformer_state_dict(seed, *, slot_size, d_model, num_layers, ffn,
                          history_len, decoder_from, cond_len=0):
  """An official SlotFormer state dict whose frozen decoder is copied from
  the SAVi state dict `decoder_from`."""
  r = _Random(seed)
  sd = {}
  add_linear(sd, r, 'rollouter.in_proj', slot_size, d_model)
  for i in range(num_layers):
    add_transformer_layer(sd, r, f'rollouter.transformer_encoder.layers.{i}',
                          d_model, ffn)
  sd['rollouter.enc_t_pe'] = sin_pos_enc(max(history_len, cond_len), d_model)
  add_linear(sd, r, 'rollouter.out_proj', d_model, slot_size)
  for key, value in decoder_from.items():
    if key.startswith('decoder'):
      sd[key] = value.copy()
  return sd
