"""dVAE, STEVE's token decoder (causality, KV-cache generation) and STEVE."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax.slot_models import steve as steve_slots
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.dvae import pixel_shuffle
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.modules.token_decoder import TokenDecoder
from tiny_models import tiny_steve

VOCAB = 16
GRID = (4, 4)


def _decoder(dropout=0.0):
  return TokenDecoder(vocab_size=VOCAB, num_tokens=GRID[0] * GRID[1], dim=16,
                      num_layers=2, num_heads=2, dropout_rate=dropout)


def _decoder_setup():
  decoder = _decoder()
  slots = jax.random.normal(jax.random.key(1), (3, 4, 16))
  tokens = jax.random.randint(jax.random.key(2), (3, 16), 0, VOCAB)
  params = decoder.init(jax.random.key(0), slots, tokens)['params']
  return decoder, params, slots, tokens


def test_pixel_shuffle_matches_pytorch_order():
  factor, channels = 2, 3
  x = np.arange(2 * 3 * 5 * channels * 4, dtype=np.float32).reshape(
      2, 3, 5, channels * 4)
  out = np.asarray(pixel_shuffle(jnp.asarray(x), factor))
  assert out.shape == (2, 6, 10, channels)
  for c in range(channels):
    for i in range(factor):
      for j in range(factor):
        np.testing.assert_array_equal(
            out[:, i::factor, j::factor, c], x[..., c * 4 + i * 2 + j])


def test_dvae_shapes():
  dvae = DVAE(vocab_size=VOCAB, hidden_size=8)
  images = jax.random.uniform(jax.random.key(0), (2, 16, 16, 3), minval=-1)
  variables = dvae.init({'params': jax.random.key(1),
                         'gumbel': jax.random.key(2)}, images, 1.0)
  recon, log_probs = dvae.apply(variables, images, 0.5,
                                rngs={'gumbel': jax.random.key(3)})
  assert recon.shape == images.shape
  assert log_probs.shape == (2, 4, 4, VOCAB)
  np.testing.assert_allclose(jnp.exp(log_probs).sum(-1), 1.0, rtol=1e-5)
  tokens = dvae.apply(variables, images, method=DVAE.tokenize)
  assert tokens.shape == (2, 4, 4) and tokens.dtype == jnp.int32
  np.testing.assert_array_equal(tokens, jnp.argmax(log_probs, -1))
  frames = jnp.asarray(np.random.default_rng(0).integers(
      0, 256, (2, 3, 16, 16, 3), dtype=np.uint8))
  flat = steve_slots.tokenize(variables['params'], frames, dvae=dvae)
  assert flat.shape == (2, 3, 16)
  decoded = steve_slots.decode_tokens(variables['params'], flat,
                                          dvae=dvae, token_grid=(4, 4))
  assert decoded.shape == (2, 3, 16, 16, 3)


def test_decoder_is_causal():
  """Changing token k never changes the logits of positions <= k (which
  are predicted from tokens < their position), and does change later ones."""
  decoder, params, slots, tokens = _decoder_setup()
  forward = jax.jit(decoder.apply)
  logits = forward({'params': params}, slots, tokens)
  for k in (0, 5, 14):
    changed = tokens.at[:, k].set((tokens[:, k] + 1) % VOCAB)
    other = forward({'params': params}, slots, changed)
    np.testing.assert_array_equal(other[:, :k + 1], logits[:, :k + 1])
    assert float(jnp.abs(other[:, k + 1:] - logits[:, k + 1:]).max()) > 1e-4


def test_kv_cache_generation_equals_recomputation():
  decoder, params, slots, _ = _decoder_setup()
  generate = jax.jit(functools.partial(steve_slots.generate_tokens,
                                       decoder=decoder))
  tokens, weights = generate(params, slots)
  reference = jax.jit(functools.partial(
      steve_slots.generate_tokens_recomputed, decoder=decoder))(
          params, slots)
  np.testing.assert_array_equal(tokens, reference)
  assert len(np.unique(np.asarray(tokens))) > 2  # not a degenerate sequence
  assert weights.shape == (3, 16, 4)
  np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=1e-5)
  # The cached step's logits are the full forward's on the same sequence.
  cache = decoder.apply({'params': params}, slots,
                        method=TokenDecoder.init_cache)
  full = decoder.apply({'params': params}, slots, tokens)
  previous = jnp.full((3,), VOCAB)
  decode_step = jax.jit(functools.partial(decoder.apply,
                                          method=TokenDecoder.decode_step))
  for position in range(16):
    step_logits, _, cache = decode_step(
        {'params': params}, previous, jnp.asarray(position), cache)
    np.testing.assert_allclose(step_logits, full[:, position], atol=1e-4,
                               rtol=1e-4)
    previous = tokens[:, position]


def _steve():
  return tiny_steve((16, 16), VOCAB)


def test_steve_shapes_and_permutation_equivariance():
  model = _steve()
  video = jax.random.uniform(jax.random.key(0), (2, 3, 16, 16, 3), minval=-1)
  tokens = jax.random.randint(jax.random.key(1), (2, 3, 16), 0, VOCAB)
  params = model.init(jax.random.key(2), video, tokens)['params']
  logits, slots, masks = model.apply({'params': params}, video, tokens)
  assert logits.shape == (2, 3, 16, VOCAB)
  assert slots.shape == (2, 3, 3, 16)
  assert masks.shape == (2, 3, 3, 8, 8)
  np.testing.assert_allclose(masks.sum(2), 1.0, rtol=1e-5)

  # Permuting the initial slots (and the LSTM state) permutes every frame's
  # slots and masks, and leaves the token logits unchanged.
  permutation = np.array([2, 0, 1])
  initial, lstm = model.apply({'params': params}, 2,
                              method=STEVE.initial_carry)
  lstm = tuple(x + 0.1 * jax.random.normal(jax.random.key(3), x.shape)
               for x in lstm)
  run = jax.jit(lambda carry: model.apply({'params': params}, video, carry,
                                          method=STEVE.encode))
  slots_a, masks_a, _ = run((initial, lstm))
  slots_b, masks_b, _ = run((initial[:, permutation],
                             tuple(x[:, permutation] for x in lstm)))
  np.testing.assert_allclose(slots_b, slots_a[:, :, permutation], atol=1e-5)
  np.testing.assert_allclose(masks_b, masks_a[:, :, permutation], atol=1e-5)
  logits_a = model.apply({'params': params}, slots_a, tokens,
                         method=STEVE.token_logits)
  logits_b = model.apply({'params': params}, slots_b, tokens,
                         method=STEVE.token_logits)
  np.testing.assert_allclose(logits_a, logits_b, atol=1e-4)
