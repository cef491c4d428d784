"""SAVi as a composition: swappable parts, no decoder, STEVE on SAVi's loop."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.modules.savi import FrameStep
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.slot_init import GaussianSlots
from slotformer_jax.modules.slot_init import LearnedSlots
from slotformer_jax.modules.steve import STEVE
from slotformer_jax.modules.transitions import ResidualMLPTransition
from tiny_models import tiny_steve


class FeatureDecoder(nn.Module):
  """A test-only decoder: slots [..., N, D] -> features [..., N, 5]."""

  @nn.compact
  def __call__(self, slots):
    return nn.Dense(5)(slots)


def _parts_savi(decoder=None, initializer=None):
  return SAVi(
      encoder=CNNEncoder(features=(8,), kernel_size=3, strides=(2,),
                         output_size=16),
      initializer=initializer or LearnedSlots(num_slots=3, slot_size=16),
      frame_step=FrameStep(corrector=SlotAttention(2, 16),
                           predictor=ResidualMLPTransition(mlp_size=32)),
      decoder=decoder)


def _video(time=3):
  return jax.random.uniform(jax.random.key(0), (2, time, 8, 8, 3),
                            minval=-1.0, maxval=1.0)


def test_savi_without_a_decoder_returns_slots_only():
  model = _parts_savi()
  variables = model.init(jax.random.key(1), _video())
  assert set(variables['params']) == {'encoder', 'initial_slots',
                                      'frame_step'}
  output = model.apply(variables, _video())
  assert output.decoded is None
  assert output.slots.shape == (2, 3, 3, 16)
  np.testing.assert_array_equal(output.kl, 0.0)
  with pytest.raises(ValueError, match='no decoder'):
    model.apply(variables, output.slots, method=SAVi.decode)


def test_savi_with_another_decoder():
  model = _parts_savi(decoder=FeatureDecoder())
  variables = model.init(jax.random.key(1), _video())
  assert variables['params']['decoder']['Dense_0']['kernel'].shape == (16, 5)
  output = model.apply(variables, _video())
  assert output.decoded.shape == (2, 3, 3, 5)


def test_frame_outputs_keep_the_attention_only_when_asked():
  model = _parts_savi()
  variables = model.init(jax.random.key(1), _video())
  frames, _ = model.apply(variables, _video(), method=SAVi.encode_frames)
  assert frames.attention is None
  with_masks = model.clone(frame_step=model.frame_step.clone(
      corrector=SlotAttention(2, 16, return_attention=True)))
  frames_b, _ = with_masks.apply(variables, _video(),
                                 method=SAVi.encode_frames)
  np.testing.assert_array_equal(frames_b.slots, frames.slots)
  assert frames_b.attention.shape == (2, 3, 3, 16)  # 4x4 features
  np.testing.assert_allclose(frames_b.attention.sum(2), 1.0, rtol=1e-5)


def test_gaussian_initial_slots_draw_from_the_sample_rng():
  model = _parts_savi(initializer=GaussianSlots(num_slots=3, slot_size=16))
  variables = model.init({'params': jax.random.key(1),
                          'sample': jax.random.key(2)}, _video())
  assert set(variables['params']) == {
      'encoder', 'initial_slots_mean', 'initial_slots_log_sigma',
      'frame_step'}
  draw = lambda seed: model.apply(variables, 2, method=SAVi.initial_carry,
                                  rngs={'sample': jax.random.key(seed)})[0]
  assert draw(3).shape == (2, 3, 16)
  np.testing.assert_array_equal(draw(3), draw(3))
  assert not np.allclose(draw(3), draw(4))


def test_steve_runs_savis_time_loop_on_the_same_parameters():
  """STEVE's slots and masks are SAVi's time loop over the same parts (a
  SAVi without a decoder) on STEVE's own parameters minus the token
  decoder; and its parts start from the same values, since they sit in
  STEVE's scope under the same names (a SAVi nested under
  `nn.share_scope` kept the names but drew other initial values)."""
  model = tiny_steve()
  savi = SAVi(encoder=model.encoder, initializer=model.initializer,
              frame_step=model.frame_step, decoder=None)
  video = jax.random.uniform(jax.random.key(0), (2, 3, 16, 16, 3),
                             minval=-1.0, maxval=1.0)
  tokens = jnp.zeros((2, 3, 16), jnp.int32)
  params = model.init(jax.random.key(1), video, tokens)['params']
  encoder_params = {k: v for k, v in params.items() if k != 'decoder'}
  jax.tree.map(np.testing.assert_array_equal, encoder_params,
               savi.init(jax.random.key(1), video)['params'])
  slots, masks, carry = model.apply({'params': params}, video,
                                    method=STEVE.encode)
  frames, savi_carry = savi.apply(
      {'params': encoder_params}, video, method=SAVi.encode_frames)
  np.testing.assert_array_equal(slots, frames.slots)
  np.testing.assert_array_equal(masks.reshape(frames.attention.shape),
                                frames.attention)
  assert masks.shape == (2, 3, 3, *model.feature_grid)
  jax.tree.map(np.testing.assert_array_equal, carry, savi_carry)
