"""The parts that make the dataset configs the official models.

SAVi's predictor / posterior-head variants, the growing-context SlotFormer
rollout, PyTorch padding, LayerNorm epsilon, PyTorch-default initialisation,
the official learning-rate schedule and the official configs' sizes.
"""

import importlib.util
import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.modules import initializers
from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.savi import FrameStep
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.modules.stochastic_savi import GaussianSlotSampler
from slotformer_jax.modules.transitions import ResidualMLPTransition
from slotformer_jax.modules.transitions import build_predictor
from slotformer_jax.train import optim
from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax.slot_models.savi import build_savi
from tiny_models import savi_section

CONFIGS = os.path.join(os.path.dirname(__file__), '..', '..', 'configs')


def _load_config(name):
  spec = importlib.util.spec_from_file_location(
      name, os.path.join(CONFIGS, f'{name}.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config()


def _layer_norm(x, scale, bias, eps):
  mean = x.mean(-1, keepdims=True)
  var = ((x - mean)**2).mean(-1, keepdims=True)
  return (x - mean) / np.sqrt(var + eps) * scale + bias


@pytest.mark.parametrize('pre_norm', [True, False])
def test_residual_mlp_predictor_matches_numpy(pre_norm):
  # Small-variance inputs make the LayerNorm epsilon (1e-5) visible.
  slots = 0.01 * jax.random.normal(jax.random.key(0), (2, 3, 8))
  module = ResidualMLPTransition(mlp_size=16, pre_norm=pre_norm,
                                 layer_norm_epsilon=1e-5)
  params = module.init(jax.random.key(1), slots)['params']
  params = jax.tree.map(
      lambda p: p + 0.1 * jax.random.normal(jax.random.key(2), p.shape),
      params)
  out, state = module.apply({'params': params}, slots)
  assert state == ()
  x = np.asarray(slots, np.float64)
  p = jax.tree.map(lambda a: np.asarray(a, np.float64), params)
  normed = _layer_norm(x, p['norm']['scale'], p['norm']['bias'], 1e-5)
  hidden = np.maximum(normed @ p['hidden']['kernel'] + p['hidden']['bias'], 0)
  expected = hidden @ p['out']['kernel'] + p['out']['bias']
  expected += normed if pre_norm else x
  np.testing.assert_allclose(out, expected, atol=1e-5)


@pytest.mark.parametrize('kind', ['linear', 'mlp'])
def test_deterministic_posterior_head_returns_the_mean(kind):
  slots = jax.random.normal(jax.random.key(0), (2, 3, 8))
  head = GaussianSlotSampler(kind=kind, stochastic=False)
  params = head.init(jax.random.key(1), slots)['params']
  mean, kl = head.apply({'params': params}, slots)
  np.testing.assert_array_equal(kl, 0.0)
  x = slots
  if kind == 'mlp':
    x = nn.Dense(16).apply({'params': params['hidden']}, x)
    x = nn.relu(nn.LayerNorm(epsilon=1e-6).apply(
        {'params': params['norm']}, x))
  else:
    assert set(params) == {'statistics'}
  statistics = nn.Dense(16).apply({'params': params['statistics']}, x)
  np.testing.assert_allclose(mean, statistics[..., :8], atol=1e-6)


def test_stochastic_savi_needs_a_posterior_head():
  with pytest.raises(ValueError, match='posterior head'):
    build_savi(savi_section(stochastic=True, posterior_head='none'),
                      (16, 16))


def test_lstm_size_must_match_the_predictor_kind():
  sizes = dict(num_layers=1, num_heads=2, mlp_size=16, pre_norm=True,
               dropout_rate=0.0, layer_norm_epsilon=1e-5)
  with pytest.raises(ValueError, match='lstm_size'):
    build_predictor('transformer', lstm_size=8, **sizes)
  with pytest.raises(ValueError, match='lstm_size'):
    build_predictor('transformer_lstm', lstm_size=0, **sizes)
  with pytest.raises(ValueError, match='predictor kind'):
    build_predictor('gru', lstm_size=0, **sizes)


def _tiny_step(kind, lstm_size=None, head='mlp', dropout_rate=0.0):
  if lstm_size is None:
    lstm_size = 8 if kind == 'transformer_lstm' else 0
  return FrameStep(
      corrector=SlotAttention(2, 16, layer_norm_epsilon=1e-5),
      predictor=build_predictor(
          kind, num_layers=1, num_heads=2, mlp_size=16, lstm_size=lstm_size,
          pre_norm=True, dropout_rate=dropout_rate, layer_norm_epsilon=1e-5),
      posterior_head=None if head == 'none' else GaussianSlotSampler(
          kind=head, stochastic=False, layer_norm_epsilon=1e-5))


def _tiny_carry(kind, batch=2, num_slots=4):
  slots = jax.random.normal(jax.random.key(3), (batch, num_slots, 8))
  if kind != 'transformer_lstm':
    return slots, ()
  c, h = jax.random.normal(jax.random.key(4), (2, batch, num_slots, 8))
  return slots, (c, h)


@pytest.mark.parametrize('kind,head', [('transformer', 'none'),
                                       ('transformer_lstm', 'mlp'),
                                       ('residual_mlp', 'linear')])
def test_savi_step_is_permutation_equivariant_over_slots(kind, head):
  step = _tiny_step(kind, head=head)
  carry = _tiny_carry(kind)
  features = jax.random.normal(jax.random.key(5), (2, 6, 8))
  params = step.init(jax.random.key(6), carry, features)
  (next_slots, lstm), frame = step.apply(params, carry, features)
  slots = frame.slots
  assert next_slots.shape == slots.shape == (2, 4, 8)
  order = np.array([2, 0, 3, 1])
  permuted = jax.tree.map(lambda x: x[:, order], carry)
  (next_p, lstm_p), frame_p = step.apply(params, permuted, features)
  slots_p = frame_p.slots
  np.testing.assert_allclose(slots_p, slots[:, order], atol=1e-5)
  np.testing.assert_allclose(next_p, next_slots[:, order], atol=1e-5)
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b[:, order],
                                                       atol=1e-5),
               lstm_p, lstm)


def test_predictor_dropout_needs_the_rng_only_when_training():
  step = _tiny_step('transformer', head='none', dropout_rate=0.5)
  carry = _tiny_carry('transformer')
  features = jax.random.normal(jax.random.key(5), (2, 6, 8))
  params = step.init(jax.random.key(6), carry, features)
  eval_a = step.apply(params, carry, features)
  eval_b = step.apply(params, carry, features)
  np.testing.assert_array_equal(eval_a[0][0], eval_b[0][0])
  train = step.apply(params, carry, features, deterministic=False,
                     rngs={'dropout': jax.random.key(7)})
  assert not np.allclose(train[0][0], eval_a[0][0])


def _growing_slotformer():
  return SlotFormer(burn_in=1, max_context=4, embed_dim=16, num_layers=1,
                    num_heads=2, mlp_size=32, layer_norm_epsilon=1e-5)


def test_growing_context_scan_equals_python_loop():
  """Grow 1 -> 4 frames, then slide: one scan == the official loop."""
  model = _growing_slotformer()
  first = jax.random.normal(jax.random.key(0), (2, 1, 3, 8))
  params = jax.jit(model.init, static_argnums=2)(jax.random.key(1), first, 7)
  rollout = jax.jit(lambda p, x: model.apply(p, x, 7))(params, first)
  predict_next = jax.jit(lambda p, h: model.apply(
      p, h, method=SlotFormer.predict_next))
  history, expected = first, []
  for _ in range(7):
    # The official loop: the last (at most) 4 frames, unpadded.
    nxt = predict_next(params, history[:, -4:])
    expected.append(nxt)
    history = jnp.concatenate([history, nxt[:, None]], axis=1)
  np.testing.assert_allclose(rollout, jnp.stack(expected, 1), atol=1e-4)
  # A fixed 1-frame context is a different model.
  fixed = jax.jit(lambda p, x: model.clone(max_context=0).apply(p, x, 7))(
      params, first)
  assert not np.allclose(fixed[:, 1:], rollout[:, 1:], atol=1e-3)


def test_growing_context_compiles_once_and_trains_with_dropout():
  model = _growing_slotformer().clone(dropout_rate=0.1)
  first = jax.random.normal(jax.random.key(0), (2, 1, 3, 8))
  params = jax.jit(model.init, static_argnums=2)(jax.random.key(1), first, 5)
  traces = []

  @jax.jit
  def run(p, x, rng):
    traces.append(1)
    return model.apply(p, x, 5, deterministic=False, rngs={'dropout': rng})

  a = run(params, first, jax.random.key(2))
  b = run(params, first + 1.0, jax.random.key(3))
  assert len(traces) == 1 and a.shape == b.shape == (2, 5, 3, 8)
  with pytest.raises(ValueError, match='max_context'):
    SlotFormer(burn_in=3, max_context=2).init(
        jax.random.key(0), jnp.zeros((1, 3, 2, 8)), 1)


def test_pytorch_padding_equals_explicit_lax_conv():
  images = jax.random.normal(jax.random.key(0), (1, 16, 16, 3))
  encoder = CNNEncoder(features=(4,), kernel_size=5, strides=(2,),
                       output_size=4, padding='pytorch')
  params = encoder.init(jax.random.key(1), images)['params']
  conv = params['conv_0']
  explicit = jax.lax.conv_general_dilated(
      images, conv['kernel'], (2, 2), ((2, 2), (2, 2)),
      dimension_numbers=('NHWC', 'HWIO', 'NHWC')) + conv['bias']
  mine = nn.Conv(4, (5, 5), strides=(2, 2), padding=((2, 2), (2, 2))).apply(
      {'params': conv}, images)
  np.testing.assert_allclose(mine, explicit, atol=1e-5)
  # The encoder itself uses it: 'same' pads (1, 2) and samples other pixels.
  same = encoder.clone(padding='same')
  out_pt = encoder.apply({'params': params}, images)
  out_same = same.apply({'params': params}, images)
  assert out_pt.shape == out_same.shape == (1, 64, 4)
  assert not np.allclose(out_pt, out_same, atol=1e-3)
  with pytest.raises(ValueError, match='padding'):
    encoder.clone(padding='valid').apply({'params': params}, images)


def test_pytorch_default_init_statistics():
  model = build_savi(savi_section(
      num_slots=3, slot_size=32,
      encoder=dict(features=(16, 16), kernel_size=3, strides=(1, 1),
                   output_size=32),
      slot_attention=dict(mlp_size=64),
      predictor=dict(kind='transformer_lstm', num_layers=1, num_heads=4,
                     mlp_size=64, lstm_size=64),
      posterior_head='mlp',
      decoder=dict(broadcast_resolution=(8, 8), features=(16, 16),
                   kernel_size=3)), (16, 16))
  # Only shapes are read, so the (slow) eager init is not needed.
  flax_params = jax.eval_shape(lambda: model.init(
      {'params': jax.random.key(0), 'sample': jax.random.key(1)},
      jnp.zeros((1, 1, 16, 16, 3))))['params']
  params = initializers.initialize(flax_params, jax.random.key(2), 'pytorch')
  assert (jax.tree.structure(params) == jax.tree.structure(flax_params))

  def check_uniform(x, bound):
    x = np.asarray(x).ravel()
    assert np.abs(x).max() <= bound + 1e-7
    # U(-b, b): std b / sqrt(3).
    np.testing.assert_allclose(x.std(), bound / np.sqrt(3), rtol=0.15)

  step = params['frame_step']
  check_uniform(step['corrector']['Dense_0']['kernel'], 1 / np.sqrt(32))
  check_uniform(step['corrector']['Dense_0']['bias'], 1 / np.sqrt(32))
  check_uniform(params['encoder']['conv_1']['kernel'], 1 / np.sqrt(9 * 16))
  # ConvTranspose2d: fan_in from the output channels (16 * 3 * 3).
  check_uniform(params['decoder']['deconv_0']['kernel'], 1 / np.sqrt(9 * 16))
  check_uniform(step['corrector']['gru']['hr']['kernel'], 1 / np.sqrt(32))
  check_uniform(step['predictor']['lstm']['ii']['kernel'], 1 / np.sqrt(64))
  # b_ih + b_hh: the sum of two U(-b, b), std b * sqrt(2/3).
  summed = np.asarray(step['predictor']['lstm']['hi']['bias'])
  assert np.abs(summed).max() <= 2 / np.sqrt(64)
  np.testing.assert_allclose(summed.std(), np.sqrt(2 / 3) / 8, rtol=0.3)
  attention = step['predictor']['transformer']['block_0']['attention']
  check_uniform(attention['query']['kernel'], np.sqrt(6 / (4 * 32)))
  check_uniform(attention['out']['kernel'], 1 / np.sqrt(32))
  for name in ('query', 'key', 'value', 'out'):
    np.testing.assert_array_equal(attention[name]['bias'], 0.0)
  np.testing.assert_array_equal(step['posterior_head']['norm']['scale'], 1.0)
  assert params['initial_slots'] is flax_params['initial_slots']  # kept
  assert initializers.initialize(flax_params, None, 'flax') is flax_params


def test_official_schedule_starts_and_ends_at_a_hundredth():
  schedule = optim.learning_rate_schedule(1e-4, 1000, 0.025,
                                          min_lr_fraction=0.01)
  np.testing.assert_allclose(schedule(0), 1e-6, rtol=1e-5)
  np.testing.assert_allclose(schedule(25), 1e-4, rtol=1e-5)
  np.testing.assert_allclose(schedule(1000), 1e-6, rtol=1e-4)
  midway = 25 + (1000 - 25) // 2
  np.testing.assert_allclose(schedule(midway), (1e-4 + 1e-6) / 2, rtol=1e-2)
  # The default stays 0 -> peak -> 0.
  np.testing.assert_allclose(optim.learning_rate_schedule(1e-4, 1000, 0.025)(0),
                             0.0)


def _num_params(module, *args):
  shapes = jax.eval_shape(lambda: module.init(
      {'params': jax.random.key(0), 'sample': jax.random.key(1)}, *args))
  return sum(x.size for x in jax.tree.leaves(shapes))


@pytest.mark.parametrize('name,savi_params,slotformer_params', [
    # The official SAVi state dicts hold 33,280 more: the `prior_slot_layer`
    # the official forward pass never uses; and PyTorch keeps two biases per
    # GRU / LSTM gate where flax keeps one (their sum): 256 more for the GRU,
    # 1,024 for the LSTM (measured on the official modules).
    ('obj3d', 1_989_124, 826_112),
    ('clevrer', 1_165_444, 3_224_960),
    ('phyre', 1_989_380, 6_384_000),
])
def test_official_configs_build_the_official_sizes(name, savi_params,
                                                   slotformer_params):
  config = _load_config(name)
  assert config.savi.layer_norm_epsilon == 1e-5
  assert config.savi.learning_rate == 1e-4
  assert config.savi.min_lr_fraction == 0.01
  savi = build_savi(config.savi, tuple(config.data.resolution))
  video = jnp.zeros((1, 2, *config.data.resolution, 3))
  assert _num_params(savi, video) == savi_params
  slotformer = dynamics_lib.build(config.slotformer, 'slotformer')
  history = jnp.zeros((1, config.slotformer.burn_in, config.savi.num_slots,
                       config.savi.slot_size))
  assert _num_params(slotformer, history, 2) == slotformer_params
