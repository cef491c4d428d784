"""Conditional SAVi: slots started from the first frame's boxes or points."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.slot_init import conditioning_coordinates
from tiny_models import tiny_savi


def _tiny_savi(**kwargs):
  return tiny_savi(num_slots=4, **kwargs)


def _boxes(seed, batch=2, rows=3):
  """Random valid boxes [B, O, 4] (ymin < ymax, xmin < xmax) in [0, 1]."""
  rng = np.random.default_rng(seed)
  low = rng.uniform(0.0, 0.5, size=(batch, rows, 2))
  high = low + rng.uniform(0.1, 0.5, size=(batch, rows, 2))
  return jnp.asarray(np.concatenate([low, high], -1),
                     jnp.float32)


def _video():
  return jax.random.uniform(jax.random.key(0), (2, 3, 16, 16, 3),
                            minval=-1.0, maxval=1.0)


def _init(model, boxes):
  return model.init({'params': jax.random.key(1),
                     'sample': jax.random.key(2)}, _video(), boxes=boxes)


@pytest.mark.parametrize('kind', ['boxes', 'points'])
def test_slot_i_follows_box_i(kind):
  """Permuting the box rows permutes slots 1.. the same way, both the
  initial slots and the first frame's corrected slots; slot 0 (background)
  stays."""
  model = _tiny_savi(initial_slots=kind)
  boxes = _boxes(0)
  params = _init(model, boxes)
  permutation = np.array([2, 0, 1])
  slot_permutation = np.concatenate([[0], 1 + permutation])

  initial, _ = model.apply(params, 2, boxes, method=SAVi.initial_carry)
  permuted, _ = model.apply(params, 2, boxes[:, permutation],
                            method=SAVi.initial_carry)
  np.testing.assert_allclose(permuted, initial[:, slot_permutation],
                             atol=1e-6)

  slots = model.apply(params, _video(), boxes=boxes).slots
  slots_permuted = model.apply(params, _video(),
                               boxes=boxes[:, permutation]).slots
  np.testing.assert_allclose(slots_permuted[:, 0],
                             slots[:, 0][:, slot_permutation], atol=1e-5)


def test_first_frame_slots_depend_on_the_boxes():
  model = _tiny_savi(initial_slots='boxes')
  params = _init(model, _boxes(0))
  a = model.apply(params, _video(), boxes=_boxes(0)).slots[:, 0]
  b = model.apply(params, _video(), boxes=_boxes(1)).slots[:, 0]
  assert np.abs(np.asarray(a - b)).max() > 1e-3
  # Videos of the batch with the same boxes start alike, whatever the other
  # video's boxes.
  mixed = jnp.concatenate([_boxes(0)[:1], _boxes(1)[1:]])
  c = model.apply(params, _video(), boxes=mixed).slots[:, 0]
  np.testing.assert_allclose(c[0], a[0], atol=1e-6)
  np.testing.assert_allclose(c[1], b[1], atol=1e-6)


def test_padding_and_absent_objects_are_zero_boxes():
  boxes = _boxes(3, rows=2)
  coords = conditioning_coordinates(boxes, 5, 'boxes')
  assert coords.shape == (2, 5, 4)
  np.testing.assert_array_equal(coords[:, 0], 0.0)  # background
  np.testing.assert_array_equal(coords[:, 1:3], boxes)
  np.testing.assert_array_equal(coords[:, 3:], 0.0)  # padding rows
  points = conditioning_coordinates(boxes, 5, 'points')
  np.testing.assert_allclose(
      points[:, 1:3], np.stack([(boxes[..., 0] + boxes[..., 2]) / 2,
                                (boxes[..., 1] + boxes[..., 3]) / 2], -1))
  # Fewer rows than slots - 1 is the same as padding them with zero boxes.
  model = _tiny_savi(initial_slots='boxes')
  params = _init(model, boxes)
  short, _ = model.apply(params, 2, boxes, method=SAVi.initial_carry)
  padded, _ = model.apply(params, 2,
                          jnp.concatenate([boxes, jnp.zeros((2, 1, 4))], 1),
                          method=SAVi.initial_carry)
  np.testing.assert_array_equal(short, padded)
  with pytest.raises(ValueError, match='4 box rows, 4 slots'):
    conditioning_coordinates(_boxes(0, rows=4), 4, 'boxes')


def test_conditional_savi_needs_boxes():
  model = _tiny_savi(initial_slots='boxes')
  params = _init(model, _boxes(0))
  with pytest.raises(ValueError, match="needs the first frame's boxes"):
    model.apply(params, _video())


def test_unconditional_savi_has_no_conditioning_parameters():
  """'learned' keeps its parameter tree and ignores boxes."""
  model = _tiny_savi()
  params = model.init({'params': jax.random.key(1),
                       'sample': jax.random.key(2)}, _video())
  assert 'slot_init_mlp' not in params['params']
  assert params['params']['initial_slots'].shape == (4, 16)
  plain = model.apply(params, _video()).slots
  with_boxes = model.apply(params, _video(), boxes=_boxes(0)).slots
  np.testing.assert_array_equal(plain, with_boxes)
  conditional = _tiny_savi(initial_slots='boxes')
  tree = _init(conditional, _boxes(0))['params']
  assert 'initial_slots' not in tree
  assert tree['slot_init_mlp']['hidden']['kernel'].shape == (4, 256)
  assert tree['slot_init_mlp']['out']['kernel'].shape == (256, 16)
