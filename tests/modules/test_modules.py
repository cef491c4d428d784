"""Properties of the linen modules (tiny shapes, CPU)."""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.modules.decoders import PointwiseConv
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.decoders import SubPixelConvTranspose
from slotformer_jax.modules.decoders import sub_pixel_conv_transpose
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.modules.stochastic_savi import GaussianSlotSampler
from slotformer_jax.modules.stochastic_savi import kl_to_fixed_sigma
from tiny_models import tiny_savi


def _transposed_conv_reference(x, kernel, bias, stride):
  """Direct definition out[s*i + k - p] += x[i] * w[k], p = K // 2 (numpy)."""
  batch, height, width, _ = x.shape
  size = kernel.shape[0]
  pad = size // 2
  out = np.zeros((batch, stride * height, stride * width, kernel.shape[-1]))
  for i in range(height):
    for j in range(width):
      for ky in range(size):
        for kx in range(size):
          oy, ox = stride * i + ky - pad, stride * j + kx - pad
          if 0 <= oy < stride * height and 0 <= ox < stride * width:
            out[:, oy, ox] += x[:, i, j] @ kernel[ky, kx]
  return out + bias


@pytest.mark.parametrize('kernel_size,stride', [(5, 2), (3, 2), (5, 3)])
def test_sub_pixel_equals_transposed_convolution(kernel_size, stride):
  rng = np.random.default_rng(kernel_size * 10 + stride)
  x = rng.normal(size=(2, 5, 4, 3)).astype(np.float32)
  kernel = rng.normal(size=(kernel_size, kernel_size, 3, 6)).astype(np.float32)
  bias = rng.normal(size=6).astype(np.float32)
  expected = _transposed_conv_reference(x, kernel, bias, stride)
  got = sub_pixel_conv_transpose(jnp.asarray(x), jnp.asarray(kernel),
                                 jnp.asarray(bias), stride)
  np.testing.assert_allclose(np.asarray(got), expected, atol=1e-4, rtol=1e-4)


def test_sub_pixel_equals_xla_transposed_convolution():
  """Against XLA's own definition: dilate the input, correlate with the
  spatially flipped kernel (PyTorch ConvTranspose2d, padding 2, output
  padding 1)."""
  rng = np.random.default_rng(0)
  x = jnp.asarray(rng.normal(size=(1, 4, 4, 2)), jnp.float32)
  layer = SubPixelConvTranspose(features=3, kernel_size=5, stride=2)
  params = layer.init(jax.random.key(0), x)
  kernel = params['params']['kernel']
  bias = params['params']['bias']
  expected = jax.lax.conv_general_dilated(
      x, kernel[::-1, ::-1], window_strides=(1, 1),
      padding=((2, 3), (2, 3)), lhs_dilation=(2, 2),
      dimension_numbers=('NHWC', 'HWIO', 'NHWC')) + bias
  np.testing.assert_allclose(layer.apply(params, x), expected, atol=1e-5)


def test_decoder_shapes_and_alpha_normalisation():
  decoder = SpatialBroadcastDecoder(output_resolution=(16, 16),
                                    broadcast_resolution=(4, 4),
                                    features=(8, 8, 8), kernel_size=3)
  slots = jax.random.normal(jax.random.key(0), (2, 3, 4, 10))  # [B, T, N, D]
  params = decoder.init(jax.random.key(1), slots)
  decoded = decoder.apply(params, slots)
  assert decoded.recon.shape == (2, 3, 16, 16, 3)
  assert decoded.rgb.shape == (2, 3, 4, 16, 16, 3)
  assert decoded.alpha_masks.shape == (2, 3, 4, 16, 16, 1)
  np.testing.assert_allclose(decoded.alpha_masks.sum(axis=-4), 1.0, atol=1e-5)
  np.testing.assert_allclose(
      decoded.recon, (decoded.rgb * decoded.alpha_masks).sum(axis=-4),
      atol=1e-5)


def test_decoder_rejects_resolution_it_cannot_reach():
  decoder = SpatialBroadcastDecoder(output_resolution=(20, 20),
                                    broadcast_resolution=(8, 8),
                                    features=(8, 8), kernel_size=3)
  with pytest.raises(ValueError, match='expected'):
    decoder.init(jax.random.key(0), jnp.zeros((1, 2, 4)))


def test_slot_attention_is_permutation_equivariant_over_slots():
  module = SlotAttention(num_iterations=3, mlp_size=16)
  slots = jax.random.normal(jax.random.key(0), (2, 5, 8))
  inputs = jax.random.normal(jax.random.key(1), (2, 12, 6))
  params = module.init(jax.random.key(2), slots, inputs)
  permutation = jnp.array([3, 0, 4, 1, 2])
  out = module.apply(params, slots, inputs)
  out_permuted = module.apply(params, slots[:, permutation], inputs)
  np.testing.assert_allclose(out_permuted, out[:, permutation], atol=1e-5)
  # ...and sensitive to which slot is which (a constant function would pass
  # the line above).
  assert not np.allclose(out[:, 0], out[:, 1], atol=1e-3)


def _slotformer(positional_encoding='temporal', **kwargs):
  return SlotFormer(burn_in=3, embed_dim=16, num_layers=2, num_heads=2,
                    mlp_size=32, positional_encoding=positional_encoding,
                    **kwargs)


def test_slotformer_is_permutation_equivariant_with_temporal_encoding():
  history = jax.random.normal(jax.random.key(0), (2, 3, 4, 8))
  permutation = jnp.array([2, 0, 3, 1])
  model = _slotformer('temporal')
  params = model.init(jax.random.key(1), history, 5)
  out = model.apply(params, history, 5)
  out_permuted = model.apply(params, history[:, :, permutation], 5)
  np.testing.assert_allclose(out_permuted, out[:, :, permutation], atol=1e-5)


def test_naive_position_encoding_breaks_equivariance():
  history = jax.random.normal(jax.random.key(0), (2, 3, 4, 8))
  permutation = jnp.array([2, 0, 3, 1])
  model = _slotformer('naive')
  params = model.init(jax.random.key(1), history, 2)
  out = model.apply(params, history, 2)
  out_permuted = model.apply(params, history[:, :, permutation], 2)
  assert not np.allclose(out_permuted, out[:, :, permutation], atol=1e-3)


@pytest.mark.parametrize('residual', [False, True])
def test_scan_rollout_equals_python_loop(residual):
  model = _slotformer(residual=residual)
  history = jax.random.normal(jax.random.key(0), (2, 3, 4, 8))
  params = model.init(jax.random.key(1), history, 6)
  # Perturb every weight (the residual variant's output layer starts at 0).
  leaves, treedef = jax.tree.flatten(params)
  noise = jax.random.split(jax.random.key(2), len(leaves))
  params = jax.tree.unflatten(treedef, [
      leaf + 0.1 * jax.random.normal(key, leaf.shape)
      for leaf, key in zip(leaves, noise)])
  rolled = model.apply(params, history, 6)
  window, expected = history, []
  for _ in range(6):
    prediction = model.apply(params, window, method=SlotFormer.predict_next)
    expected.append(prediction)
    window = jnp.concatenate([window[:, 1:], prediction[:, None]], axis=1)
  np.testing.assert_allclose(rolled, jnp.stack(expected, axis=1), rtol=1e-5,
                             atol=1e-4)


def test_teacher_forcing_feeds_the_given_slots():
  model = _slotformer()
  history = jax.random.normal(jax.random.key(0), (1, 3, 4, 8))
  teacher = jax.random.normal(jax.random.key(1), (1, 4, 4, 8))
  params = model.init(jax.random.key(2), history, 4)
  rolled = model.apply(params, history, 4, teacher_slots=teacher)
  # Step k sees the burn-in tail followed by the true slots of steps < k.
  for step in range(4):
    context = jnp.concatenate([history, teacher[:, :step]], axis=1)[:, -3:]
    np.testing.assert_allclose(
        rolled[:, step],
        model.apply(params, context, method=SlotFormer.predict_next),
        atol=1e-5)


def test_residual_prediction_starts_from_the_last_slots():
  model = _slotformer(residual=True)
  history = jax.random.normal(jax.random.key(0), (1, 3, 4, 8))
  params = model.init(jax.random.key(1), history, 4)
  # Freshly initialised, the refinement is 0: the copy-last baseline.
  np.testing.assert_allclose(model.apply(params, history, 4),
                             jnp.repeat(history[:, -1:], 4, axis=1),
                             atol=1e-6)
  # The plain variant predicts from scratch.
  plain = _slotformer(residual=False)
  plain_params = plain.init(jax.random.key(1), history, 1)
  assert not np.allclose(plain.apply(plain_params, history, 1)[:, 0],
                         history[:, -1], atol=1e-2)


def test_kl_matches_hand_computation():
  # One slot, two dimensions: sigma = 0.2 and 0.05 against sigma_hat = 0.1.
  log_variance = jnp.log(jnp.array([[0.2**2, 0.05**2]]))
  by_hand = ((np.log(0.1 / 0.2) + 0.2**2 / (2 * 0.1**2) - 0.5)
             + (np.log(0.1 / 0.05) + 0.05**2 / (2 * 0.1**2) - 0.5))
  np.testing.assert_allclose(kl_to_fixed_sigma(log_variance, 0.1), [by_hand],
                             rtol=1e-6)
  # Zero exactly at the prior.
  np.testing.assert_allclose(
      kl_to_fixed_sigma(jnp.full((3, 5), 2 * np.log(0.1)), 0.1), 0.0,
      atol=1e-6)


def test_gaussian_sampler_kl_and_sampling():
  sampler = GaussianSlotSampler(prior_sigma=0.1)
  slots = jax.random.normal(jax.random.key(0), (2, 3, 8))
  variables = sampler.init({'params': jax.random.key(1),
                            'sample': jax.random.key(2)}, slots)
  sample_a, kl = sampler.apply(variables, slots,
                               rngs={'sample': jax.random.key(3)})
  sample_b, _ = sampler.apply(variables, slots,
                              rngs={'sample': jax.random.key(4)})
  assert kl.shape == (2, 3)
  assert not np.allclose(sample_a, sample_b)  # stochastic
  # The KL is that of the predicted log-variance (second half of the MLP).
  hidden = nn.Dense(16).apply({'params': variables['params']['hidden']},
                              slots)
  hidden = nn.relu(nn.LayerNorm().apply(
      {'params': variables['params']['norm']}, hidden))
  statistics = nn.Dense(16).apply(
      {'params': variables['params']['statistics']}, hidden)
  np.testing.assert_allclose(kl, kl_to_fixed_sigma(statistics[..., 8:], 0.1),
                             rtol=1e-5)


@pytest.mark.parametrize('stochastic,lstm_size', [(False, 0), (True, 8)])
def test_savi_chunked_encoding_equals_whole_video(stochastic, lstm_size):
  """Carrying the state across chunks gives the same slots as one call."""
  model = tiny_savi(
      stochastic=stochastic, posterior_head='mlp' if stochastic else 'none',
      predictor=dict(
          kind='transformer_lstm' if lstm_size else 'transformer',
          lstm_size=lstm_size))
  video = jax.random.uniform(jax.random.key(0), (2, 6, 16, 16, 3),
                             minval=-1.0, maxval=1.0)
  rngs = {'params': jax.random.key(1), 'sample': jax.random.key(2)}
  params = model.init(rngs, video)
  rng = {'sample': jax.random.key(5)}
  output = model.apply(params, video, rngs=rng)
  assert output.slots.shape == (2, 6, 3, 16)
  assert output.decoded.recon.shape == (2, 6, 16, 16, 3)
  if stochastic:
    assert np.all(np.asarray(output.kl) > 0)
    return  # different chunks draw different noise by construction
  np.testing.assert_array_equal(output.kl, 0.0)
  first, _, carry = model.apply(params, video[:, :4], method=SAVi.encode,
                                rngs=rng)
  second, _, _ = model.apply(params, video[:, 4:], carry, method=SAVi.encode,
                             rngs=rng)
  np.testing.assert_allclose(jnp.concatenate([first, second], axis=1),
                             output.slots, atol=1e-5)


def test_pointwise_conv_is_a_1x1_convolution():
  """Same parameter tree, initial values and outputs as nn.Conv(F, (1, 1))."""
  x = jax.random.normal(jax.random.key(0), (2, 3, 5, 7, 6))
  conv = nn.Conv(4, (1, 1))
  pointwise = PointwiseConv(4)
  conv_params = conv.init(jax.random.key(1), x)
  pointwise_params = pointwise.init(jax.random.key(1), x)
  jax.tree.map(np.testing.assert_array_equal, conv_params, pointwise_params)
  np.testing.assert_allclose(pointwise.apply(conv_params, x),
                             conv.apply(conv_params, x), atol=1e-5)


@pytest.mark.parametrize('padding', [((2, 2), (2, 2)), ((1, 1), (0, 1)),
                                     ((0, 1), (1, 0)), ((-1, 2), (0, 0))])
def test_conv2d_gradients_equal_xla_autodiff(padding):
  """conv2d's own kernel gradient (transpose of x @ I) is the plain one."""
  from slotformer_jax.modules import convolution
  rng = np.random.default_rng(7)
  x = jnp.asarray(rng.normal(size=(3, 7, 6, 4)), jnp.float32)
  kernel = jnp.asarray(rng.normal(size=(3, 2, 4, 5)), jnp.float32)

  def plain(x, kernel):
    return jax.lax.conv_general_dilated(
        x, kernel, (1, 1), padding,
        dimension_numbers=('NHWC', 'HWIO', 'NHWC'))

  out = convolution.conv2d(x, kernel, padding)
  np.testing.assert_array_equal(out, plain(x, kernel))
  cotangent = jnp.asarray(rng.normal(size=out.shape), jnp.float32)
  expected = jax.vjp(plain, x, kernel)[1](cotangent)
  got = jax.vjp(lambda x, k: convolution.conv2d(x, k, padding),
                x, kernel)[1](cotangent)
  for e, g in zip(expected, got):
    np.testing.assert_allclose(g, e, rtol=1e-5, atol=1e-5)


def test_same_conv_is_nn_conv():
  from slotformer_jax.modules import convolution
  x = jax.random.normal(jax.random.key(0), (2, 9, 8, 3))
  conv = nn.Conv(6, (5, 5), padding='SAME')
  same = convolution.SameConv(6, 5)
  params = conv.init(jax.random.key(1), x)
  jax.tree.map(np.testing.assert_array_equal, params,
               same.init(jax.random.key(1), x))
  np.testing.assert_allclose(same.apply(params, x), conv.apply(params, x),
                             atol=1e-5)
  grads = [jax.grad(lambda p, m=m: jnp.sum(m.apply(p, x) ** 2))(params)
           for m in (conv, same)]
  jax.tree.map(functools.partial(np.testing.assert_allclose, rtol=1e-5,
                                 atol=1e-4), *grads)
