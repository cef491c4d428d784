"""The official-checkpoint converter against an independent NumPy
implementation of the official layers (tests/official_reference.py).

State dicts here have the official key names and shapes and random values;
each mapped layer kind is checked by running this project's module with the
converted parameters and comparing with NumPy, then whole converted models
(SlotFormer rollout, SAVi encoder / corrector / decoder / predictor) are,
then the errors and the workdir the converter writes.
"""

import json
import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import official_reference as ref
from slotformer_jax.official import convert as convert_official
from slotformer_jax.config.defaults import base_config
from slotformer_jax.modules.decoders import SubPixelConvTranspose
from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.transformer import TransformerBlock
from slotformer_jax.official import families
from slotformer_jax.official import layers
from slotformer_jax.official.layers import StateDictMapper
from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.official import common
from slotformer_jax.workdir.paths import Paths
from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax.slot_models.savi import build_decoder
from slotformer_jax.slot_models.savi import build_savi
from pipeline_helpers import run_stage
from slotformer_jax.errors import UserError
from slotformer_jax.run import Run

# float32 modules vs the float64 reference, values of order 1.
TOLERANCE = 1e-4


def _params(m: StateDictMapper, prefix: str):
  return common.unflatten({
      path[len(prefix) + 1:]: assigned.value
      for path, assigned in m.params.items() if path.startswith(prefix + '/')})


def _apply(module, params, *args, **kwargs):
  """module.apply, jitted: one compile beats op-by-op dispatch on a CPU."""
  return jax.jit(module.apply, static_argnames=('method',),
                 static_argnums=tuple(
                     i + 1 for i, a in enumerate(args) if isinstance(a, int)))(
                         {'params': params}, *args, **kwargs)


def _close(actual, expected, tolerance=TOLERANCE):
  actual = np.asarray(actual, np.float64)
  assert actual.shape == expected.shape
  assert np.max(np.abs(actual - expected)) < tolerance, np.max(
      np.abs(actual - expected))


# --------------------------------------------------------------------------
# One layer kind at a time
# --------------------------------------------------------------------------


@pytest.fixture
def r():
  return ref._Random(0)  # pylint: disable=protected-access


def test_linear(r):
  sd = {}
  ref.add_linear(sd, r, 'fc', 5, 7)
  m = StateDictMapper(sd)
  layers.linear(m, 'fc', 'layer', 'field')
  x = r.rng.standard_normal((3, 5))
  out = nn.Dense(7).apply({'params': _params(m, 'layer')}, x)
  _close(out, ref.linear(x, sd, 'fc'))


@pytest.mark.parametrize('stride', [1, 2])
def test_conv2d_with_pytorch_padding(r, stride):
  sd = {'conv.weight': r.matrix(6, 3, 5, 5), 'conv.bias': r.vector(6)}
  m = StateDictMapper(sd)
  layers.conv(m, 'conv', 'layer', 'field')
  x = r.rng.standard_normal((2, 3, 12, 12))
  # PyTorch pads k // 2 on every side, also at stride 2.
  conv = nn.Conv(6, (5, 5), strides=(stride, stride), padding=((2, 2), (2, 2)))
  out = conv.apply({'params': _params(m, 'layer')}, x.transpose(0, 2, 3, 1))
  expected = ref.conv2d(x, sd['conv.weight'], sd['conv.bias'], stride, 2)
  _close(out, expected.transpose(0, 2, 3, 1))


@pytest.mark.parametrize('stride', [1, 2])
def test_conv_transpose2d(r, stride):
  """Stride 2: the sub-pixel layer (kernel unflipped); stride 1: a 'same'
  convolution with the flipped kernel, as the decoder evaluates them."""
  sd = {'deconv.weight': r.transposed(4, 6, 5), 'deconv.bias': r.vector(6)}
  m = StateDictMapper(sd)
  layers.conv_transpose(m, 'deconv', 'layer', 'field', stride=stride)
  x = r.rng.standard_normal((2, 4, 6, 6))
  module = (SubPixelConvTranspose(6, 5, stride=2) if stride == 2 else
            nn.Conv(6, (5, 5), padding='SAME'))
  out = module.apply({'params': _params(m, 'layer')}, x.transpose(0, 2, 3, 1))
  expected = ref.conv_transpose2d(x, sd['deconv.weight'], sd['deconv.bias'],
                                  stride, 2, stride - 1)
  assert expected.shape[-1] == 6 * stride
  _close(out, expected.transpose(0, 2, 3, 1))


def test_layer_norm(r):
  sd = {}
  ref.add_layer_norm(sd, r, 'ln', 8)
  m = StateDictMapper(sd)
  layers.layer_norm(m, 'ln', 'layer', 'field')
  x = 3 * r.rng.standard_normal((4, 8)) + 1
  out = nn.LayerNorm(epsilon=ref.LN_EPS).apply({'params': _params(m, 'layer')},
                                               x)
  _close(out, ref.layer_norm(x, sd, 'ln'))


def test_gru_cell(r):
  sd = {'gru.weight_ih': r.matrix(3 * 6, 5), 'gru.weight_hh': r.matrix(18, 6),
        'gru.bias_ih': r.vector(18, 0.5), 'gru.bias_hh': r.vector(18, 0.5)}
  m = StateDictMapper(sd)
  layers.gru_cell(m, 'gru', 'layer', 'field')
  x, h = r.rng.standard_normal((3, 5)), r.rng.standard_normal((3, 6))
  new_h, _ = nn.GRUCell(6).apply({'params': _params(m, 'layer')}, h, x)
  _close(new_h, ref.gru_cell(x, h, sd, 'gru'))


def test_lstm(r):
  sd = {'rnn.weight_ih_l0': r.matrix(4 * 6, 5),
        'rnn.weight_hh_l0': r.matrix(24, 6),
        'rnn.bias_ih_l0': r.vector(24, 0.5), 'rnn.bias_hh_l0': r.vector(24, 0.5)}
  m = StateDictMapper(sd)
  layers.lstm(m, 'rnn', 'layer', 'field')
  x = r.rng.standard_normal((3, 5))
  h, c = r.rng.standard_normal((3, 6)), r.rng.standard_normal((3, 6))
  (new_c, new_h), _ = nn.OptimizedLSTMCell(6).apply(
      {'params': _params(m, 'layer')}, (c, h), x)
  expected_h, expected_c = ref.lstm_step(x, h, c, sd, 'rnn')
  _close(new_h, expected_h)
  _close(new_c, expected_c)


def test_multihead_attention(r):
  sd = {'attn.in_proj_weight': r.matrix(24, 8),
        'attn.in_proj_bias': r.vector(24)}
  ref.add_linear(sd, r, 'attn.out_proj', 8, 8)
  m = StateDictMapper(sd)
  layers.multihead_attention(m, 'attn', 'layer', 'field', num_heads=2)
  x = r.rng.standard_normal((2, 5, 8))
  out = nn.MultiHeadDotProductAttention(num_heads=2).apply(
      {'params': _params(m, 'layer')}, x)
  _close(out, ref.multihead_attention(x, sd, 'attn', 2))


def test_transformer_encoder_layer_pre_ln(r):
  sd = {}
  ref.add_transformer_layer(sd, r, 'layer0', 8, 16)
  m = StateDictMapper(sd)
  layers.transformer_encoder_layer(m, 'layer0', 'block', 'field', num_heads=2)
  x = r.rng.standard_normal((2, 5, 8))
  out = TransformerBlock(num_heads=2, mlp_size=16, pre_norm=True).apply(
      {'params': _params(m, 'block')}, x)
  # LayerNorm epsilon: 1e-5 officially, flax's 1e-6 by default: an
  # O(1e-6) difference on unit-variance tokens, inside the tolerance.
  _close(out, ref.transformer_layer(x, sd, 'layer0', 2))


# --------------------------------------------------------------------------
# Whole models on a tiny config
# --------------------------------------------------------------------------


def tiny_config():
  config = base_config()
  config.data.resolution = (16, 16)
  savi = config.savi
  savi.num_slots, savi.slot_size = 3, 16
  savi.encoder.features, savi.encoder.output_size = (8, 8), 16
  savi.encoder.strides = (1, 1)
  savi.encoder.padding = 'pytorch'
  savi.slot_attention.mlp_size = 32
  # The OBJ3D / PHYRE layout (see configs/obj3d.py).
  savi.predictor.update(kind='transformer_lstm', num_layers=1, num_heads=2,
                        mlp_size=32, lstm_size=24)
  savi.posterior_head = 'mlp'
  savi.layer_norm_epsilon = 1e-5
  savi.decoder.broadcast_resolution, savi.decoder.features = (4, 4), (8, 8, 8)
  dyn = config.slotformer
  dyn.burn_in, dyn.embed_dim, dyn.num_layers = 3, 32, 2
  dyn.num_heads, dyn.mlp_ratio = 4, 2
  dyn.layer_norm_epsilon = 1e-5
  savi.num_train_steps = dyn.num_train_steps = 10
  return config


def clevrer_layout(config):
  """The official CLEVRER StoSAVi layout (see configs/clevrer.py)."""
  config.savi.predictor.update(kind='residual_mlp', mlp_size=32, lstm_size=0)
  config.savi.posterior_head = 'linear'
  return config


def official_savi(config, seed=0):
  savi = config.savi
  layout = ({'predictor': 'residual_mlp', 'head': 'linear'}
            if savi.predictor.kind == 'residual_mlp' else {})
  return ref.savi_state_dict(
      seed, num_slots=savi.num_slots, slot_size=savi.slot_size,
      encoder_features=savi.encoder.features,
      encoder_size=savi.encoder.output_size,
      feature_resolution=config.data.resolution,
      slot_mlp_size=savi.slot_attention.mlp_size,
      decoder_features=savi.decoder.features,
      broadcast=savi.decoder.broadcast_resolution,
      predictor_layers=savi.predictor.num_layers,
      predictor_ffn=savi.predictor.mlp_size,
      lstm_size=savi.predictor.lstm_size, **layout)


def official_slotformer(config, savi_state, seed=1):
  dyn = config.slotformer
  return ref.slotformer_state_dict(
      seed, slot_size=config.savi.slot_size, d_model=dyn.embed_dim,
      num_layers=dyn.num_layers, ffn=dyn.mlp_ratio * dyn.embed_dim,
      history_len=dyn.burn_in, cond_len=dyn.max_context,
      decoder_from=savi_state)


def test_slotformer_rollout_and_frozen_decoder():
  config = tiny_config()
  savi_state = official_savi(config)
  state = official_slotformer(config, savi_state)
  converted = families.convert_state_dict(state, config)
  assert converted.family == 'slotformer'
  rng = np.random.default_rng(2)
  slots = rng.standard_normal((2, 3, 3, 16))
  model = dynamics_lib.build(config.slotformer, 'slotformer')
  predicted = _apply(model, converted.params, jnp.asarray(slots), 6)
  expected = ref.slot_rollouter(slots, state, 6, num_heads=4, num_layers=2)
  _close(predicted, expected)
  decoded = _apply(build_decoder(config.savi.decoder,
                                        tuple(config.data.resolution)),
                   converted.extras['decoder'],
                   jnp.asarray(slots[:, 0]))
  recon, masks = ref.savi_decoder(slots[:, 0], state, (16, 16), (4, 4))
  _close(decoded.recon, recon.transpose(0, 2, 3, 1))
  _close(decoded.alpha_masks, masks.transpose(0, 1, 3, 4, 2))


@pytest.mark.parametrize('layout', ['obj3d', 'clevrer'])
def test_savi_video(layout):
  """A converted deterministic SAVi over 3 frames against the official
  definition: posterior-head mean -> Slot Attention -> predictor."""
  config = tiny_config() if layout == 'obj3d' else clevrer_layout(
      tiny_config())
  state = official_savi(config)
  params = families.convert_state_dict(state, config).params
  video = np.random.default_rng(4).uniform(-1, 1, (2, 3, 3, 16, 16))
  output = _apply(build_savi(config.savi,
                                    tuple(config.data.resolution)), params,
                  jnp.asarray(video.transpose(0, 1, 3, 4, 2)))
  predictor = config.savi.predictor
  expected = ref.savi_forward(
      video, state, num_iterations=2, num_heads=predictor.num_heads,
      num_layers=predictor.num_layers, lstm_size=predictor.lstm_size,
      predictor=predictor.kind, head=config.savi.posterior_head)
  _close(output.slots, expected)
  recon, _ = ref.savi_decoder(expected.reshape(6, 3, 16), state, (16, 16),
                              (4, 4))
  _close(output.decoded.recon.reshape(6, 16, 16, 3),
         recon.transpose(0, 2, 3, 1))


def test_slotformer_growing_context():
  """The PHYRE model: 1 observed frame, the context grows to 4 frames
  (official cond_len), then slides."""
  config = tiny_config()
  config.slotformer.update(burn_in=1, max_context=4)
  state = official_slotformer(config, official_savi(config))
  converted = families.convert_state_dict(state, config)
  slots = np.random.default_rng(5).standard_normal((2, 1, 3, 16))
  predicted = _apply(dynamics_lib.build(config.slotformer, 'slotformer'), converted.params,
                     jnp.asarray(slots), 7)
  _close(predicted, ref.single_step_rollouter(slots, state, 7, num_heads=4,
                                              num_layers=2))


@pytest.mark.slow  # test_savi_video covers the same parts end to end
def test_savi_parts():
  """Encoder, Slot Attention corrector, decoder and the Transformer + LSTM
  predictor of a converted SAVi, each against the official definition."""
  config = tiny_config()
  state = official_savi(config)
  params = families.convert_state_dict(state, config).params
  rng = np.random.default_rng(3)
  savi = config.savi

  img = rng.uniform(-1, 1, (2, 3, 16, 16))
  features = _apply(
      CNNEncoder(features=(8, 8), strides=(1, 1), output_size=16,
                 padding='pytorch', layer_norm_epsilon=1e-5),
      params['encoder'], jnp.asarray(img.transpose(0, 2, 3, 1)))
  expected_features = ref.savi_encoder(img, state)
  _close(features, expected_features)

  slots = rng.standard_normal((2, 3, 16))
  corrected = _apply(SlotAttention(num_iterations=2, mlp_size=32,
                                   layer_norm_epsilon=1e-5),
                     params['frame_step']['corrector'], jnp.asarray(slots),
                     jnp.asarray(expected_features))
  _close(corrected, ref.slot_attention(expected_features, slots, state, 2))

  decoded = _apply(build_savi(config.savi,
                                     tuple(config.data.resolution)), params,
                   jnp.asarray(slots),
                   method='decode')
  recon, _ = ref.savi_decoder(slots, state, (16, 16), (4, 4))
  _close(decoded.recon, recon.transpose(0, 2, 3, 1))

  from slotformer_jax.modules.transitions import SlotTransition  # pylint: disable=g-import-not-at-top
  transition = SlotTransition(num_layers=1, num_heads=2, mlp_size=32,
                              lstm_size=savi.predictor.lstm_size,
                              layer_norm_epsilon=1e-5)
  h = rng.standard_normal((6, 24))
  c = rng.standard_normal((6, 24))
  carry = (jnp.asarray(c.reshape(2, 3, 24)), jnp.asarray(h.reshape(2, 3, 24)))
  predicted, (new_c, new_h) = _apply(
      transition, params['frame_step']['predictor'], jnp.asarray(slots), carry)
  expected, (expected_h, expected_c) = ref.transformer_lstm_predictor(
      slots, (h, c), state, num_layers=1, num_heads=2)
  _close(predicted, expected)
  _close(new_h, expected_h.reshape(2, 3, 24))
  _close(new_c, expected_c.reshape(2, 3, 24))

  np.testing.assert_array_equal(params['initial_slots'],
                                state['init_latents'][0].astype(np.float32))


# --------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------


def test_missing_and_unknown_keys_in_one_error():
  config = tiny_config()
  state = official_savi(config)
  del state['slot_attention.gru.bias_hh']
  del state['encoder_out_layer.3.weight']
  state['slot_attention.extra.weight'] = np.zeros(3)
  with pytest.raises(families.ConversionError) as error:
    families.convert_state_dict(state, config)
  message = str(error.value)
  for key in ('slot_attention.gru.bias_hh', 'encoder_out_layer.3.weight',
              'slot_attention.extra.weight'):
    assert key in message
  assert 'missing keys' in message and 'unknown keys' in message


def test_unknown_part_names_the_config_field():
  state = official_savi(tiny_config())
  config = tiny_config()
  config.savi.predictor.update(kind='transformer', lstm_size=0)
  config.savi.posterior_head = 'none'
  with pytest.raises(families.ConversionError) as error:
    families.convert_state_dict(state, config)
  message = str(error.value)
  assert ('predictor.rnn.weight_ih_l0  (config.savi.predictor.kind / '
          'lstm_size)') in message
  assert 'kernel_dist_layer.3.weight  (config.savi.posterior_head)' in message


@pytest.mark.parametrize('field, value', [
    ('savi.decoder.broadcast_resolution', (8, 8)),
    ('savi.layer_norm_epsilon', 1e-6),
    ('savi.encoder.strides', (2, 1)),
    ('savi.initial_slots', 'gaussian'),
])
def test_savi_config_must_be_the_official_one(field, value):
  config = tiny_config()
  state = official_savi(config)
  section, *rest = field.split('.')
  node = config[section]
  for key in rest[:-1]:
    node = node[key]
  node[rest[-1]] = value
  with pytest.raises(families.ConversionError, match=f'config.{field}'):
    families.convert_state_dict(state, config)


def test_shape_mismatch_names_key_shapes_and_field():
  config = tiny_config()
  state = official_savi(config)
  config.savi.num_slots = 5
  with pytest.raises(families.ConversionError) as error:
    families.convert_state_dict(state, config)
  message = str(error.value)
  assert 'init_latents: checkpoint shape (1, 3, 16)' in message
  assert 'builds (5, 16)' in message
  assert 'config.savi.num_slots' in message


def test_slotformer_config_must_match():
  config = tiny_config()
  state = official_slotformer(config, official_savi(config))
  config.slotformer.residual = True
  with pytest.raises(families.ConversionError, match='slotformer.residual'):
    families.convert_state_dict(state, config)
  config.slotformer.residual = False
  config.slotformer.num_heads = 3  # 32 not divisible by 3
  with pytest.raises(ValueError, match='not divisible by 3 heads'):
    families.convert_state_dict(state, config)


@pytest.mark.parametrize('keys, family', [
    (('in_proj.weight', 'transformer_encoder.layers.0.linear1.weight',
      'cls_mlp.0.weight'), 'phyre_readout'),
    (('comb_idx', 'linear1.weight', 'linear2.weight'), 'physion_readout'),
    (('transformer_model.cls_answer_mlp.0.weight',
      'transformer_model.text_token'), 'aloe'),
])
def test_downstream_families_are_recognised(keys, family):
  """Official key layouts of the VQA model and the readouts (see the
  official modules) are recognised; their converters (tests/
  test_convert_aloe.py) refuse a config of another task."""
  state = {key: np.zeros(1) for key in keys}
  assert families.detect_family(state).name == family
  with pytest.raises(families.ConversionError, match='--config=configs/'):
    families.convert_state_dict(state, tiny_config())


def test_unrecognised_state_dict():
  with pytest.raises(families.ConversionError, match='no official model'):
    families.convert_state_dict({'foo': np.zeros(1)}, tiny_config())


def test_bgr_datasets_need_bgr():
  config = tiny_config()
  config.data.name = 'clevrer'
  with pytest.raises(families.ConversionError, match='channel_order=bgr'):
    convert_official.check_channel_order(config)
  config.data.channel_order = 'bgr'
  convert_official.check_channel_order(config)
  assert savi_slots.model_fields(config.savi, config.data)[
      'channel_order'] == 'bgr'


# --------------------------------------------------------------------------
# The workdir the pipeline reads
# --------------------------------------------------------------------------


def _convert_files(config, workdir, tmp_path, monkeypatch, states):
  """convert_official.convert_files on {file name: state dict}, the .pth
  reading replaced by the dicts (the reader has its own tests)."""
  files = {str(tmp_path / name): state for name, state in states.items()}
  for path in files:
    open(path, 'wb').close()
  monkeypatch.setattr(convert_official.pth_reader, 'read_state_dict',
                      lambda path, reader: files[path])
  return convert_official.convert_files(config, workdir, list(files))


def test_writes_where_the_pipeline_reads(tmp_path, monkeypatch):
  """SlotFormer listed first is still written after the SAVi its decoder is
  checked against; the pipeline's loaders read both back exactly."""
  config = tiny_config()
  workdir = str(tmp_path / 'run')
  savi_state = official_savi(config)
  slotformer_state = official_slotformer(config, savi_state)
  directories = _convert_files(
      config, workdir, tmp_path, monkeypatch,
      {'slotformer.pth': slotformer_state, 'savi.pth': savi_state})
  assert directories == [Paths.of(workdir).model('savi'),
                         Paths.of(workdir).dynamics('slotformer')]
  with open(os.path.join(directories[1],
                         convert_official.CONVERTED_FROM_FILE)) as f:
    provenance = json.load(f)
  assert provenance['file'] == str(tmp_path / 'slotformer.pth')
  assert provenance['family'] == 'slotformer'
  assert len(provenance['sha256']) == 64

  mesh = jax.sharding.Mesh(np.array(jax.devices()), ('data',))
  run = Run.create(config, workdir, mesh)
  loaded = run.stage1
  savi_params, savi_step = loaded.params['savi'], loaded.step
  assert savi_step == config.savi.num_train_steps
  expected = families.convert_state_dict(savi_state, config).params
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(savi_params),
               expected)
  dyn_params = run.dynamics('slotformer').params
  expected = families.convert_state_dict(slotformer_state, config).params
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(dyn_params),
               expected)
  # Never overwritten.
  with pytest.raises(FileExistsError):
    convert_official.write_converted(run, 'savi', expected, {})


def test_frozen_decoder_must_be_the_savi_decoder(tmp_path, monkeypatch):
  config = tiny_config()
  workdir = str(tmp_path / 'run')
  slotformer_state = official_slotformer(config, official_savi(config, seed=5))
  with pytest.raises(families.ConversionError, match='no SAVi checkpoint'):
    convert_official.check_frozen_decoder(
        Run.create(config, workdir),
        families.convert_state_dict(slotformer_state, config).extras['decoder'])
  # In one command: refused before anything is written.
  with pytest.raises(families.ConversionError,
                     match='frozen copy of the savi decoder differs'):
    _convert_files(config, workdir, tmp_path, monkeypatch,
                   {'savi.pth': official_savi(config),
                    'slotformer.pth': slotformer_state})
  assert not os.path.exists(Paths.of(workdir).model('savi'))
  # Against the SAVi an earlier command wrote.
  _convert_files(config, workdir, tmp_path, monkeypatch,
                 {'savi.pth': official_savi(config)})
  with pytest.raises(families.ConversionError, match='frozen decoder differs'):
    _convert_files(config, workdir, tmp_path, monkeypatch,
                   {'slotformer.pth': slotformer_state})


@pytest.mark.slow
def test_converted_workdir_runs_extract_evaluate_render(tmp_path):
  """Official-format weights in the official layout -> the workdir ->
  slot extraction, evaluation and pictures, with no training stage run."""
  import pipeline_helpers  # pylint: disable=g-import-not-at-top
  config = pipeline_helpers.micro_config('savi', tmp_path / 'data')
  config.slot_lstm.train = False
  config.slotformer.residual = False  # the official SlotFormer has none
  savi = config.savi
  savi.encoder.padding = 'pytorch'
  savi.predictor.update(kind='transformer_lstm', lstm_size=24)
  savi.posterior_head = 'mlp'
  savi.layer_norm_epsilon = config.slotformer.layer_norm_epsilon = 1e-5
  savi_state = ref.savi_state_dict(
      0, num_slots=savi.num_slots, slot_size=savi.slot_size,
      encoder_features=savi.encoder.features,
      encoder_size=savi.encoder.output_size,
      feature_resolution=config.data.resolution,
      slot_mlp_size=savi.slot_attention.mlp_size,
      decoder_features=savi.decoder.features,
      broadcast=savi.decoder.broadcast_resolution,
      predictor_layers=savi.predictor.num_layers,
      predictor_ffn=savi.predictor.mlp_size, lstm_size=24,
      kernel=savi.encoder.kernel_size)
  assert savi.decoder.kernel_size == savi.encoder.kernel_size
  slotformer_state = official_slotformer(config, savi_state)
  workdir = str(tmp_path / 'run')
  run = Run.create(config, workdir)
  for state in (savi_state, slotformer_state):
    converted = families.convert_state_dict(state, config)
    convert_official.write_converted(run, converted.stage, converted.params,
                                     {'file': 'test'})
  mesh = jax.sharding.Mesh(np.array(jax.devices()), ('data',))
  run_stage(config, workdir, mesh, 'extract_slots')
  results = run_stage(config, workdir, mesh, 'evaluate')
  pictures = run_stage(config, workdir, mesh, 'render')
  assert results['checkpoints'] == {
      'savi_step': savi.num_train_steps,
      'slotformer_step': config.slotformer.num_train_steps}
  per_step = results['rollout']['slotformer']['psnr']['per_step']
  assert len(per_step) == config.evaluation.rollout_steps
  assert all(np.isfinite(v) for v in per_step)
  assert any(p.endswith('.gif') for p in pictures)


def test_the_mean_path_of_a_stochastic_savi_is_a_fresh_conversion(
    tmp_path, monkeypatch):
  """docs/official_weights.md: the stochastic SAVi's mean path on the same
  weights is a conversion with --config.savi.stochastic=false into a fresh
  workdir (its slots do not depend on the sampling key); the stochastic
  workdir itself refuses that setting, in one line naming the field."""
  state = official_savi(clevrer_layout(tiny_config()))
  stochastic = clevrer_layout(tiny_config())
  stochastic.savi.stochastic = True
  _convert_files(stochastic, str(tmp_path / 'sampled'), tmp_path,
                 monkeypatch, {'savi.pth': state})
  mean = clevrer_layout(tiny_config())
  mean.savi.stochastic = False
  with pytest.raises(UserError, match='stochastic: checkpoint True vs '
                     'config False'):
    Run.create(mean, str(tmp_path / 'sampled')).stage1  # pylint: disable=expression-not-assigned
  _convert_files(mean, str(tmp_path / 'mean'), tmp_path, monkeypatch,
                 {'savi.pth': state})
  run = Run.create(mean, str(tmp_path / 'mean'))
  video = np.random.default_rng(0).integers(0, 256, (1, 2, 16, 16, 3),
                                            np.uint8)
  slots = [run.slot_model.encode(run.stage1.params, video,
                                 jax.random.key(k), None)[0]
           for k in (1, 2)]
  np.testing.assert_array_equal(slots[0], slots[1])
  sampled = Run.create(stochastic, str(tmp_path / 'sampled'))
  drawn = [sampled.slot_model.encode(sampled.stage1.params, video,
                                     jax.random.key(k), None)[0]
           for k in (1, 2)]
  assert np.abs(np.asarray(drawn[0]) - np.asarray(drawn[1])).max() > 0
  # The mean path is the sample's mean: the same weights, no noise.
  jax.tree.map(np.testing.assert_array_equal, run.stage1.params,
               sampled.stage1.params)
