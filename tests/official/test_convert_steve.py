"""Official dVAE / STEVE / STEVESlotFormer (Physion) checkpoints -> this
project's parameters, checked against an independent NumPy implementation
of the official modules (official_steve_reference.py) on official-format
state dicts with random values. No torch needed."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import official_reference as ref
import official_steve_reference as sref
from slotformer_jax.official import convert as convert_official
from slotformer_jax.config.defaults import base_config
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.official import families
from slotformer_jax.official import layers
from slotformer_jax.official.layers import StateDictMapper
from slotformer_jax.official import common
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.slot_models.steve import build_steve
from slotformer_jax.slot_models.steve import build_dvae
from slotformer_jax import dynamics as dynamics_lib
from pipeline_helpers import run_stage
from slotformer_jax.slot_models import chain as chain_lib
from slotformer_jax.run import Run

TOLERANCE = 1e-4


def _close(actual, expected, tolerance=TOLERANCE):
  actual = np.asarray(actual, np.float64)
  assert actual.shape == expected.shape, (actual.shape, expected.shape)
  worst = np.max(np.abs(actual - expected))
  assert worst < tolerance, worst


def steve_config(resolution=32):
  """The official Physion architecture with tiny widths. At 128x128 the
  encoder's first convolution has stride 2 (PyTorch padding)."""
  config = base_config()
  config.slot_model = 'steve'
  config.data.name = 'physion'
  config.data.resolution = (resolution, resolution)
  config.dvae.vocab_size, config.dvae.hidden_size = 24, 8
  steve = config.steve
  steve.num_slots, steve.slot_size = 3, 16
  steve.encoder.update(features=(8, 8), kernel_size=3, output_size=16,
                       strides=(2 if resolution == 128 else 1, 1),
                       padding='pytorch')
  steve.slot_attention.mlp_size = 24
  steve.predictor.update(num_layers=1, num_heads=2, mlp_size=32,
                         lstm_size=24)
  steve.decoder.update(num_layers=2, num_heads=4)
  steve.layer_norm_epsilon = 1e-5
  steve.clip_length = 2
  dyn = config.slotformer
  dyn.burn_in, dyn.embed_dim, dyn.num_layers = 3, 32, 2
  dyn.num_heads, dyn.mlp_ratio = 4, 2
  dyn.layer_norm_epsilon = 1e-5
  dyn.image_loss_weight = 0.0
  config.dvae.num_train_steps = config.steve.num_train_steps = 10
  dyn.num_train_steps = 10
  return config


def official_dvae(config, seed=0):
  return sref.dvae_state_dict(seed, vocab_size=config.dvae.vocab_size,
                              hidden=config.dvae.hidden_size)


def official_steve(config, dvae_state, seed=1):
  steve = config.steve
  stride = steve.encoder.strides[0]
  height, width = config.data.resolution
  return sref.steve_state_dict(
      seed, dvae=dvae_state, num_slots=steve.num_slots,
      slot_size=steve.slot_size, encoder_features=steve.encoder.features,
      feature_resolution=(height // stride, width // stride),
      slot_mlp_size=steve.slot_attention.mlp_size,
      predictor_layers=steve.predictor.num_layers,
      predictor_ffn=steve.predictor.mlp_size,
      vocab_size=config.dvae.vocab_size,
      num_tokens=height * width // 16,
      decoder_layers=steve.decoder.num_layers,
      kernel=steve.encoder.kernel_size)


def official_steve_slotformer(config, dvae_state, steve_state, seed=2):
  dyn = config.slotformer
  return sref.steve_slotformer_state_dict(
      seed, dvae=dvae_state, steve=steve_state,
      slot_size=config.steve.slot_size, d_model=dyn.embed_dim,
      num_layers=dyn.num_layers, ffn=dyn.mlp_ratio * dyn.embed_dim,
      history_len=dyn.burn_in)


@pytest.fixture(scope='module')
def states():
  config = steve_config()
  dvae = official_dvae(config)
  steve = official_steve(config, dvae)
  return config, dvae, steve, official_steve_slotformer(config, dvae, steve)


@pytest.fixture(scope='module')
def converted(states):
  """The converted (dVAE, STEVE, STEVESlotFormer) of `states`."""
  config = states[0]
  return tuple(families.convert_state_dict(state, config)
               for state in states[1:])


# --------------------------------------------------------------------------
# One layer kind at a time
# --------------------------------------------------------------------------


def test_slate_attention_causal_and_cross():
  """proj_q/k/v/o [E, E] -> the decoder's Attention, causal self-attention
  and cross-attention to another sequence."""
  from slotformer_jax.modules.token_decoder import Attention  # pylint: disable=g-import-not-at-top
  r = ref._Random(0)  # pylint: disable=protected-access
  sd = {f'a.proj_{p}.weight': r.matrix(12, 12) for p in 'qkvo'}
  m = StateDictMapper(sd)
  layers.slate_attention(m, 'a', 't', 'field', num_heads=3)
  params = common.unflatten(
      {k[2:]: v.value for k, v in m.params.items()})
  x, context = r.rng.standard_normal((2, 5, 12)), r.rng.standard_normal(
      (2, 4, 12))
  module = Attention(12, 3)
  for causal, kv in ((True, x), (False, context)):
    out = module.apply({'params': params}, x.astype(np.float32),
                       kv.astype(np.float32), causal=causal,
                       deterministic=True)
    _close(out, sref.slate_attention(x, kv, sd, 'a', 3, causal=causal))


def test_pixel_shuffle_channel_order():
  from slotformer_jax.modules.dvae import pixel_shuffle  # pylint: disable=g-import-not-at-top
  x = np.random.default_rng(0).standard_normal((2, 3, 4, 12))  # NHWC
  out = pixel_shuffle(x, 2)
  expected = sref.pixel_shuffle(x.transpose(0, 3, 1, 2), 2)
  np.testing.assert_array_equal(np.asarray(out).transpose(0, 3, 1, 2),
                                expected)


# --------------------------------------------------------------------------
# Whole models
# --------------------------------------------------------------------------


def test_dvae_logits_tokens_and_reconstruction(states, converted):
  config, dvae_state, _, _ = states
  converted = converted[0]
  assert converted.family == 'dvae' and converted.stage == 'dvae'
  model = build_dvae(config.dvae)
  rng = np.random.default_rng(0)
  img = rng.uniform(-1, 1, (2, 3, *config.data.resolution))
  variables = {'params': converted.params}
  images = img.transpose(0, 2, 3, 1).astype(np.float32)
  logits = jax.jit(lambda v, x: model.apply(v, x, method=DVAE.logits))(
      variables, images)
  expected = sref.dvae_logits(img, dvae_state)
  _close(np.asarray(logits).transpose(0, 3, 1, 2), expected)
  tokens = jax.jit(lambda v, x: model.apply(v, x, method=DVAE.tokenize))(
      variables, images)
  np.testing.assert_array_equal(tokens, expected.argmax(1))
  # The decoder on soft codes (as in training) and on tokens (generation).
  codes = ref.softmax(rng.standard_normal(expected.shape) * 3, 1)
  recon = jax.jit(lambda v, z: model.apply(v, z, method=DVAE.decode))(
      variables, codes.transpose(0, 2, 3, 1).astype(np.float32))
  _close(np.asarray(recon).transpose(0, 3, 1, 2),
         sref.dvae_decode(codes, dvae_state))


def test_steve_slots_masks_and_token_logits():
  """At 128x128, as the official model: the first encoder convolution has
  stride 2 with PyTorch's padding, the token decoder sees 32x32 = 1024
  tokens."""
  resolution = 128
  config = steve_config(resolution)
  dvae_state = official_dvae(config)
  state = official_steve(config, dvae_state)
  converted = families.convert_state_dict(state, config)
  assert converted.family == 'steve' and converted.stage == 'steve'
  assert common.max_difference(
      converted.extras['dvae'],
      families.convert_state_dict(dvae_state, config).params) == 0
  model = build_steve(config.steve, tuple(config.data.resolution),
                             config.dvae.vocab_size)
  rng = np.random.default_rng(1)
  time = 3
  video = rng.uniform(-1, 1, (2, time, 3, *config.data.resolution))
  slots, masks, _ = jax.jit(lambda p, v: model.apply(
      {'params': p}, v, method=STEVE.encode))(
          converted.params, video.transpose(0, 1, 3, 4, 2).astype(np.float32))
  steve = config.steve
  expected_slots, expected_masks = sref.steve_encode(
      video, state, first_stride=steve.encoder.strides[0],
      num_iterations=steve.slot_attention.num_iterations,
      num_heads=steve.predictor.num_heads,
      num_layers=steve.predictor.num_layers,
      lstm_size=steve.predictor.lstm_size)
  _close(slots, expected_slots)
  _close(np.asarray(masks).reshape(expected_masks.shape), expected_masks)
  # Token logits given the tokens (teacher forcing), from the slots above.
  num_tokens = resolution * resolution // 16
  tokens = rng.integers(0, config.dvae.vocab_size, (2, num_tokens))
  frame_slots = expected_slots[:, -1]
  logits = jax.jit(lambda p, s, t: model.apply(
      {'params': p}, s, t, method=STEVE.token_logits))(
          converted.params, frame_slots.astype(np.float32), tokens)
  expected = sref.token_decoder(frame_slots, tokens[:, :-1], state,
                                steve.decoder.num_heads,
                                steve.decoder.num_layers)
  _close(logits, expected)


def test_steve_slotformer_rollout_and_frozen_copies(states, converted):
  config, _, _, state = states
  dvae, steve, converted = converted
  assert converted.family == 'steve_slotformer'
  assert converted.stage == common.SLOTFORMER_STAGE
  assert common.max_difference(converted.extras['steve_decoder'],
                                       steve.params['decoder']) == 0
  assert common.max_difference(converted.extras['dvae'],
                                       dvae.params) == 0
  assert common.max_difference(steve.extras['dvae'],
                                       dvae.params) == 0
  dyn = config.slotformer
  rng = np.random.default_rng(2)
  history = rng.standard_normal((2, dyn.burn_in, config.steve.num_slots,
                                 config.steve.slot_size))
  model = dynamics_lib.build(config.slotformer, 'slotformer')
  steps = 4
  predicted = jax.jit(lambda p, h: model.apply({'params': p}, h, steps))(
      converted.params, history.astype(np.float32))
  _close(predicted, ref.slot_rollouter(history, state, steps, dyn.num_heads,
                                       dyn.num_layers))


# --------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------


def test_missing_and_unknown_keys_in_one_error(states):
  config, _, steve_state, _ = states
  state = dict(steve_state)
  del state['trans_decoder.tf_dec.blocks.1.ffn.0.weight']
  del state['predictor.rnn.weight_hh_l0']
  state['trans_decoder.extra.weight'] = np.zeros(3)
  with pytest.raises(families.ConversionError) as error:
    families.convert_state_dict(state, config)
  message = str(error.value)
  for key in ('trans_decoder.tf_dec.blocks.1.ffn.0.weight',
              'predictor.rnn.weight_hh_l0', 'trans_decoder.extra.weight'):
    assert key in message
  assert 'missing keys' in message and 'unknown keys' in message


def test_more_decoder_blocks_name_the_field(states):
  steve_state = states[2]
  config = steve_config()
  config.steve.decoder.num_layers = 1
  with pytest.raises(families.ConversionError,
                     match=r'blocks\.1\..*config\.steve\.decoder\.num_layers'):
    families.convert_state_dict(steve_state, config)


def test_shape_mismatch_names_key_shapes_and_field(states):
  _, dvae_state, steve_state, _ = states
  config = steve_config()
  config.dvae.vocab_size = 30
  with pytest.raises(families.ConversionError) as error:
    families.convert_state_dict(dvae_state, config)
  message = str(error.value)
  assert ('encoder.7.weight: checkpoint shape (24, 8, 1, 1) gives '
          'encoder/layers_7/kernel (1, 1, 8, 24), the config builds '
          '(1, 1, 8, 30); change config.dvae') in message
  config = steve_config()
  config.steve.num_slots = 4
  with pytest.raises(families.ConversionError,
                     match=r'init_latents: checkpoint shape \(1, 3, 16\) '
                     r'gives initial_slots \(3, 16\), the config builds '
                     r'\(4, 16\); change config.steve.num_slots'):
    families.convert_state_dict(steve_state, config)


@pytest.mark.parametrize('field, value', [
    ('steve.layer_norm_epsilon', 1e-6),
    ('slot_model', 'savi'),
])
def test_steve_config_must_be_the_official_one(states, field, value):
  _, _, steve_state, _ = states
  config = steve_config()
  section, _, name = field.rpartition('.')
  (config[section] if section else config)[name] = value
  with pytest.raises(families.ConversionError, match=field):
    families.convert_state_dict(steve_state, config)


def test_strided_encoder_needs_pytorch_padding():
  config = steve_config(128)
  config.steve.encoder.padding = 'same'
  state = {'init_latents': np.zeros((1, 3, 16)), 'dvae.encoder.0.m.weight':
           np.zeros(1)}
  with pytest.raises(families.ConversionError,
                     match='steve.encoder.padding=.pytorch'):
    families.convert_state_dict(state, config)


def test_families_are_recognised(states):
  _, dvae_state, steve_state, slotformer_state = states
  assert families.detect_family(dvae_state).name == 'dvae'
  assert families.detect_family(steve_state).name == 'steve'
  assert families.detect_family(slotformer_state).name == 'steve_slotformer'


def test_physion_is_rgb():
  """The official Physion frames were read with PIL as RGB: converting with
  channel_order='bgr' is refused."""
  config = steve_config()
  convert_official.check_channel_order(config)
  config.data.channel_order = 'bgr'
  with pytest.raises(families.ConversionError, match='RGB'):
    convert_official.check_channel_order(config)


# --------------------------------------------------------------------------
# The workdir the STEVE pipeline reads
# --------------------------------------------------------------------------


def _convert_files(config, workdir, tmp_path, monkeypatch, named_states):
  files = {str(tmp_path / name): state for name, state in named_states.items()}
  for path in files:
    open(path, 'wb').close()
  monkeypatch.setattr(convert_official.pth_reader, 'read_state_dict',
                      lambda path, reader: files[path])
  return convert_official.convert_files(config, workdir, list(files))


def test_writes_where_the_steve_pipeline_reads(states, converted, tmp_path,
                                              monkeypatch):
  """Given in any order, the files are written dVAE, STEVE, SlotFormer with
  the run identities training stamps; the STEVE loaders and the identity
  checks of extraction accept them."""
  config, dvae_state, steve_state, slotformer_state = states
  workdir = str(tmp_path / 'run')
  directories = _convert_files(
      config, workdir, tmp_path, monkeypatch,
      {'slotformer.pth': slotformer_state, 'steve.pth': steve_state,
       'dvae.pth': dvae_state})
  assert directories == [Paths.of(workdir).model('dvae'),
                         Paths.of(workdir).model('steve'),
                         Paths.of(workdir).dynamics('slotformer')]
  mesh = jax.sharding.Mesh(np.array(jax.devices()), ('data',))
  run = Run.create(config, workdir, mesh)
  slot_model = run.slot_model

  def dynamics():
    loaded = run.dynamics('slotformer')
    return loaded.params, loaded.step
  loads = (lambda: chain_lib.load_part(slot_model.part('dvae'), run.paths,
                                       mesh),
           lambda: chain_lib.load_part(slot_model.part('steve'), run.paths,
                                       mesh), dynamics)
  for load, expected in zip(loads, converted):
    params, step = load()
    assert step == 10
    assert common.max_difference(jax.device_get(params),
                                 expected.params) == 0
  # STEVE descends from the dVAE, SlotFormer from STEVE.
  chain_lib.chain(slot_model, run.paths, {'dvae': 10, 'steve': 10})
  steve_identity = identity_lib.read_identity(run.paths.model('steve'))
  slotformer_identity = identity_lib.read_identity(
      Paths.of(workdir).dynamics('slotformer'))
  assert slotformer_identity['parent'] == identity_lib.parent_of(
      steve_identity, 10, 'steve')


def test_frozen_copies_must_match_the_workdir(states, tmp_path, monkeypatch):
  config, dvae_state, steve_state, _ = states
  workdir = str(tmp_path / 'run')
  with pytest.raises(families.ConversionError,
                     match='no dVAE checkpoint yet: convert '
                     'dvae_physion_params/model_20.pth first'):
    _convert_files(config, workdir, tmp_path, monkeypatch,
                   {'steve.pth': steve_state})
  other_dvae = official_dvae(config, seed=7)
  # In one command: refused before anything is written.
  with pytest.raises(families.ConversionError,
                     match='steve.pth: its frozen copy of the dvae differs '
                     'from .*dvae.pth'):
    _convert_files(config, workdir, tmp_path, monkeypatch,
                   {'dvae.pth': other_dvae, 'steve.pth': steve_state})
  assert not (tmp_path / 'run' / 'dvae').exists()
  # Against the workdir's dVAE, converted by an earlier command.
  _convert_files(config, workdir, tmp_path, monkeypatch,
                 {'dvae.pth': other_dvae})
  with pytest.raises(families.ConversionError,
                     match='frozen copy of the dVAE differs'):
    _convert_files(config, workdir, tmp_path, monkeypatch,
                   {'steve.pth': steve_state})


@pytest.mark.slow
def test_converted_steve_workdir_runs_extract_evaluate_render(tmp_path,
                                                              monkeypatch,
                                                              caplog):
  """Official-format dVAE, STEVE and STEVESlotFormer weights -> the workdir
  -> slot extraction, evaluation (generated frames) and pictures, with no
  training stage run (the embedded data, 16x16, the official architecture
  with the micro widths of the STEVE pipeline test)."""
  import pipeline_helpers  # pylint: disable=g-import-not-at-top
  from slotformer_jax.runtime import sharding  # pylint: disable=g-import-not-at-top
  config = pipeline_helpers.micro_config('steve', tmp_path / 'data')
  steve = config.steve
  steve.encoder.strides = (1,) * len(steve.encoder.features)
  steve.encoder.padding = 'pytorch'
  steve.layer_norm_epsilon = 1e-5
  config.slotformer.residual = False
  config.slotformer.positional_encoding = 'temporal'
  config.slotformer.layer_norm_epsilon = 1e-5
  config.slot_lstm.train = False
  dvae_state = official_dvae(config)
  steve_state = official_steve(config, dvae_state)
  workdir = str(tmp_path / 'run')
  _convert_files(config, workdir, tmp_path, monkeypatch, {
      'dvae.pth': dvae_state, 'steve.pth': steve_state,
      'slotformer.pth': official_steve_slotformer(config, dvae_state,
                                                  steve_state)})
  mesh = sharding.make_mesh()
  run_stage(config, workdir, mesh, 'extract_slots')
  results = run_stage(config, workdir, mesh, 'evaluate')
  assert results['checkpoints']['steve_step'] == steve.num_train_steps
  for method in ('slotformer', 'copy_last', 'steve_reconstruction'):
    assert np.isfinite(results['rollout'][method]['psnr']['mean'])
  pictures = run_stage(config, workdir, mesh, 'render')
  assert any(p.endswith('rollout_000.gif') for p in pictures)
  # No attention figure (no per-slot reconstructions), so no frame was
  # generated for one; the generation was announced before each stage.
  assert not any('attention_' in p for p in pictures)
  for stage in ('evaluate', 'render'):
    assert (f'{stage}: STEVE generates each decoded frame token by token'
            in caplog.text)
