"""One converter per official model family, and the registry that picks it.

A family recognises its state dicts by their keys, maps every tensor to this
project's parameters (see layers.py) and says which pipeline stage the result
belongs to. `convert_state_dict` runs the checks every family shares:
missing and unknown keys are reported together in ONE error, and each
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

from slotformer_jax import models
from slotformer_jax.modules import savi as savi_module
from slotformer_jax.modules import slotformer as slotformer_module
from slotformer_jax.modules.stochastic_savi import LINEAR_HEAD
from slotformer_jax.modules.stochastic_savi import MLP_HEAD
from slotformer_jax.official import layers
from slotformer_jax.official.layers import StateDictMapper

SAVI_STAGE = 'savi'
SLOTFORMER_STAGE = models.SLOTFORMER

# Datasets whose official models saw OpenCV's BGR frames: CLEVRER's
# read the videos with cv2 (nerv's VideoReader without to_rgb). Physion's
# did not: its frames were written to JPEG by cv2.imwrite (colours kept)
# and read back with PIL's convert('RGB').
BGR_DATASETS = ('clevrer',)
# Datasets whose official models saw RGB frames (PIL).
RGB_DATASETS = ('obj3d', 'phyre', 'physion')


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


_FAMILIES: list[Family] = []


def register(family: Family) -> Family:
  """Adds a family; the first one whose `detect` matches converts."""
  if any(f.name == family.name for f in _FAMILIES):
    raise ValueError(f'family {family.name!r} registered twice')
  _FAMILIES.append(family)
  return family


def families() -> tuple[Family, ...]:
  return tuple(_FAMILIES)


def detect_family(state_dict: dict[str, np.ndarray]) -> Family:
  keys = set(state_dict)
  for family in _FAMILIES:
    if family.detect(keys):
      return family
  some = ', '.join(sorted(keys)[:8])
  raise ConversionError(
      f'no official model family recognises this state dict (keys: {some}, '
      f'...); known families: {[f.name for f in _FAMILIES]}')


def convert_state_dict(state_dict: dict[str, np.ndarray],
                       config: ml_collections.ConfigDict) -> Converted:
  family = detect_family(state_dict)
  if family.convert is None:
    raise NotImplementedError(
        f'official {family.name} checkpoints are recognised but not '
        f'convertible yet: {family.missing_reason}')
  return family.convert(state_dict, config)


# --------------------------------------------------------------------------
# Shared checks
# --------------------------------------------------------------------------


def _flatten(tree: Any) -> dict[str, Any]:
  return {'/'.join(str(k.key) for k in path): leaf
          for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _unflatten(flat: dict[str, np.ndarray]) -> dict[str, Any]:
  tree: dict[str, Any] = {}
  for path, value in flat.items():
    node = tree
    *parents, leaf = path.split('/')
    for key in parents:
      node = node.setdefault(key, {})
    node[leaf] = value
  return tree


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

  target = _flatten(abstract_params)
  problems = []
  if m.missing:
    problems.append('missing keys (the config builds a part the checkpoint '
                    'does not have):\n    ' + '\n    '.join(
                        k + hint(k) for k in m.missing))
  unknown = m.unknown()
  if unknown:
    problems.append('unknown keys (the checkpoint has a part the config '
                    'does not build):\n    ' + '\n    '.join(
                        k + hint(k) for k in unknown))
  if problems:
    raise ConversionError('the checkpoint does not fit the config:\n  ' +
                          '\n  '.join(problems))

  mismatches = []
  for path, assigned in m.params.items():
    if path not in target:
      mismatches.append(f'{assigned.source} {assigned.source_shape}: the '
                        f'model has no parameter {path}; change '
                        f'{assigned.field}')
    elif tuple(target[path].shape) != assigned.value.shape:
      mismatches.append(
          f'{assigned.source}: checkpoint shape {assigned.source_shape} '
          f'gives {path} {assigned.value.shape}, the config builds '
          f'{tuple(target[path].shape)}; change {assigned.field}')
  unfilled = sorted(set(target) - set(m.params))
  if unfilled:
    mismatches.append('parameters of the config\'s model no checkpoint key '
                      'fills: ' + ', '.join(unfilled))
  if mismatches:
    raise ConversionError('shape mismatch:\n  ' + '\n  '.join(mismatches))
  return _unflatten({path: m.params[path].value for path in target})


# --------------------------------------------------------------------------
# SAVi / stochastic SAVi (slotformer/base_slots/models/savi.py: StoSAVi)
# --------------------------------------------------------------------------


def savi_abstract_params(config: ml_collections.ConfigDict) -> Any:
  model = models.build_savi(config)
  video = jnp.zeros((1, 1, *config.data.resolution, 3), jnp.float32)
  rngs = {'params': jax.random.key(0), 'sample': jax.random.key(1)}
  return jax.eval_shape(lambda: model.init(rngs, video))['params']


def _check_grid(m: StateDictMapper, key: str, size: tuple[int, int],
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
  _check_grid(m, 'decoder_pos_embedding.grid',
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
  _check_grid(m, 'encoder_pos_embedding.grid',
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


def _map_savi_predictor(m: StateDictMapper, config: ml_collections.ConfigDict,
                        target: str):
  """The official predictors (slotformer/base_slots/models/predictor.py).

  The config decides which parts to read, so a checkpoint part the config
  lacks is reported as unknown keys with the field to change.
  """
  predictor = config.savi.predictor
  field = 'config.savi.predictor (kind / num_layers / mlp_size / lstm_size)'
  if predictor.kind == savi_module.RESIDUAL_MLP:  # ResidualMLPPredictor
    layers.layer_norm(m, 'predictor.ln', f'{target}/norm', field)
    layers.linear(m, 'predictor.mlp.0', f'{target}/hidden', field)
    layers.linear(m, 'predictor.mlp.2', f'{target}/out', field)
    return
  if predictor.kind == savi_module.TRANSFORMER_LSTM:  # RNNPredictorWrapper
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


def official_encoder_strides(config: ml_collections.ConfigDict,
                             section: str = 'savi'):
  """The official encoder halves 128x128 frames in its first layer only."""
  num_layers = len(config[section].encoder.features)
  first = 2 if config.data.resolution[0] == 128 else 1
  return (first,) + (1,) * (num_layers - 1)


def convert_savi(state_dict: dict[str, np.ndarray],
                 config: ml_collections.ConfigDict) -> Converted:
  """Official StoSAVi (deterministic when trained with kld_method='none')."""
  require(config, 'slot_model', 'savi', 'is a SAVi')
  require(config, 'savi.initial_slots', 'learned',
          'starts from one learned vector per slot (init_latents)')
  require(config, 'savi.layer_norm_epsilon', PYTORCH_LN_EPSILON,
          "uses PyTorch's LayerNorm epsilon")
  require(config, 'savi.encoder.strides', official_encoder_strides(config),
          f'strides its encoder so at {tuple(config.data.resolution)}')
  if max(config.savi.encoder.strides) > 1:
    require(config, 'savi.encoder.padding', 'pytorch',
            'pads its strided convolution by K // 2 on every side')
  m = StateDictMapper(state_dict)
  latents = m.take('init_latents')  # [1, N, D]
  if latents is not None:
    m.put('initial_slots', latents[0], 'init_latents', latents.shape,
          'config.savi.num_slots / slot_size')
  map_cnn_encoder(m, config)
  _map_posterior_head(m, config, 'frame_step/posterior_head')
  map_slot_attention(m, 'frame_step/corrector')
  _map_savi_predictor(m, config, 'frame_step/predictor')
  map_spatial_broadcast_decoder(m, config)
  # The official code builds it "just for compatibility" and never uses it.
  m.skip_prefix('prior_slot_layer.')
  params = assemble(m, savi_abstract_params(config), hints={
      'predictor.rnn': 'config.savi.predictor.kind / lstm_size',
      'predictor.out_projector': 'config.savi.predictor.kind / lstm_size',
      'predictor.': 'config.savi.predictor.kind',
      'kernel_dist_layer': 'config.savi.posterior_head',
      'encoder': 'config.savi.encoder.features',
      'decoder': 'config.savi.decoder.features',
  })
  return Converted('savi', SAVI_STAGE, params)


def _is_savi(keys: set[str]) -> bool:
  return ('slot_attention.project_k.weight' in keys
          and 'init_latents' in keys and 'encoder_out_layer.1.weight' in keys)


# --------------------------------------------------------------------------
# SlotFormer (slotformer/video_prediction/models/slotformer.py)
# --------------------------------------------------------------------------


def slotformer_abstract_params(config: ml_collections.ConfigDict) -> Any:
  model = models.build_slotformer(config)
  dynamics = config.slotformer
  history = jnp.zeros((1, dynamics.burn_in, config.savi.num_slots,
                       config.savi.slot_size), jnp.float32)
  return jax.eval_shape(
      lambda: model.init(jax.random.key(0), history, 1))['params']


def convert_slotformer(state_dict: dict[str, np.ndarray],
                       config: ml_collections.ConfigDict) -> Converted:
  """Official SlotFormer: `rollouter.*` plus its frozen copy of SAVi's
  decoder, returned in `extras['decoder']` to be checked against the SAVi
  checkpoint of the same run."""
  require(config, 'slot_model', 'savi', 'runs on SAVi slots')
  m = StateDictMapper(state_dict)
  map_rollouter(m, config)
  decoder = StateDictMapper(state_dict)
  map_spatial_broadcast_decoder(decoder, config, target='decoder')
  for key in state_dict:  # what the decoder read is known to `m` too
    if key.startswith('decoder'):
      m.skip(key)
  params = assemble(m, slotformer_abstract_params(config), hints={
      'rollouter.transformer_encoder': 'config.slotformer.num_layers',
  })
  decoder_model = models.build_decoder(config)
  decoder_abstract = jax.eval_shape(lambda: decoder_model.init(
      jax.random.key(0), jnp.zeros((1, config.savi.num_slots,
                                    config.savi.slot_size))))['params']
  decoder_params = assemble(
      _only(decoder, 'decoder/'), {'decoder': decoder_abstract}, hints={})
  return Converted('slotformer', SLOTFORMER_STAGE, params,
                   extras={'decoder': decoder_params['decoder']})


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
    context = max(dynamics.burn_in, dynamics.get('max_context', 0))
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


def _only(m: StateDictMapper, prefix: str) -> StateDictMapper:
  """`m` restricted to the parameters under `prefix` (and its keys)."""
  restricted = StateDictMapper({})
  restricted.missing = list(m.missing)
  restricted.params = {k: v for k, v in m.params.items()
                       if k.startswith(prefix)}
  return restricted


def _is_slotformer(keys: set[str]) -> bool:
  return 'rollouter.in_proj.weight' in keys


# --------------------------------------------------------------------------
# The registry. Families recognised but not implemented yet say so.
# --------------------------------------------------------------------------

def _convert_steve_family(name: str):
  """The STEVE families' converters live in steve_families.py, which uses
  this module's helpers: imported when first called."""

  def convert(state_dict, config):
    from slotformer_jax.official import steve_families  # pylint: disable=g-import-not-at-top
    return getattr(steve_families, f'convert_{name}')(state_dict, config)

  return convert


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


# Order matters: the first family whose keys match converts.
register(Family('steve_slotformer', _is_steve_slotformer,
                _convert_steve_family('steve_slotformer')))
register(Family('steve', _is_steve, _convert_steve_family('steve')))
register(Family('savi', _is_savi, convert_savi))
register(Family('slotformer', _is_slotformer, convert_slotformer))


def _lazy(module: str, function: str, detect_name: str):
  """(detect, convert) of a family in official/<module>.py, which uses this
  module's helpers: imported when first called."""

  def load(name):
    import importlib  # pylint: disable=g-import-not-at-top
    return getattr(importlib.import_module(
        f'slotformer_jax.official.{module}'), name)

  return (lambda keys: load(detect_name)(keys),
          lambda state_dict, config: load(function)(state_dict, config))


register(Family('phyre_readout', *_lazy('readouts', 'convert_phyre_readout',
                                        'is_phyre_readout')))
register(Family('physion_readout', *_lazy(
    'readouts', 'convert_physion_readout', 'is_physion_readout')))
register(Family('aloe', *_lazy('aloe', 'convert_aloe', 'is_aloe')))
register(Family('dvae', _is_dvae, _convert_steve_family('dvae')))
