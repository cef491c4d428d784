"""Aloe over slots: slot-order invariance, padding mask, per-choice heads."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.modules import aloe

B, T, N, D, L, LQ, C = 2, 3, 4, 8, 7, 4, 3


def _model(positions: str) -> aloe.Aloe:
  return aloe.Aloe(vocab_size=11, num_answers=5, num_frames=T, num_slots=N,
                   text_length=L, question_length=LQ, d_model=16, word_dim=6,
                   num_layers=2, num_heads=2, mlp_size=32, head_size=16,
                   dropout_rate=0.0, positions=positions)


def _inputs(seed: int = 0):
  rng = np.random.default_rng(seed)
  slots = jnp.asarray(rng.normal(size=(B, T, N, D)), jnp.float32)
  tokens = jnp.asarray(rng.integers(1, 11, size=(B, C, L)), jnp.int32)
  lengths = np.array([[5, 7, 6], [4, 5, 7]])
  pad = jnp.asarray(np.arange(L)[None, None] >= lengths[..., None])
  return slots, tokens, pad


def _params(model: aloe.Aloe, seed: int = 0):
  """Initialised, then every leaf perturbed: zero-initialised positions and
  [CLS] would otherwise hide what the test looks for."""
  slots, tokens, pad = _inputs()
  params = jax.jit(model.init)(jax.random.PRNGKey(seed), slots,
                               tokens[:, 0], pad[:, 0], slots, tokens, pad)
  leaves, tree = jax.tree_util.tree_flatten(params)
  keys = jax.random.split(jax.random.PRNGKey(seed + 1), len(leaves))
  leaves = [x + 0.3 * jax.random.normal(k, x.shape) for x, k in
            zip(leaves, keys)]
  return jax.tree_util.tree_unflatten(tree, leaves)


def _permute_within_frames(slots: jax.Array, seed: int) -> jax.Array:
  rng = np.random.default_rng(seed)
  out = np.array(slots)
  for b in range(B):
    for t in range(T):
      out[b, t] = out[b, t, rng.permutation(N)]
  return jnp.asarray(out)


def _outputs(model, params, slots, tokens, pad):
  return _jit_apply(model)(params, slots, tokens[:, 0], pad[:, 0], slots,
                           tokens, pad)


def _jit_apply(model, method=None):
  # Op-by-op (eager) flax is several times slower than one compiled call.
  return jax.jit(lambda *args: model.apply(*args, method=method))


def test_frame_positions_make_answers_invariant_to_slot_order():
  model = _model(aloe.FRAME)
  params = _params(model)
  slots, tokens, pad = _inputs()
  open_logits, choice_logits = _outputs(model, params, slots, tokens, pad)
  assert open_logits.shape == (B, 5) and choice_logits.shape == (B, C)
  permuted = _permute_within_frames(slots, seed=3)
  assert not np.allclose(permuted, slots)
  open_p, choice_p = _outputs(model, params, permuted, tokens, pad)
  np.testing.assert_allclose(open_p, open_logits, atol=1e-5)
  np.testing.assert_allclose(choice_p, choice_logits, atol=1e-5)
  # Swapping slots across frames is not a symmetry.
  swapped = slots.at[:, 0, 0].set(slots[:, 1, 0]).at[:, 1, 0].set(
      slots[:, 0, 0])
  open_s, _ = _outputs(model, params, swapped, tokens, pad)
  assert not np.allclose(open_s, open_logits, atol=1e-4)


def test_token_positions_tell_slots_apart():
  # The official per-token positions (once trained, i.e. non-zero) break the
  # symmetry: the invariance test above would fail for them.
  model = _model(aloe.TOKEN)
  params = _params(model)
  slots, tokens, pad = _inputs()
  open_logits, _ = _outputs(model, params, slots, tokens, pad)
  open_p, _ = _outputs(model, params, _permute_within_frames(slots, 3),
                       tokens, pad)
  assert not np.allclose(open_p, open_logits, atol=1e-4)


@pytest.mark.parametrize('positions', [aloe.TOKEN, aloe.FRAME])
def test_padded_words_are_ignored(positions):
  model = _model(positions)
  params = _params(model)
  slots, tokens, pad = _inputs()
  reference = _outputs(model, params, slots, tokens, pad)
  # Different ids at padded positions: same answers.
  noise = jnp.asarray(np.random.default_rng(5).integers(1, 11, tokens.shape))
  changed = jnp.where(pad, noise, tokens)
  assert not np.array_equal(changed, tokens)
  for got, want in zip(_outputs(model, params, slots, changed, pad),
                       reference):
    np.testing.assert_allclose(got, want, atol=1e-5)
  # Un-padding a word changes them: the mask is what hides it.
  unpadded = jnp.zeros_like(pad)
  got = _outputs(model, params, slots, changed, unpadded)
  assert not np.allclose(got[1], reference[1], atol=1e-4)


def test_choices_are_scored_independently():
  model = _model(aloe.TOKEN)
  params = _params(model)
  slots, tokens, pad = _inputs()
  choice_logits = _jit_apply(model, aloe.Aloe.choice_logits)
  together = choice_logits(params, slots, tokens, pad)
  for c in range(C):
    alone = choice_logits(params, slots, tokens[:, c:c + 1], pad[:, c:c + 1])
    np.testing.assert_allclose(alone[:, 0], together[:, c], atol=1e-5)
  # The question part and the choice part carry different flags.
  flipped = choice_logits(params, slots, tokens[:, :, ::-1], pad[:, :, ::-1])
  assert not np.allclose(flipped, together, atol=1e-4)
