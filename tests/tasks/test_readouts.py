"""Tests of the Physion / PHYRE readout heads."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from slotformer_jax.modules import readouts


def _slots(seed=0, shape=(3, 5, 4, 8)):
  return jax.random.normal(jax.random.key(seed), shape)


def _permuted(slots):
  # Reverse the slots then swap the first two: no slot stays in place.
  perm = np.arange(slots.shape[2])[::-1].copy()
  perm[[0, 1]] = perm[[1, 0]]
  return slots[:, :, perm]


def test_slot_pairs():
  np.testing.assert_array_equal(readouts.slot_pairs(3, 'unordered'),
                                [[0, 1], [0, 2], [1, 2]])
  assert len(readouts.slot_pairs(4, 'both_orders')) == 12
  with pytest.raises(ValueError):
    readouts.slot_pairs(1, 'unordered')


def test_physion_readout_is_the_relation_max_max():
  slots = _slots()
  model = readouts.PhysionReadout(features=6)
  params = model.init(jax.random.key(0), slots)
  logits = model.apply(params, slots)
  assert logits.shape == (3,)
  # By hand: per frame max over i<j of W1 [s_i; s_j] + b1, then W2 . + b2,
  # then max over frames.
  p = params['params']
  w1, b1 = p['relation']['kernel'], p['relation']['bias']
  w2, b2 = p['logit']['kernel'], p['logit']['bias']
  x = np.asarray(slots)
  expected = np.full(3, -np.inf)
  for b in range(3):
    for t in range(5):
      feats = [np.concatenate([x[b, t, i], x[b, t, j]]) @ w1 + b1
               for i in range(4) for j in range(i + 1, 4)]
      frame = np.max(feats, axis=0) @ w2 + b2
      expected[b] = max(expected[b], frame[0])
  np.testing.assert_allclose(logits, expected, rtol=1e-5, atol=1e-5)


def test_physion_readout_permutation_invariance():
  slots = _slots()
  model = readouts.PhysionReadout(features=6, pairs='both_orders')
  params = model.init(jax.random.key(0), slots)
  np.testing.assert_allclose(model.apply(params, slots),
                             model.apply(params, _permuted(slots)),
                             rtol=1e-6, atol=1e-6)
  # Over time as well (max over frames).
  np.testing.assert_allclose(model.apply(params, slots),
                             model.apply(params, slots[:, ::-1]),
                             rtol=1e-6, atol=1e-6)
  # The official unordered pairs concatenate in index order, so they are
  # NOT invariant: this is why 'both_orders' exists.
  official = readouts.PhysionReadout(features=6)
  params = official.init(jax.random.key(0), slots)
  assert not np.allclose(official.apply(params, slots),
                         official.apply(params, _permuted(slots)))


def test_phyre_readout_permutation_invariance_and_time_order():
  slots = _slots(shape=(2, 6, 5, 16))
  model = readouts.PhyreReadout(selected_steps=(0, 3), embed_dim=16,
                                num_layers=2, num_heads=4, mlp_size=32)
  params = model.init(jax.random.key(0), slots)
  # [CLS] starts at zero: perturb it so the test does not pass trivially.
  params = jax.tree.map(
      lambda v: v + 0.1 * jax.random.normal(jax.random.key(3), v.shape),
      params)
  apply = jax.jit(model.apply)
  logits = apply(params, slots)
  assert logits.shape == (2,)
  np.testing.assert_allclose(logits, apply(params, _permuted(slots)),
                             rtol=1e-5, atol=1e-5)
  # Only frames 0 and 3 are read ...
  changed = slots.at[:, 1].add(5.0).at[:, 4:].add(5.0)
  np.testing.assert_allclose(logits, apply(params, changed),
                             rtol=1e-6, atol=1e-6)
  # ... and their order matters (temporal position code).
  swapped = slots.at[:, 0].set(slots[:, 3]).at[:, 3].set(slots[:, 0])
  assert not np.allclose(logits, apply(params, swapped), atol=1e-4)
  with pytest.raises(ValueError, match='out of range'):
    model.apply(params, slots[:, :3])
