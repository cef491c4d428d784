"""PyTorch layer weights -> this project's flax parameters, one layer kind each.

Every function reads the official tensors of one layer under `source` (a
state-dict prefix such as 'slot_attention.gru') and records the flax
parameters under `target` (a '/'-separated path such as
'frame_step/corrector/gru') in a `StateDictMapper`. Missing tensors are
collected, not raised, so that one error can list all of them.

Conventions (PyTorch -> flax):
  Linear          weight [out, in]            -> Dense kernel [in, out]
  Conv2d          weight [out, in, kh, kw]    -> Conv kernel [kh, kw, in, out]
  ConvTranspose2d weight [in, out, kh, kw]    -> stride 2: the sub-pixel
                  layer's kernel [kh, kw, in, out], not flipped (it keeps the
                  transposed-convolution definition); stride 1 ('same'
                  padding): an ordinary Conv with the kernel flipped in space
  LayerNorm       weight, bias                -> scale, bias
  GroupNorm (the dVAE blocks' F.group_norm) weight, bias -> scale, bias
  Embedding       weight [num, dim]           -> embedding [num, dim]
  GRUCell         (r, z, n) blocks; flax folds b_hr into ir, b_hz into iz
  LSTM            (i, f, g, o) blocks; flax keeps one bias per gate (b_ih+b_hh)
  MultiheadAttention in_proj (q; k; v) [3E, E] -> query/key/value
                  DenseGeneral [E, heads, E/heads]; out_proj -> out
                  [heads, E/heads, E]
  SLATE attention proj_q/k/v/o [E, E] (no bias) -> the same DenseGeneral
                  kernels
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class Assigned:
  """One flax parameter and where it came from (for error messages)."""

  value: np.ndarray
  source: str  # the official key(s)
  source_shape: tuple[int, ...]
  field: str  # the config field that sets this shape


class StateDictMapper:
  """Reads an official state dict once, key by key, and records the flax
  parameters built from it; knows which keys were missing or never read."""

  def __init__(self, state_dict: dict[str, np.ndarray]):
    self._state = state_dict
    self._read: set[str] = set()
    self.missing: list[str] = []
    self.params: dict[str, Assigned] = {}

  def has(self, key: str) -> bool:
    return key in self._state

  def has_prefix(self, prefix: str) -> bool:
    return any(key.startswith(prefix) for key in self._state)

  def count(self, template: str) -> int:
    """How many consecutive i make `template.format(i)` a key (from 0)."""
    i = 0
    while template.format(i) in self._state:
      i += 1
    return i

  def take(self, key: str) -> np.ndarray | None:
    if key not in self._state:
      self.missing.append(key)
      return None
    self._read.add(key)
    return np.asarray(self._state[key], np.float32)

  def skip(self, key: str) -> None:
    """Marks a key as known but unused (buffers, unused heads)."""
    if key in self._state:
      self._read.add(key)

  def skip_prefix(self, prefix: str) -> None:
    for key in self._state:
      if key.startswith(prefix):
        self._read.add(key)

  def unknown(self) -> list[str]:
    return [key for key in self._state if key not in self._read]

  def put(self, target: str, value: np.ndarray, source: str,
          source_shape: tuple[int, ...], field: str) -> None:
    if target in self.params:
      raise ValueError(f'{target} assigned twice ({source})')
    self.params[target] = Assigned(np.ascontiguousarray(value, np.float32),
                                   source, tuple(source_shape), field)


def _all(*arrays) -> bool:
  return all(a is not None for a in arrays)


def linear(m: StateDictMapper, source: str, target: str, field: str, *,
           bias: bool = True) -> None:
  weight = m.take(f'{source}.weight')
  b = m.take(f'{source}.bias') if bias else None
  if weight is None:
    return
  m.put(f'{target}/kernel', weight.T, f'{source}.weight', weight.shape, field)
  if b is not None:
    m.put(f'{target}/bias', b, f'{source}.bias', b.shape, field)


def conv(m: StateDictMapper, source: str, target: str, field: str, *,
         bias: bool = True) -> None:
  """nn.Conv2d -> nn.Conv (same padding / stride; checked by the caller)."""
  weight = m.take(f'{source}.weight')
  b = m.take(f'{source}.bias') if bias else None
  if weight is None or (bias and b is None):
    return
  m.put(f'{target}/kernel', weight.transpose(2, 3, 1, 0), f'{source}.weight',
        weight.shape, field)
  if bias:
    m.put(f'{target}/bias', b, f'{source}.bias', b.shape, field)


def group_norm(m: StateDictMapper, source: str, target: str,
               field: str) -> None:
  """F.group_norm's affine `weight`, `bias` [C] -> nn.GroupNorm scale, bias
  (the group count and epsilon are the module's, not in the weights)."""
  layer_norm(m, source, target, field)


def embedding(m: StateDictMapper, source: str, target: str,
              field: str) -> None:
  """nn.Embedding weight [num, dim] -> nn.Embed embedding [num, dim]."""
  weight = m.take(f'{source}.weight')
  if weight is not None:
    m.put(f'{target}/embedding', weight, f'{source}.weight', weight.shape,
          field)


def slate_attention(m: StateDictMapper, source: str, target: str,
                    field: str, *, num_heads: int) -> None:
  """SLATE / STEVE's MultiHeadAttention (bias-free `proj_q/k/v/o`, each
  [E, E]) -> the token decoder's `Attention`: query/key/value DenseGeneral
  kernels [E, heads, E/heads], out [heads, E/heads, E]. PyTorch splits the
  projected E features into heads as (heads, E/heads), row-major, which is
  the reshape here."""
  weights = {name: m.take(f'{source}.proj_{name[0]}.weight')
             for name in ('query', 'key', 'value', 'out')}
  if not _all(*weights.values()):
    return
  dim = weights['out'].shape[0]
  if dim % num_heads:
    raise ValueError(f'{source}: embedding size {dim} is not divisible by '
                     f'{num_heads} heads; change {field}')
  head_dim = dim // num_heads
  for name in ('query', 'key', 'value'):
    w = weights[name]
    m.put(f'{target}/{name}/kernel', w.T.reshape(-1, num_heads, head_dim),
          f'{source}.proj_{name[0]}.weight', w.shape, field)
  w = weights['out']
  m.put(f'{target}/out/kernel', w.T.reshape(num_heads, head_dim, -1),
        f'{source}.proj_o.weight', w.shape, field)


def conv_transpose(m: StateDictMapper, source: str, target: str, field: str,
                   *, stride: int) -> None:
  """nn.ConvTranspose2d(k, stride, padding=k // 2, output_padding=stride - 1).

  Stride 2 goes to `SubPixelConvTranspose`, whose kernel is the transposed
  convolution's own (unflipped). Stride 1 with padding k // 2 equals a
  'same' convolution with the kernel flipped in both spatial axes and the
  channel axes swapped, which is how the decoder evaluates it.
  """
  weight, bias = m.take(f'{source}.weight'), m.take(f'{source}.bias')
  if not _all(weight, bias):
    return
  if stride == 1:
    kernel = weight[:, :, ::-1, ::-1].transpose(2, 3, 0, 1)
  else:
    kernel = weight.transpose(2, 3, 0, 1)
  m.put(f'{target}/kernel', kernel, f'{source}.weight', weight.shape, field)
  m.put(f'{target}/bias', bias, f'{source}.bias', bias.shape, field)


def layer_norm(m: StateDictMapper, source: str, target: str,
               field: str) -> None:
  weight, bias = m.take(f'{source}.weight'), m.take(f'{source}.bias')
  if not _all(weight, bias):
    return
  m.put(f'{target}/scale', weight, f'{source}.weight', weight.shape, field)
  m.put(f'{target}/bias', bias, f'{source}.bias', bias.shape, field)


def gru_cell(m: StateDictMapper, source: str, target: str,
             field: str) -> None:
  """nn.GRUCell -> flax GRUCell.

  PyTorch: r = s(W_ir x + b_ir + W_hr h + b_hr), z likewise,
  n = tanh(W_in x + b_in + r * (W_hn h + b_hn)). flax keeps the sum
  b_ir + b_hr on `ir` (and b_iz + b_hz on `iz`) and b_hn on `hn`.
  """
  w_ih, w_hh = m.take(f'{source}.weight_ih'), m.take(f'{source}.weight_hh')
  b_ih, b_hh = m.take(f'{source}.bias_ih'), m.take(f'{source}.bias_hh')
  if not _all(w_ih, w_hh, b_ih, b_hh):
    return
  hidden = w_hh.shape[1]
  if w_ih.shape[0] != 3 * hidden:
    raise ValueError(f'{source}.weight_ih: expected {3 * hidden} rows (3 '
                     f'gates x {hidden}), got {w_ih.shape}')
  blocks = lambda a: np.split(a, 3, axis=0)
  (w_ir, w_iz, w_in), (w_hr, w_hz, w_hn) = blocks(w_ih), blocks(w_hh)
  (b_ir, b_iz, b_in), (b_hr, b_hz, b_hn) = blocks(b_ih), blocks(b_hh)
  src = f'{source}.weight_ih'
  for name, kernel in (('ir', w_ir), ('iz', w_iz), ('in', w_in)):
    m.put(f'{target}/{name}/kernel', kernel.T, src, w_ih.shape, field)
  src = f'{source}.weight_hh'
  for name, kernel in (('hr', w_hr), ('hz', w_hz), ('hn', w_hn)):
    m.put(f'{target}/{name}/kernel', kernel.T, src, w_hh.shape, field)
  src = f'{source}.bias_ih+bias_hh'
  m.put(f'{target}/ir/bias', b_ir + b_hr, src, b_ih.shape, field)
  m.put(f'{target}/iz/bias', b_iz + b_hz, src, b_ih.shape, field)
  m.put(f'{target}/in/bias', b_in, f'{source}.bias_ih', b_ih.shape, field)
  m.put(f'{target}/hn/bias', b_hn, f'{source}.bias_hh', b_hh.shape, field)


def lstm(m: StateDictMapper, source: str, target: str, field: str, *,
         suffix: str = '_l0') -> None:
  """One layer of nn.LSTM (suffix '_l0') or nn.LSTMCell (suffix '') ->
  flax (Optimized)LSTMCell: per gate g in (i, f, g, o) a kernel `i<g>`
  [in, H] without bias and `h<g>` [H, H] with bias b_ih + b_hh."""
  w_ih = m.take(f'{source}.weight_ih{suffix}')
  w_hh = m.take(f'{source}.weight_hh{suffix}')
  b_ih = m.take(f'{source}.bias_ih{suffix}')
  b_hh = m.take(f'{source}.bias_hh{suffix}')
  if not _all(w_ih, w_hh, b_ih, b_hh):
    return
  hidden = w_hh.shape[1]
  if w_ih.shape[0] != 4 * hidden:
    raise ValueError(f'{source}.weight_ih{suffix}: expected {4 * hidden} rows '
                     f'(4 gates x {hidden}), got {w_ih.shape}')
  gates = ('i', 'f', 'g', 'o')
  bias = b_ih + b_hh
  for gate, w_i, w_h, b in zip(gates, np.split(w_ih, 4), np.split(w_hh, 4),
                               np.split(bias, 4)):
    m.put(f'{target}/i{gate}/kernel', w_i.T, f'{source}.weight_ih{suffix}',
          w_ih.shape, field)
    m.put(f'{target}/h{gate}/kernel', w_h.T, f'{source}.weight_hh{suffix}',
          w_hh.shape, field)
    m.put(f'{target}/h{gate}/bias', b, f'{source}.bias_ih{suffix}+bias_hh',
          b_ih.shape, field)


def multihead_attention(m: StateDictMapper, source: str, target: str,
                        field: str, *, num_heads: int) -> None:
  """nn.MultiheadAttention (batch_first, packed in_proj) ->
  nn.MultiHeadDotProductAttention. The head count is not in the weights:
  it comes from the config."""
  w_in, b_in = m.take(f'{source}.in_proj_weight'), m.take(
      f'{source}.in_proj_bias')
  w_out, b_out = m.take(f'{source}.out_proj.weight'), m.take(
      f'{source}.out_proj.bias')
  if not _all(w_in, b_in, w_out, b_out):
    return
  dim = w_out.shape[0]
  if dim % num_heads:
    raise ValueError(f'{source}: embedding size {dim} is not divisible by '
                     f'{num_heads} heads; change {field}')
  head_dim = dim // num_heads
  for name, w, b in zip(('query', 'key', 'value'), np.split(w_in, 3),
                        np.split(b_in, 3)):
    m.put(f'{target}/{name}/kernel', w.T.reshape(-1, num_heads, head_dim),
          f'{source}.in_proj_weight', w_in.shape, field)
    m.put(f'{target}/{name}/bias', b.reshape(num_heads, head_dim),
          f'{source}.in_proj_bias', b_in.shape, field)
  m.put(f'{target}/out/kernel', w_out.T.reshape(num_heads, head_dim, -1),
        f'{source}.out_proj.weight', w_out.shape, field)
  m.put(f'{target}/out/bias', b_out, f'{source}.out_proj.bias', b_out.shape,
        field)


def transformer_encoder_layer(m: StateDictMapper, source: str, target: str,
                              field: str, *, num_heads: int) -> None:
  """nn.TransformerEncoderLayer (ReLU) -> `TransformerBlock`.

  Whether LayerNorm comes first (`norm_first`) is not in the weights; the
  official SAVi predictors and SlotFormer all use Pre-LN, as the blocks here
  do by default.
  """
  multihead_attention(m, f'{source}.self_attn', f'{target}/attention', field,
                      num_heads=num_heads)
  linear(m, f'{source}.linear1', f'{target}/Dense_0', field)
  linear(m, f'{source}.linear2', f'{target}/Dense_1', field)
  layer_norm(m, f'{source}.norm1', f'{target}/norm_attention', field)
  layer_norm(m, f'{source}.norm2', f'{target}/norm_mlp', field)
