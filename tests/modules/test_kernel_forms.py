"""Kernels per platform (`slotformer_jax.modules.platform`): the CPU forms
and the accelerator forms compute the same function, share one parameter
tree, and the default picks the CPU form on CPU (bit for bit) and the
accelerator form when lowered for GPU / TPU."""

import functools
import importlib.util
import os
import subprocess
import sys

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.modules import convolution
from slotformer_jax.modules import decoders
from slotformer_jax.modules import platform
from slotformer_jax.modules import transformer
from slotformer_jax.modules.aloe import Aloe
from slotformer_jax.modules.slotformer import SlotFormer

CPU, ACCELERATOR, AUTO = platform.CPU, platform.ACCELERATOR, platform.AUTO
ROOT = os.path.join(os.path.dirname(__file__), '..', '..')
close = functools.partial(np.testing.assert_allclose, rtol=1e-4, atol=1e-5)


def _tree_close(a, b, **tolerance):
  assert jax.tree.structure(a) == jax.tree.structure(b)
  jax.tree.map(functools.partial(np.testing.assert_allclose, **tolerance),
               a, b)


def _tree_equal(a, b):
  assert jax.tree.structure(a) == jax.tree.structure(b)
  jax.tree.map(np.testing.assert_array_equal, a, b)


def _value_and_grads(module, variables, *inputs, **kwargs):
  """jit(value_and_grad) of sum(sin(output)) w.r.t. the parameters and the
  float array inputs (others, masks and step counts, are held fixed): a
  cotangent that is not constant, so every gradient is tested."""
  is_float = [isinstance(x, jax.Array) and jnp.issubdtype(x.dtype,
                                                          jnp.floating)
              for x in inputs]

  def loss(params, *floats):
    floats = iter(floats)
    args = [next(floats) if f else x for x, f in zip(inputs, is_float)]
    out = module.apply({'params': params}, *args, **kwargs)
    leaves = jax.tree.leaves(out)
    return sum(jnp.sum(jnp.sin(leaf)) for leaf in leaves
               if jnp.issubdtype(leaf.dtype, jnp.floating))

  floats = [x for x, f in zip(inputs, is_float) if f]
  argnums = tuple(range(1 + len(floats)))
  return jax.jit(jax.value_and_grad(loss, argnums=argnums))(
      variables['params'], *floats)


def test_unknown_form_is_rejected():
  with pytest.raises(ValueError, match='kernels must be one of'):
    convolution.conv2d(jnp.ones((1, 3, 3, 1)), jnp.ones((1, 1, 1, 1)),
                       ((0, 0), (0, 0)), 'gpu')


@pytest.mark.parametrize('padding', [((2, 2), (2, 2)), ((1, 1), (0, 1)),
                                     ((-1, 2), (0, 0))])
def test_conv2d_forms_agree(padding):
  rng = np.random.default_rng(3)
  x = jnp.asarray(rng.normal(size=(3, 7, 6, 4)), jnp.float32)
  kernel = jnp.asarray(rng.normal(size=(3, 2, 4, 5)), jnp.float32)
  cotangent = None
  results = {}
  for form in (CPU, ACCELERATOR):
    out, vjp = jax.vjp(lambda x, k, f=form: convolution.conv2d(x, k, padding,
                                                               f), x, kernel)
    if cotangent is None:
      cotangent = jnp.asarray(rng.normal(size=out.shape), jnp.float32)
    results[form] = (out, *vjp(cotangent))
  # Same forward op; the kernel gradients differ in how they are computed.
  np.testing.assert_array_equal(results[CPU][0], results[ACCELERATOR][0])
  for cpu, accelerator in zip(results[CPU][1:], results[ACCELERATOR][1:]):
    np.testing.assert_allclose(cpu, accelerator, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize('kernel_size,stride', [(5, 2), (3, 2), (5, 3),
                                                (1, 2)])
def test_transposed_convolution_forms_agree(kernel_size, stride):
  """Phase by phase (CPU) and input-dilated (accelerators): same values,
  same gradients, one parameter tree."""
  x = jax.random.normal(jax.random.key(0), (2, 5, 4, 3))
  layers = {form: decoders.SubPixelConvTranspose(6, kernel_size, stride,
                                                 kernels=form)
            for form in (CPU, ACCELERATOR)}
  variables = {form: layer.init(jax.random.key(1), x)
               for form, layer in layers.items()}
  _tree_equal(variables[CPU], variables[ACCELERATOR])
  out = {form: layer.apply(variables[CPU], x)
         for form, layer in layers.items()}
  assert out[CPU].shape == (2, 5 * stride, 4 * stride, 6)
  close(out[CPU], out[ACCELERATOR])
  grads = {form: _value_and_grads(layer, variables[CPU], x)
           for form, layer in layers.items()}
  _tree_close(grads[CPU], grads[ACCELERATOR], rtol=1e-4, atol=1e-4)


def _paper_decoder(kernels):
  """The OBJ3D / CLEVRER decoder: 8x8 -> 64x64, 4 x 5x5 layers of 64."""
  return decoders.SpatialBroadcastDecoder(
      output_resolution=(64, 64), broadcast_resolution=(8, 8),
      features=(64, 64, 64, 64), kernel_size=5, kernels=kernels)


def test_decoder_forms_agree_and_share_parameters():
  slots = jax.random.normal(jax.random.key(0), (2, 3, 16))  # [B, N, D]
  variables = {form: _paper_decoder(form).init(jax.random.key(1), slots)
               for form in (CPU, ACCELERATOR, AUTO)}
  _tree_equal(variables[CPU], variables[ACCELERATOR])
  _tree_equal(variables[CPU], variables[AUTO])
  values = {form: _value_and_grads(_paper_decoder(form), variables[CPU],
                                   slots)
            for form in (CPU, ACCELERATOR)}
  _tree_close(values[CPU], values[ACCELERATOR], rtol=2e-4, atol=2e-4)


def test_default_decoder_on_cpu_is_the_cpu_form_bit_for_bit():
  """What every CPU result of this project was computed with: `kernels`
  'auto' runs the CPU forms here, outputs and gradients identical."""
  slots = jax.random.normal(jax.random.key(0), (2, 3, 16))
  variables = _paper_decoder(CPU).init(jax.random.key(1), slots)
  _tree_equal(_value_and_grads(_paper_decoder(AUTO), variables, slots),
              _value_and_grads(_paper_decoder(CPU), variables, slots))
  decoded = {form: jax.jit(_paper_decoder(form).apply)(variables, slots)
             for form in (AUTO, CPU)}
  _tree_equal(decoded[AUTO], decoded[CPU])


def _lowered_text(fn, *args, platform_name):
  return jax.jit(fn).trace(*args).lower(
      lowering_platforms=(platform_name,)).as_text()


@pytest.mark.parametrize('platform_name', ['tpu', 'cuda'])
def test_default_lowers_to_the_accelerator_form_off_cpu(platform_name):
  """Lowered from this CPU host for an accelerator (as an ahead-of-time
  compile is), 'auto' is the plain convolution: one `convolution` op for a
  stride-2 transposed convolution instead of one per output phase (4), and
  a kernel gradient without the `x @ I` product (a dot_general)."""
  x = jnp.ones((1, 4, 4, 3))
  kernel = jnp.ones((5, 5, 3, 2))
  transposed = functools.partial(decoders.conv_transpose, stride=2)
  count = lambda text: text.count('stablehlo.convolution')
  assert count(_lowered_text(transposed, x, kernel,
                             platform_name='cpu')) == 4
  assert count(_lowered_text(transposed, x, kernel,
                             platform_name=platform_name)) == 1

  def kernel_grad(x, kernel):
    return jax.grad(lambda k: jnp.sum(convolution.conv2d(
        x, k, ((2, 2), (2, 2))) ** 2))(kernel)

  kernel = jnp.ones((5, 5, 3, 2))
  assert 'dot_general' in _lowered_text(kernel_grad, x, kernel,
                                        platform_name='cpu')
  assert 'dot_general' not in _lowered_text(kernel_grad, x, kernel,
                                            platform_name=platform_name)


def _attention_reference(query, key, value, mask):
  """softmax(Q K^T / sqrt(d)) V written out in numpy (float64)."""
  query, key, value = (np.asarray(a, np.float64) for a in (query, key, value))
  logits = np.einsum('bqhd,bkhd->bhqk', query, key) / np.sqrt(query.shape[-1])
  if mask is not None:
    logits = np.where(np.asarray(mask), logits, -np.inf)
  weights = np.exp(logits - logits.max(axis=-1, keepdims=True))
  weights /= weights.sum(axis=-1, keepdims=True)
  return np.einsum('bhqk,bkhd->bqhd', weights, value)


def _key_mask(batch, length, first_valid):
  """SlotFormer's growing-context mask: keys before `first_valid` hidden."""
  valid = jnp.arange(length) >= first_valid
  return jnp.broadcast_to(valid[None, None, None, :],
                          (batch, 1, length, length))


def _padding_mask(batch, length, num_padded):
  """Aloe's key-padding mask: the last `num_padded` tokens hidden."""
  keep = jnp.arange(length) < length - num_padded
  keep = jnp.broadcast_to(keep, (batch, length))
  return nn.make_attention_mask(jnp.ones_like(keep), keep)


@pytest.mark.parametrize('mask_kind', ['none', 'key', 'padding'])
@pytest.mark.parametrize('form', [CPU, ACCELERATOR, AUTO])
def test_attention_forms_equal_explicit_softmax(form, mask_kind):
  query, key, value = (jax.random.normal(jax.random.key(i), (2, 12, 4, 8))
                       for i in range(3))
  mask = {'none': None, 'key': _key_mask(2, 12, 5),
          'padding': _padding_mask(2, 12, 4)}[mask_kind]
  got = jax.jit(functools.partial(transformer.attention_by_platform,
                                  kernels=form))(query, key, value, mask)
  np.testing.assert_allclose(got, _attention_reference(query, key, value,
                                                       mask),
                             rtol=1e-5, atol=1e-5)


def _encoder(kernels, dropout_rate=0.0):
  return transformer.TransformerEncoder(
      num_layers=2, num_heads=4, mlp_size=64, dropout_rate=dropout_rate,
      kernels=kernels)


def test_transformer_forms_agree_with_gradients():
  x = jax.random.normal(jax.random.key(0), (2, 12, 32))
  mask = _key_mask(2, 12, 3)
  variables = {form: _encoder(form).init(jax.random.key(1), x, mask)
               for form in (CPU, ACCELERATOR)}
  _tree_equal(variables[CPU], variables[ACCELERATOR])
  values = {form: _value_and_grads(_encoder(form), variables[CPU], x, mask)
            for form in (CPU, ACCELERATOR)}
  _tree_close(values[CPU], values[ACCELERATOR], rtol=1e-4, atol=1e-5)
  # The default here is the explicit form, bit for bit.
  _tree_equal(_value_and_grads(_encoder(AUTO), variables[CPU], x, mask),
              values[CPU])


def test_attention_dropout_keeps_the_explicit_form():
  """With attention-probability dropout on, both forms drop the same
  probabilities: the explicit form runs whatever `kernels` says."""
  x = jax.random.normal(jax.random.key(0), (2, 12, 32))
  variables = _encoder(CPU, 0.5).init(jax.random.key(1), x)
  outs = [_encoder(form, 0.5).apply(variables, x, deterministic=False,
                                    rngs={'dropout': jax.random.key(2)})
          for form in (CPU, ACCELERATOR)]
  np.testing.assert_array_equal(*outs)
  deterministic = _encoder(CPU, 0.5).apply(variables, x)
  assert not np.allclose(outs[0], deterministic, atol=1e-3)


def test_attention_lowers_to_jax_nn_off_cpu():
  """jax.nn.dot_product_attention scales the logits (a multiply), flax's
  explicit form the query (a divide): the lowered program says which."""
  query = jnp.ones((2, 5, 2, 4))
  attend = lambda q: transformer.attention_by_platform(q, q, q)
  assert 'stablehlo.multiply' not in _lowered_text(attend, query,
                                                   platform_name='cpu')
  assert 'stablehlo.multiply' in _lowered_text(attend, query,
                                               platform_name='tpu')


def _slotformer(kernels, **fields):
  return SlotFormer(burn_in=2, embed_dim=32, num_layers=2, num_heads=4,
                    mlp_size=64, kernels=kernels, **fields)


@pytest.mark.parametrize('max_context', [0, 4])
def test_slotformer_rollout_forms_agree(max_context):
  """The rollout (nn.scan, a growing-context mask with max_context)."""
  history = jax.random.normal(jax.random.key(0), (2, 2, 3, 8))
  variables = _slotformer(CPU, max_context=max_context).init(
      jax.random.key(1), history, 4)
  _tree_equal(variables, _slotformer(ACCELERATOR, max_context=max_context)
              .init(jax.random.key(1), history, 4))
  values = {form: _value_and_grads(
      _slotformer(form, max_context=max_context), variables, history, 4)
            for form in (CPU, ACCELERATOR, AUTO)}
  # Gradients through 4 fed-back steps reach ~40: 1e-4 absolute is float32
  # rounding at that scale.
  _tree_close(values[CPU], values[ACCELERATOR], rtol=1e-4, atol=1e-4)
  _tree_equal(values[AUTO], values[CPU])


def test_attention_weights_are_still_recorded():
  """The attention figures read the sown weights of the last block
  (`evaluation.visualize.last_layer_attention`): with 'intermediates'
  mutable every form records them, and the output is unchanged."""
  history = jax.random.normal(jax.random.key(0), (2, 2, 3, 8))
  variables = _slotformer(CPU).init(jax.random.key(1), history, 1)
  for form in (CPU, ACCELERATOR):
    model = _slotformer(form)
    prediction, state = model.apply(variables, history,
                                    method=model.predict_next,
                                    mutable=['intermediates'])
    weights = state['intermediates']['predictor']['transformer'][
        'block_1']['attention']['attention_weights'][0]
    assert weights.shape == (2, 4, 6, 6)  # [B, heads, T*N, T*N]
    np.testing.assert_allclose(weights.sum(axis=-1), 1.0, atol=1e-5)
    close(prediction, model.apply(variables, history,
                                  method=model.predict_next))


def test_aloe_forms_agree():
  model = functools.partial(Aloe, vocab_size=11, num_answers=5, num_frames=2,
                            num_slots=3, text_length=6, question_length=4,
                            d_model=32, word_dim=6, num_layers=2,
                            num_heads=4, mlp_size=64, head_size=16)
  rng = np.random.default_rng(0)
  slots = jnp.asarray(rng.normal(size=(2, 2, 3, 8)), jnp.float32)
  tokens = jnp.asarray(rng.integers(1, 11, (2, 6)))
  pad = jnp.asarray([[False] * 6, [False] * 3 + [True] * 3])
  variables = model(kernels=CPU).init(jax.random.key(0), slots, tokens, pad,
                                      method='open_logits')
  logits = {form: model(kernels=form).apply(variables, slots, tokens, pad,
                                            method='open_logits')
            for form in (CPU, ACCELERATOR, AUTO)}
  close(logits[CPU], logits[ACCELERATOR])
  np.testing.assert_array_equal(logits[AUTO], logits[CPU])


def test_tpu_kernels_benchmark_without_libtpu_says_so():
  if importlib.util.find_spec('libtpu') is not None:
    pytest.skip('libtpu is installed: the benchmark would compile')
  result = subprocess.run(
      [sys.executable, os.path.join(ROOT, 'benchmarks', 'tpu_kernels.py')],
      capture_output=True, text=True, timeout=300, check=False)
  assert result.returncode == 0, result.stderr
  assert 'nothing compiled: libtpu is not installed' in result.stdout


def test_tiny_decoder_compiles_for_a_tpu_in_both_forms():
  """With libtpu (pip install -e '.[tpu]'): the XLA:TPU compiler on this
  host, compile-only v5e devices; 'auto' must be the accelerator form."""
  pytest.importorskip('libtpu')
  from jax.experimental import topologies
  from jax.sharding import Mesh, NamedSharding, PartitionSpec
  devices = topologies.get_topology_desc(topology_name='v5e:2x2',
                                         platform='tpu').devices
  mesh = Mesh(np.array(devices), ('data',))
  replicated = NamedSharding(mesh, PartitionSpec())
  batch = NamedSharding(mesh, PartitionSpec('data'))
  slots = jax.ShapeDtypeStruct((8, 3, 16), jnp.float32, sharding=batch)
  costs = {}
  for form in (CPU, ACCELERATOR, AUTO):
    decoder = decoders.SpatialBroadcastDecoder(
        output_resolution=(16, 16), broadcast_resolution=(4, 4),
        features=(8, 8, 8), kernel_size=5, kernels=form)
    params = jax.eval_shape(decoder.init, jax.random.key(0), slots)
    params = jax.tree.map(
        lambda p: jax.ShapeDtypeStruct(p.shape, p.dtype, sharding=replicated),
        params)
    grad = jax.jit(jax.grad(
        lambda p, s, d=decoder: jnp.mean(d.apply(p, s).recon ** 2),
        argnums=(0, 1)))
    compiled = grad.lower(params, slots).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    assert compiled.memory_analysis().temp_size_in_bytes >= 0
    costs[form] = (cost['flops'], cost['bytes accessed'])
  assert costs[AUTO] == costs[ACCELERATOR]
  assert costs[CPU] != costs[ACCELERATOR]
