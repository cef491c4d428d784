"""SAVi++'s parts: the ResNet-34 backbone (group norm, small-input stem),
the encoder with a Transformer over the feature map, and a SAVi++ built
from `config.savi` (savi.encoder.kind='resnet34', targets flow + depth)."""

import functools
import importlib.util
import os

import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax import losses
from slotformer_jax.modules import resnet
from slotformer_jax.modules.encoders import ConvStack
from slotformer_jax.modules.encoders import FrameEncoder
from slotformer_jax.modules.transformer import TransformerEncoder
from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.train import steps
from tiny_models import savi_section

# SAVi's own ResNet34(norm_type='group', small_inputs=True) has 21,276,992
# parameters (its module built with jax.eval_shape; docs/savi_plus_plus.md).
SAVI_RESNET34_PARAMETERS = 21_276_992


def _count(tree) -> int:
  return sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree))


def _resnet_parameters(stage_sizes, width=64, channels_in=3) -> int:
  """By hand: 3x3 convolutions without bias, two GroupNorm parameters per
  channel, a 1x1 projection (+ GN) in the first block of stages 2..."""
  count = 9 * channels_in * width + 2 * width  # stem
  channels = width
  for stage, blocks in enumerate(stage_sizes):
    out = width * 2**stage
    for block in range(blocks):
      count += 9 * channels * out + 9 * out * out + 2 * (2 * out)
      if stage > 0 and block == 0:
        count += channels * out + 2 * out
      channels = out
  return count


def test_resnet34_shapes_and_parameter_count():
  model = resnet.ResNet()
  images = jnp.zeros((2, 128, 128, 3))
  variables = jax.eval_shape(model.init, jax.random.key(0), images)
  assert _count(variables) == _resnet_parameters(resnet.RESNET34_STAGES)
  assert _count(variables) == SAVI_RESNET34_PARAMETERS
  out = jax.eval_shape(model.apply, variables, images)
  assert out.shape == (2, 16, 16, 512)  # SAVi++'s 16x16 map
  assert resnet.output_grid((128, 128)) == (16, 16)
  params = variables['params']
  assert set(params) == {'stem_conv', 'stem_norm'} | {
      f'stage_{s + 1}_block_{b + 1}'
      for s, n in enumerate(resnet.RESNET34_STAGES) for b in range(n)}
  # Only the first block of stages 2.. changes the shape: projected.
  assert 'projection' in params['stage_2_block_1']
  assert 'projection' not in params['stage_1_block_1']
  assert 'projection' not in params['stage_2_block_2']


def test_resnet_block_starts_as_the_identity_then_relu():
  """The second GroupNorm's scale starts at 0: a block without projection
  is relu(x) at initialisation."""
  block = resnet.BasicBlock(features=32)
  x = jax.random.normal(jax.random.key(0), (2, 6, 6, 32))
  params = block.init(jax.random.key(1), x)
  np.testing.assert_allclose(block.apply(params, x), jax.nn.relu(x),
                             atol=1e-6)
  # Strided: half the size, the projection's channels.
  strided = resnet.BasicBlock(features=64, stride=2)
  out, _ = jax.eval_shape(lambda: strided.init_with_output(
      jax.random.key(0), x))
  assert out.shape == (2, 3, 3, 64)


def test_frame_encoder_with_a_transformer():
  encoder = FrameEncoder(
      backbone=ConvStack(features=(8, 8), kernel_size=3, strides=(2, 1)),
      output_size=12, mlp_size=6,
      transformer=TransformerEncoder(num_layers=2, num_heads=2, mlp_size=20),
      qkv_size=10)
  images = jax.random.normal(jax.random.key(0), (3, 16, 16, 3))
  params = encoder.init(jax.random.key(1), images)['params']
  assert set(params) == {'backbone', 'position_embedding', 'norm',
                         'mlp_hidden', 'mlp_out', 'transformer_in',
                         'transformer'}
  assert params['mlp_hidden']['kernel'].shape == (8, 6)
  assert params['mlp_out']['kernel'].shape == (6, 12)
  assert params['transformer_in']['kernel'].shape == (12, 10)
  assert set(params['transformer']) == {'block_0', 'block_1'}
  features = encoder.apply({'params': params}, images)
  assert features.shape == (3, 8 * 8, 10)
  grads = jax.jit(jax.grad(lambda p: jnp.sum(
      encoder.apply({'params': p}, images)**2)))(params)
  for name, grad in grads.items():  # every layer learns
    assert sum(np.abs(g).sum()
               for g in jax.tree_util.tree_leaves(grad)) > 0, name
  # The Transformer mixes positions: changing one pixel's neighbourhood
  # changes features far away; without it, only nearby positions change.
  changed = images.at[:, :2, :2].set(5.0)
  moved = encoder.apply({'params': params}, changed) - features
  assert np.abs(moved[:, -1]).max() > 1e-4
  plain = FrameEncoder(backbone=ConvStack(features=(8, 8), kernel_size=3,
                                          strides=(2, 1)), output_size=12)
  plain_params = plain.init(jax.random.key(1), images)
  assert set(plain_params['params']) == {'backbone', 'position_embedding',
                                         'norm', 'mlp_hidden', 'mlp_out'}
  still = (plain.apply(plain_params, changed)
           - plain.apply(plain_params, images))
  assert np.abs(still[:, -1]).max() == 0
  assert plain.apply(plain_params, images).shape == (3, 64, 12)


def _savi_plus_plus_section():
  """SAVi++'s settings (savi++_conditional.py) at a tiny slot size and
  decoder, for 32x32 frames."""
  return savi_section(
      num_slots=4, slot_size=16, initial_slots='boxes',
      targets=('flow', 'depth'),
      encoder=dict(kind='resnet34', output_size=32, mlp_size=8,
                   transformer=dict(num_layers=4, num_heads=4, qkv_size=16,
                                    mlp_size=32)),
      slot_attention=dict(num_iterations=1, mlp_size=16),
      predictor=dict(num_layers=1, num_heads=4, mlp_size=32, pre_norm=False),
      decoder=dict(broadcast_resolution=(4, 4), features=(8, 8, 8),
                   kernel_size=5))


def test_savi_plus_plus_forward_and_loss_on_a_two_frame_clip():
  resolution = (32, 32)
  model = savi_slots.build_savi(_savi_plus_plus_section(), resolution)
  rng = np.random.default_rng(0)
  video = rng.integers(0, 256, (2, 2, *resolution, 3), np.uint8)
  boxes = np.tile(np.array([[0.1, 0.1, 0.5, 0.5], [0.4, 0.3, 0.9, 0.8],
                            [0.0, 0.5, 0.3, 1.0]], np.float32), (2, 2, 1, 1))
  params = jax.jit(functools.partial(steps.init_params, model))(
      jax.random.key(0), jnp.zeros((1, 2, *resolution, 3)),
      boxes=jnp.asarray(boxes[:1, 0]))
  encoder = params['encoder']
  assert set(encoder) == {'backbone', 'position_embedding', 'norm',
                          'mlp_hidden', 'mlp_out', 'transformer_in',
                          'transformer'}
  assert _count(encoder['backbone']) == SAVI_RESNET34_PARAMETERS
  assert set(encoder['transformer']) == {f'block_{i}' for i in range(4)}
  output = jax.eval_shape(functools.partial(model.apply, {'params': params}),
                          jnp.asarray(video) / 127.5 - 1.0,
                          boxes=jnp.asarray(boxes[:, 0]))
  assert output.slots.shape == (2, 2, 4, 16)
  assert output.decoded.recon is None
  assert output.decoded.targets['flow'].shape == (2, 2, *resolution, 3)
  assert output.decoded.targets['depth'].shape == (2, 2, *resolution, 1)
  batch = {'video': video, 'boxes': boxes,
           'flow': rng.uniform(-1, 1, (2, 2, *resolution, 3)).astype(
               np.float32),
           'depth': rng.uniform(0, 3, (2, 2, *resolution, 1)).astype(
               np.float32)}
  loss_fn = functools.partial(losses.savi_loss, model=model, kl_weight=0.0)
  loss, metrics = jax.jit(loss_fn)(params, batch, None, jax.random.key(1))
  assert np.isfinite(loss)
  assert set(metrics) == {'recon_loss', 'recon_loss_flow',
                          'recon_loss_depth', 'kl'}


def _param_counts():
  script = os.path.join(os.path.dirname(__file__), '..', '..', 'benchmarks',
                        'param_counts.py')
  spec = importlib.util.spec_from_file_location('param_counts', script)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def test_parameter_counts_of_the_docs_table():
  """benchmarks/param_counts.py: SAVi's counts by hand equal the measured
  ones, and this project's are those of docs/savi_plus_plus.md."""
  counts = _param_counts()
  for model in ('SAVi-S', 'SAVi++'):
    assert counts.savi_parts_by_hand(model) == counts.SAVI_MEASURED[model]
  assert counts.our_parts('SAVi-S') == {
      'encoder': 83_744, 'initializer': 34_176, 'corrector': 123_712,
      'predictor': 132_480, 'decoder': 513_156}
  assert counts.our_parts('SAVi++') == {
      'encoder': 21_975_744, 'initializer': 34_176, 'corrector': 213_888,
      'predictor': 395_776, 'decoder': 513_221}
  # The corrector is SAVi's to the parameter (no MLP, as SAVi's configs).
  for model in ('SAVi-S', 'SAVi++'):
    assert (counts.our_parts(model)['corrector']
            == counts.SAVI_MEASURED[model]['corrector'][0])


def test_slot_attention_without_an_mlp():
  """mlp_size=None (SAVi's MOVi configs): no residual MLP; the update is
  the GRU's, the rest of the tree and its values those of the module with
  an MLP."""
  from slotformer_jax.modules.slot_attention import SlotAttention  # pylint: disable=g-import-not-at-top
  slots = jax.random.normal(jax.random.key(2), (2, 3, 16))
  inputs = jax.random.normal(jax.random.key(0), (2, 5, 8))
  key = jax.random.key(1)
  with_mlp = SlotAttention(1, 32).init(key, slots, inputs)['params']
  without = SlotAttention(1, None).init(key, slots, inputs)['params']
  # The MLP's layers (LN, hidden, out) are named in the module's scope.
  mlp = {'LayerNorm_0', 'Dense_0', 'Dense_1'}
  assert set(with_mlp) - set(without) == mlp
  assert set(without) == set(with_mlp) - mlp
  np.testing.assert_array_equal(without['gru']['ir']['kernel'],
                                with_mlp['gru']['ir']['kernel'])
  # With the MLP's last layer zeroed, both compute the same slots.
  zeroed = dict(with_mlp)
  zeroed['Dense_1'] = jax.tree_util.tree_map(jnp.zeros_like,
                                             zeroed['Dense_1'])
  np.testing.assert_allclose(
      SlotAttention(1, None).apply({'params': without}, slots, inputs),
      SlotAttention(1, 32).apply({'params': zeroed}, slots, inputs),
      atol=1e-6)


def test_qkv_size_widens_attention_and_none_keeps_the_tree():
  """SAVi++'s 256-wide corrector and predictor on 128-d slots: the
  projections (and the GRU's input) take qkv_size; None is the slot size,
  the parameter tree and values of before."""
  from slotformer_jax.modules.slot_attention import SlotAttention  # pylint: disable=g-import-not-at-top
  from slotformer_jax.modules.transitions import SlotTransition  # pylint: disable=g-import-not-at-top
  slots = jnp.ones((2, 3, 128))
  inputs = jax.random.normal(jax.random.key(0), (2, 5, 32))
  key = jax.random.key(1)
  wide = SlotAttention(1, 256, qkv_size=256)
  params = wide.init(key, slots, inputs)['params']
  assert params['key']['kernel'].shape == (32, 256)
  assert params['query']['kernel'].shape == (128, 256)
  assert params['gru']['ir']['kernel'].shape == (256, 128)
  assert wide.apply({'params': params}, slots, inputs).shape == slots.shape
  default, same = SlotAttention(1, 256), SlotAttention(1, 256, qkv_size=128)
  p_default = default.init(key, slots, inputs)
  p_same = same.init(key, slots, inputs)
  assert jax.tree_util.tree_all(jax.tree_util.tree_map(
      lambda a, b: a.shape == b.shape and bool(jnp.all(a == b)),
      p_default, p_same))
  np.testing.assert_array_equal(default.apply(p_default, slots, inputs),
                                same.apply(p_same, slots, inputs))
  predictor = SlotTransition(num_layers=1, num_heads=4, mlp_size=64,
                             qkv_size=256)
  params = predictor.init(key, slots)['params']
  attention = params['transformer']['block_0']['attention']
  assert attention['query']['kernel'].shape == (128, 4, 64)
  assert attention['out']['kernel'].shape == (4, 64, 128)
  assert predictor.apply({'params': params}, slots)[0].shape == slots.shape
