"""What every official model family shares: the result and error types, the
family record, the checks, and the mappers of model parts several families
contain (SAVi's CNN encoder and Slot Attention are STEVE's too; the rollouter
is in SlotFormer on SAVi slots and on STEVE slots).

A family recognises its state dicts by their keys, maps every tensor to this
project's parameters (layers.py: one mapper per layer kind) and says which
pipeline stage the result belongs to. `assemble` runs the checks every family
shares: missing and unknown keys are reported together in ONE error, and each
shape that does not fit the model built from the config names the official
key, both shapes and the config field to change.
"""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax.dynamics.slotformer import NAME as SLOTFORMER
from slotformer_jax.errors import shown
from slotformer_jax.modules import slotformer as slotformer_module
from slotformer_jax.official import layers
from slotformer_jax.official.layers import StateDictMapper

# The pipeline stage (workdir folder) each converted model belongs to.
SAVI_STAGE = 'savi'
SLOTFORMER_STAGE = SLOTFORMER
DVAE_STAGE = 'dvae'
STEVE_STAGE = 'steve'

# nn.LayerNorm's default in PyTorch, in every official model.
PYTORCH_LN_EPSILON = 1e-5


class ConversionError(ValueError):
  """The checkpoint does not fit the model built from the config."""


@dataclasses.dataclass(frozen=True)
class Converted:
  """A converted model: the stage it belongs to and its flax parameters.

  `extras` holds official weights that are not parameters of that stage
  but must agree with another one (SlotFormer's frozen decoder copy).
  """

  family: str
  stage: str
  params: Any
  extras: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Family:
  """An official model family.

  Attributes:
    name: e.g. 'savi'.
    detect: state-dict keys -> whether they are this family's.
    convert: (state dict, config) -> Converted; None while the model is not
      implemented here (then `missing_reason` says what is needed).
    missing_reason: shown when `convert` is None.
  """

  name: str
  detect: Callable[[set[str]], bool]
  convert: Callable[[dict[str, np.ndarray], ml_collections.ConfigDict],
                    Converted] | None = None
  missing_reason: str = ''


# --------------------------------------------------------------------------
# Shared checks
# --------------------------------------------------------------------------


def flatten(tree: Any) -> dict[str, Any]:
  """{'a/b/c': leaf} of a nested parameter dict."""
  return {'/'.join(str(k.key) for k in path): leaf
          for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def unflatten(flat: dict[str, np.ndarray]) -> dict[str, Any]:
  """The inverse of `flatten`."""
  tree: dict[str, Any] = {}
  for path, value in flat.items():
    node = tree
    *parents, leaf = path.split('/')
    for key in parents:
      node = node.setdefault(key, {})
    node[leaf] = value
  return tree


def max_difference(a: Any, b: Any) -> float:
  """Largest |a - b| over two parameter trees (inf: other structures)."""
  flat_a, flat_b = flatten(a), flatten(b)
  if set(flat_a) != set(flat_b):
    return float('inf')
  return max(float(np.max(np.abs(np.asarray(flat_a[k]) -
                                 np.asarray(flat_b[k]))))
             for k in flat_a)


def require(config: ml_collections.ConfigDict, field: str, expected: Any,
            why: str) -> None:
  """The official family only fits configs where `field` == `expected`."""
  node = config
  for key in field.split('.'):
    node = node[key]
  if isinstance(node, (list, tuple)):
    node = tuple(node)
  if node != expected:
    raise ConversionError(
        f'config.{field} is {node!r}, but the official model {why}: set '
        f'--config.{field}={expected!r}')


def assemble(m: StateDictMapper, abstract_params: Any, *,
             hints: dict[str, str]) -> dict[str, Any]:
  """Checks the mapped parameters against the model's and nests them.

  Args:
    m: the mapper after every layer was read.
    abstract_params: `jax.eval_shape` of the model's init (the target).
    hints: official key prefix -> the config field that decides whether
      the model has that part (for unknown / missing keys).

  Raises:
    ConversionError: listing every missing and unknown key at once, or
      every shape mismatch at once.
  """

  def hint(key: str) -> str:
    for prefix, field in hints.items():
      if key.startswith(prefix):
        return f'  ({field})'
    return ''

  # Keys come from the file: a newline or an escape sequence in one must not
  # reach the terminal (a forged `error:` line, a cleared screen).
  def listed(keys: list[str]) -> str:
    return '\n    '.join(shown(k, 200) + hint(k) for k in keys)

  target = flatten(abstract_params)
  problems = []
  if m.missing:
    problems.append('missing keys (the config builds a part the checkpoint '
                    'does not have):\n    ' + listed(m.missing))
  unknown = m.unknown()
  if unknown:
    problems.append('unknown keys (the checkpoint has a part the config '
                    'does not build):\n    ' + listed(unknown))
  if problems:
    raise ConversionError('the checkpoint does not fit the config:\n  ' +
                          '\n  '.join(problems))

  mismatches = []
  for path, assigned in m.params.items():
    if path not in target:
      mismatches.append(f'{shown(assigned.source)} {assigned.source_shape}: the '
                        f'model has no parameter {path}; change '
                        f'{assigned.field}')
    elif tuple(target[path].shape) != assigned.value.shape:
      mismatches.append(
          f'{shown(assigned.source)}: checkpoint shape {assigned.source_shape} '
          f'gives {path} {assigned.value.shape}, the config builds '
          f'{tuple(target[path].shape)}; change {assigned.field}')
  unfilled = sorted(set(target) - set(m.params))
  if unfilled:
    mismatches.append('parameters of the config\'s model no checkpoint key '
                      'fills: ' + ', '.join(unfilled))
  if mismatches:
    raise ConversionError('shape mismatch:\n  ' + '\n  '.join(mismatches))
  return unflatten({path: m.params[path].value for path in target})


def only(m: StateDictMapper, prefix: str) -> StateDictMapper:
  """`m` restricted to the parameters under `prefix` (and its keys)."""
  restricted = StateDictMapper({})
  restricted.missing = list(m.missing)
  restricted.params = {k: v for k, v in m.params.items()
                       if k.startswith(prefix)}
  return restricted


# --------------------------------------------------------------------------
# Model parts of several families
# --------------------------------------------------------------------------


def check_grid(m: StateDictMapper, key: str, size: tuple[int, int],
                field: str) -> None:
  """An official SoftPositionEmbed grid [1, H, W, 4] must be H x W = size."""
  if not m.has(key):
    return  # older checkpoints may lack the buffer
  grid_size = tuple(m.take(key).shape[1:3])
  if grid_size != size:
    raise ConversionError(
        f'{key}: the official model works on a {grid_size} grid, the config '
        f'on {size}; change {field}')


def map_spatial_broadcast_decoder(m: StateDictMapper,
                                  config: ml_collections.ConfigDict,
                                  target: str = 'decoder') -> None:
  """`decoder.*` + `decoder_pos_embedding.*` (SAVi's and SlotFormer's)."""
  field = ('config.savi.decoder (features / kernel_size / '
           'broadcast_resolution)')
  layers.linear(m, 'decoder_pos_embedding.dense',
                f'{target}/position_embedding/dense', field)
  # The fixed coordinate grid: no parameter, but its size is the broadcast
  # size, which no weight shape reveals and which decides the strides.
  check_grid(m, 'decoder_pos_embedding.grid',
              tuple(config.savi.decoder.broadcast_resolution),
              'config.savi.decoder.broadcast_resolution')
  num_layers = m.count('decoder.{}.0.weight')
  size = config.savi.decoder.broadcast_resolution[0]
  for i in range(num_layers):
    # Upsample by 2 until the frame size is reached (as both codes do).
    stride = 2 if size < config.data.resolution[0] else 1
    layers.conv_transpose(m, f'decoder.{i}.0', f'{target}/deconv_{i}', field,
                          stride=stride)
    size *= stride
  layers.conv(m, f'decoder.{num_layers}', f'{target}/readout', field)


def map_cnn_encoder(m: StateDictMapper, config: ml_collections.ConfigDict,
                    section: str = 'savi'):
  """SAVi's (and STEVE's) CNN encoder `encoder.*`, `encoder_pos_embedding`,
  `encoder_out_layer`; `section`: the config section ('savi', 'steve')."""
  field = (f'config.{section}.encoder (features / kernel_size / '
           'output_size)')
  for i in range(m.count('encoder.{}.0.weight')):
    layers.conv(m, f'encoder.{i}.0', f'encoder/conv_{i}', field)
  layers.linear(m, 'encoder_pos_embedding.dense',
                'encoder/position_embedding/dense', field)
  strides = np.prod(config[section].encoder.strides)
  check_grid(m, 'encoder_pos_embedding.grid',
              tuple(int(size // strides) for size in config.data.resolution),
              f'config.data.resolution / config.{section}.encoder.strides')
  layers.layer_norm(m, 'encoder_out_layer.0', 'encoder/norm', field)
  layers.linear(m, 'encoder_out_layer.1', 'encoder/mlp_hidden', field)
  layers.linear(m, 'encoder_out_layer.3', 'encoder/mlp_out', field)


def map_slot_attention(m: StateDictMapper, target: str,
                       section: str = 'savi'):
  field = f'config.{section}.slot_size / slot_attention.mlp_size'
  source = 'slot_attention'
  layers.layer_norm(m, f'{source}.norm_inputs', f'{target}/norm_inputs',
                    field)
  layers.layer_norm(m, f'{source}.project_q.0', f'{target}/norm_slots', field)
  layers.linear(m, f'{source}.project_q.1', f'{target}/query', field,
                bias=False)
  layers.linear(m, f'{source}.project_k', f'{target}/key', field, bias=False)
  layers.linear(m, f'{source}.project_v', f'{target}/value', field,
                bias=False)
  layers.gru_cell(m, f'{source}.gru', f'{target}/gru', field)
  layers.layer_norm(m, f'{source}.mlp.0', f'{target}/LayerNorm_0', field)
  layers.linear(m, f'{source}.mlp.1', f'{target}/Dense_0', field)
  layers.linear(m, f'{source}.mlp.3', f'{target}/Dense_1', field)


def official_encoder_strides(config: ml_collections.ConfigDict,
                             section: str = 'savi'):
  """The official encoder halves 128x128 frames in its first layer only."""
  num_layers = len(config[section].encoder.features)
  first = 2 if config.data.resolution[0] == 128 else 1
  return (first,) + (1,) * (num_layers - 1)


def map_rollouter(m: StateDictMapper,
                  config: ml_collections.ConfigDict) -> None:
  """`rollouter.*` (SlotRollouter) -> the SlotFormer's `predictor/*`; the
  fixed temporal encoding is checked, not mapped."""
  dynamics = config.slotformer
  require(config, 'slotformer.residual', False,
          'predicts the next slots directly (no residual)')
  require(config, 'slotformer.positional_encoding', 'temporal',
          'adds a sinusoidal temporal encoding')
  require(config, 'slotformer.layer_norm_epsilon', PYTORCH_LN_EPSILON,
          "uses PyTorch's LayerNorm epsilon")
  field = 'config.slotformer (embed_dim / num_layers / mlp_ratio)'
  layers.linear(m, 'rollouter.in_proj', 'predictor/in_proj', field)
  for i in range(dynamics.num_layers):
    layers.transformer_encoder_layer(
        m, f'rollouter.transformer_encoder.layers.{i}',
        f'predictor/transformer/block_{i}', field,
        num_heads=dynamics.num_heads)
  layers.linear(m, 'rollouter.out_proj', 'predictor/out_proj', field)
  encoding = m.take('rollouter.enc_t_pe')  # [1, history_len, D_e], fixed
  if encoding is not None:
    history_len, dim = encoding.shape[1:]
    # The encoding covers the longest context: history_len frames, or
    # cond_len for the growing context of the PHYRE model.
    context = max(dynamics.burn_in, dynamics.max_context)
    if history_len != context:
      raise ConversionError(
          f'rollouter.enc_t_pe covers {history_len} frames, the config\'s '
          f'context {context}; change config.slotformer.burn_in (or '
          'max_context, the official cond_len)')
    expected = np.asarray(slotformer_module.sinusoidal_encoding(
        jnp.arange(history_len - 1, -1, -1), dim))
    if not np.allclose(encoding[0], expected, atol=1e-5):
      raise ConversionError(
          'rollouter.enc_t_pe is not the sinusoidal encoding (a learnable '
          "t_pe?); only t_pe='sin' is implemented here")
  if m.has_prefix('rollouter.enc_slots_pe'):
    m.take('rollouter.enc_slots_pe')
    raise ConversionError(
        'rollouter.enc_slots_pe: a per-slot position encoding (slots_pe) '
        'is not part of SlotFormer here')
