"""SAVi's reconstruction targets (`config.savi.targets`, slotformer_jax/
targets.py): RGB (the default) bit for bit as before, flow and depth with
their own readout heads and loss terms, L_I on the same targets, the
pictures of each target, and the data contract's colouring of flow."""

import colorsys
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from slotformer_jax import losses
from slotformer_jax import targets as targets_lib
from slotformer_jax.config import checks
from slotformer_jax.config.defaults import base_config
from slotformer_jax.errors import ConfigError
from slotformer_jax.frames import GRID_LABEL_WIDTH
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import to_uint8
from slotformer_jax.modules import convolution
from slotformer_jax.modules.decoders import PointwiseConv
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.decoders import SubPixelConvTranspose
from slotformer_jax.modules.encoders import SoftPositionEmbedding
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.train import steps
from slotformer_jax.workdir import identity as identity_lib
from tiny_models import RESOLUTION
from tiny_models import savi_section
from tiny_models import tiny_savi

FLOW_DEPTH = ('flow', 'depth')


class DecoderBeforeTargets(nn.Module):
  """SpatialBroadcastDecoder as it was before targets existed (its
  `__call__` and compositing, kept here as the reference)."""

  output_resolution: tuple[int, int]
  broadcast_resolution: tuple[int, int]
  features: tuple[int, ...]
  kernel_size: int

  @nn.compact
  def __call__(self, slots, presence=None):
    *batch_shape, num_slots, slot_size = slots.shape
    height, width = self.broadcast_resolution
    x = slots.reshape(-1, 1, 1, slot_size)
    x = jnp.broadcast_to(x, (x.shape[0], height, width, slot_size))
    x = SoftPositionEmbedding(name='position_embedding')(x)
    for i, channels in enumerate(self.features):
      if x.shape[1] < self.output_resolution[0]:
        x = SubPixelConvTranspose(channels, self.kernel_size, stride=2,
                                  name=f'deconv_{i}')(x)
      else:
        x = convolution.SameConv(channels, self.kernel_size,
                                 name=f'deconv_{i}')(x)
      x = nn.relu(x)
    x = PointwiseConv(4, name='readout')(x)
    x = x.reshape(*batch_shape, num_slots, *x.shape[1:])
    rgb, alpha_logits = x[..., :3], x[..., 3:]
    if presence is not None:
      lowest = jnp.finfo(alpha_logits.dtype).min
      alpha_logits = jnp.where(presence[..., None, None, None], alpha_logits,
                               lowest)
    alpha_masks = jax.nn.softmax(alpha_logits, axis=-4)
    recon = jnp.sum(rgb * alpha_masks, axis=-4)
    segmentation = jnp.argmax(alpha_masks[..., 0], axis=-3).astype(jnp.int32)
    return recon, rgb, alpha_masks, segmentation


_DECODER = dict(output_resolution=RESOLUTION, broadcast_resolution=(4, 4),
                features=(8, 8, 8), kernel_size=3)


def _slots(shape=(2, 3, 4, 10), seed=0):
  return jax.random.normal(jax.random.key(seed), shape)


def _data(batch=2, time=2, seed=0):
  """A batch with every target's field, as the data contract says."""
  rng = np.random.default_rng(seed)
  flow = rng.normal(scale=3.0, size=(batch, time, *RESOLUTION, 2))
  depth = rng.uniform(0.5, 20.0, size=(batch, time, *RESOLUTION, 1))
  return {
      'video': rng.integers(0, 256, (batch, time, *RESOLUTION, 3), np.uint8),
      'flow': targets_lib.flow_to_rgb(flow),
      'depth': targets_lib.log_plus_depth(depth)}


# ---- RGB: today's decoder and losses, bit for bit --------------------------


@pytest.mark.parametrize('with_presence', [False, True])
def test_rgb_decoder_is_the_decoder_before_targets_bit_for_bit(with_presence):
  before = DecoderBeforeTargets(**_DECODER)
  after = SpatialBroadcastDecoder(**_DECODER)
  slots = _slots()
  presence = (jnp.array([True, False, True, True]) if with_presence
              else None)
  params = before.init(jax.random.key(1), slots)
  assert (jax.tree_util.tree_structure(params)
          == jax.tree_util.tree_structure(
              after.init(jax.random.key(1), slots)))
  recon, rgb, alpha, segmentation = before.apply(params, slots, presence)
  decoded = after.apply(params, slots, presence)
  for got, expected in ((decoded.recon, recon), (decoded.rgb, rgb),
                        (decoded.alpha_masks, alpha),
                        (decoded.segmentation, segmentation)):
    np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))
  assert decoded.targets is None
  assert list(decoded.reconstructions()) == ['rgb']


def _savi_loss_before(params, batch, frozen_params, rng, *, model, kl_weight):
  """losses.savi_loss as it was before targets existed."""
  del frozen_params
  video = frames_to_model(batch['video'])
  sample_rng, dropout_rng = jax.random.split(rng)
  output = model.apply({'params': params}, video, deterministic=False,
                       rngs={'sample': sample_rng, 'dropout': dropout_rng})
  recon_loss = jnp.mean(jnp.square(output.decoded.recon - video))
  kl = jnp.mean(output.kl)
  return recon_loss + kl_weight * kl, {'recon_loss': recon_loss, 'kl': kl}


def test_rgb_savi_loss_and_gradients_are_those_before_targets():
  model = tiny_savi(stochastic=True, posterior_head='mlp')
  batch = {'video': _data()['video']}
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, 2, *RESOLUTION, 3)))
  rng = jax.random.key(3)

  def run(loss_fn):
    fn = jax.jit(jax.value_and_grad(
        functools.partial(loss_fn, model=model, kl_weight=1e-3),
        has_aux=True))
    return fn(params, batch, None, rng)

  (loss, metrics), grads = run(losses.savi_loss)
  (loss_before, metrics_before), grads_before = run(_savi_loss_before)
  assert set(metrics) == set(metrics_before) == {'recon_loss', 'kl'}
  np.testing.assert_array_equal(loss, loss_before)
  for key in metrics:
    np.testing.assert_array_equal(metrics[key], metrics_before[key])
  jax.tree_util.tree_map(np.testing.assert_array_equal, grads, grads_before)


def _slotformer():
  return SlotFormer(burn_in=2, embed_dim=16, num_layers=1, num_heads=2,
                    mlp_size=32, dropout_rate=0.0)


def _image_loss_setup(targets):
  model = _slotformer()
  decoder = SpatialBroadcastDecoder(
      **_DECODER, targets=targets_lib.channels(targets))
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, 2, 3, 16)), 2)
  decoder_params = decoder.init(jax.random.key(1),
                                jnp.zeros((1, 3, 16)))['params']
  batch = {'slots': np.random.default_rng(2).normal(
      size=(2, 4, 3, 16)).astype(np.float32), **_data(time=4)}
  return model, decoder, params, decoder_params, batch


def test_rgb_image_loss_is_the_one_before_targets():
  model, decoder, params, decoder_params, batch = _image_loss_setup(('rgb',))
  rng = jax.random.key(4)
  loss, metrics = losses.slotformer_loss(
      params, batch, decoder_params, rng, model=model, decoder=decoder,
      rollout=2,
      weights={'slot_loss': 1.0, 'image_loss': 0.5},
      teacher_forcing=False)
  predicted = model.apply({'params': params}, batch['slots'][:, :2], 2,
                          deterministic=False, rngs={'dropout': rng})
  slot_loss = jnp.mean(jnp.square(predicted - batch['slots'][:, 2:]))
  frames = frames_to_model(batch['video'][:, -2:])
  recon = decoder.apply({'params': decoder_params}, predicted).recon
  image_loss = jnp.mean(jnp.square(recon - frames))
  assert list(metrics) == ['slot_loss', 'image_loss']
  np.testing.assert_array_equal(metrics['image_loss'], image_loss)
  np.testing.assert_array_equal(loss, slot_loss + 0.5 * image_loss)


# ---- flow and depth ----------------------------------------------------------


def test_flow_depth_decoder_has_a_head_per_target_and_shared_masks():
  decoder = SpatialBroadcastDecoder(**_DECODER,
                                    targets=targets_lib.channels(FLOW_DEPTH))
  slots = _slots()
  params = decoder.init(jax.random.key(1), slots)['params']
  # The first target shares `readout` with the alpha logit; depth has its own.
  assert params['readout']['kernel'].shape == (1, 1, 8, 3 + 1)
  assert params['readout_depth']['kernel'].shape == (1, 1, 8, 1)
  decoded = decoder.apply({'params': params}, slots)
  assert decoded.recon is None and decoded.rgb is None
  assert decoded.targets['flow'].shape == (2, 3, *RESOLUTION, 3)
  assert decoded.targets['depth'].shape == (2, 3, *RESOLUTION, 1)
  assert decoded.alpha_masks.shape == (2, 3, 4, *RESOLUTION, 1)
  assert list(decoded.reconstructions()) == ['flow', 'depth']
  # A decoder of flow alone has the RGB decoder's tree and shapes.
  flow_only = SpatialBroadcastDecoder(**_DECODER,
                                      targets=targets_lib.channels(('flow',)))
  assert (jax.tree_util.tree_map(jnp.shape, flow_only.init(
      jax.random.key(1), slots)) == jax.tree_util.tree_map(
          jnp.shape, SpatialBroadcastDecoder(**_DECODER).init(
              jax.random.key(1), slots)))


def test_decoder_refuses_bad_targets():
  for targets in ((), (('flow', 3), ('flow', 3)), (('depth', 0),)):
    with pytest.raises(ValueError, match='targets'):
      SpatialBroadcastDecoder(**_DECODER, targets=targets).init(
          jax.random.key(0), _slots())


def test_flow_depth_savi_loss_one_term_per_target_and_every_head_learns():
  model = tiny_savi(targets=FLOW_DEPTH)
  batch = _data()
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, 2, *RESOLUTION, 3)))
  loss_fn = functools.partial(losses.savi_loss, model=model, kl_weight=0.0)
  loss, metrics = jax.jit(loss_fn)(params, batch, None, jax.random.key(1))
  assert set(metrics) == {'recon_loss', 'recon_loss_flow',
                          'recon_loss_depth', 'kl'}
  # The MSE over every target channel: flow weighs 3, depth 1 (SAVi's
  # relative weights).
  np.testing.assert_allclose(
      metrics['recon_loss'],
      (3 * metrics['recon_loss_flow'] + metrics['recon_loss_depth']) / 4,
      rtol=1e-6)
  np.testing.assert_allclose(loss, metrics['recon_loss'], rtol=1e-6)

  def terms(p):
    metrics = loss_fn(p, batch, None, jax.random.key(1))[1]
    return jnp.stack([metrics['recon_loss_flow'], metrics['recon_loss_depth']])

  grads = jax.jit(jax.jacrev(terms))(params)['decoder']
  flow_grads = jax.tree_util.tree_map(lambda g: g[0], grads)
  depth_grads = jax.tree_util.tree_map(lambda g: g[1], grads)
  # The flow term trains the flow columns of `readout` (and the alpha
  # column) but not the depth head; the depth term the depth head.
  assert np.abs(flow_grads['readout']['kernel'][..., :3]).sum() > 0
  assert np.abs(flow_grads['readout_depth']['kernel']).sum() == 0
  assert np.abs(depth_grads['readout_depth']['kernel']).sum() > 0
  assert np.abs(depth_grads['readout']['kernel'][..., :3]).sum() == 0
  assert np.abs(depth_grads['readout']['kernel'][..., 3]).sum() > 0
  # Both reach the encoder through the shared slots.
  for grads in (flow_grads, depth_grads):
    assert np.abs(grads['deconv_0']['kernel']).sum() > 0


def test_image_loss_with_several_targets():
  model, decoder, params, decoder_params, batch = _image_loss_setup(
      ('rgb',) + FLOW_DEPTH)
  rng = jax.random.key(4)
  loss_fn = functools.partial(
      losses.slotformer_loss, model=model, decoder=decoder, rollout=2,
      weights={'slot_loss': 1.0, 'image_loss': 1.0}, teacher_forcing=False)
  loss, metrics = loss_fn(params, batch, decoder_params, rng)
  assert set(metrics) == {'slot_loss', 'image_loss', 'image_loss_rgb',
                          'image_loss_flow', 'image_loss_depth'}
  predicted = model.apply({'params': params}, batch['slots'][:, :2], 2,
                          deterministic=False, rngs={'dropout': rng})
  decoded = decoder.apply({'params': decoder_params}, predicted)
  expected = {
      'rgb': jnp.mean(jnp.square(
          decoded.recon - frames_to_model(batch['video'][:, -2:]))),
      'flow': jnp.mean(jnp.square(decoded.targets['flow']
                                  - batch['flow'][:, -2:])),
      'depth': jnp.mean(jnp.square(decoded.targets['depth']
                                   - batch['depth'][:, -2:]))}
  for name, value in expected.items():
    np.testing.assert_allclose(metrics[f'image_loss_{name}'], value,
                               rtol=1e-5)
  np.testing.assert_allclose(
      metrics['image_loss'],
      (3 * expected['rgb'] + 3 * expected['flow'] + expected['depth']) / 7,
      rtol=1e-5)
  np.testing.assert_allclose(loss, metrics['slot_loss']
                             + metrics['image_loss'], rtol=1e-6)
  # The dynamics model learns from every term; the decoder stays frozen.
  grads = jax.grad(lambda p: loss_fn(p, batch, decoder_params, rng)[0])(params)
  assert sum(np.abs(g).sum() for g in jax.tree_util.tree_leaves(grads)) > 0
  # Without the frames in the batch, only the other targets are read.
  model, decoder, params, decoder_params, batch = _image_loss_setup(
      FLOW_DEPTH)
  del batch['video']
  _, metrics = losses.slotformer_loss(
      params, batch, decoder_params, rng, model=model, decoder=decoder,
      rollout=2,
      weights={'slot_loss': 1.0, 'image_loss': 1.0},
      teacher_forcing=False)
  assert set(metrics) == {'slot_loss', 'image_loss', 'image_loss_flow',
                          'image_loss_depth'}


# ---- the slot model -------------------------------------------------------


def _config(**savi_updates):
  config = base_config()
  config.data.resolution = RESOLUTION
  config.savi = savi_section(**savi_updates)
  return config


def test_slot_model_fields_identity_and_decoding_per_targets():
  rgb = savi_slots.Savi(_config())
  flow = savi_slots.Savi(_config(targets=('flow',)))
  # RGB: model_config.json and the identity as before the field existed.
  assert 'targets' not in rgb.parts[0].model_fields
  assert 'targets' not in rgb.parts[0].identity_fields['savi']
  for fields in (rgb.parts[0].model_fields['encoder'],
                 rgb.parts[0].identity_fields['savi']['encoder']):
    assert not {'kind', 'mlp_size', 'transformer'} & set(fields)
  assert flow.parts[0].model_fields['targets'] == ['flow']
  assert flow.parts[0].identity_fields['savi']['targets'] == ['flow']
  # An identity made before the field reads as RGB, not as a change.
  old = rgb.parts[0].identity_fields
  assert not identity_lib.flat_differences(
      old, identity_lib.stage_fields(
          0, _config().data.to_dict(), 'savi', _config().savi.to_dict()))
  assert identity_lib.flat_differences(old, flow.parts[0].identity_fields)
  assert rgb.decodes_pixels and not flow.decodes_pixels
  assert rgb.image_loss_fields == ('video',)
  assert flow.image_loss_fields == ('flow',)
  assert flow.parts[0].batch_fields == ('video', 'flow')

  params = {'savi': flow.parts[0].module.init(
      jax.random.key(0), *flow.parts[0].example)['params']}
  decoded = flow.decode(params, _slots((2, 3, 16)))
  assert decoded.recon is None and decoded.rgb is None
  assert decoded.targets['flow'].shape == (2, *RESOLUTION, 3)
  slots = _slots((1, 2, 3, 16))
  alpha, recon, _ = flow.observe(params, slots, _data(1)['video'], None)
  assert recon is None and alpha.shape == (1, 2, 3, *RESOLUTION)


def test_a_config_without_the_new_fields_builds_todays_model():
  section = savi_section()
  old = section.to_dict()
  del old['targets']
  for key in ('kind', 'mlp_size', 'transformer'):
    del old['encoder'][key]
  shapes = lambda model: jax.tree_util.tree_map(jnp.shape, jax.eval_shape(
      model.init, jax.random.key(0), jnp.zeros((1, 2, *RESOLUTION, 3))))
  assert shapes(savi_slots.build_savi(ml_collections.ConfigDict(old),
                                      RESOLUTION)) == shapes(
      savi_slots.build_savi(section, RESOLUTION))


def test_target_settings_are_checked_in_one_line():
  config = _config()
  config.savi.targets = ('flow', 'flow')
  assert checks.choice_problems(config, ['savi.targets']) == [
      "savi.targets=('flow', 'flow'): each must be one of 'rgb', 'flow', "
      "'depth', once"]
  config.savi.targets = ('optical_flow',)
  assert checks.choice_problems(config, ['savi.targets'])
  config.savi.targets = ('depth', 'flow')
  assert not checks.choice_problems(config, ['savi.targets'])
  config.savi.targets = ()
  problems = savi_slots.Savi(config).check_config(frozenset())
  assert len(problems) == 1 and 'names no target' in problems[0]


def test_data_without_a_target_field_is_one_line():
  model = savi_slots.Savi(_config(targets=FLOW_DEPTH))
  source = [{'video': _data(1)['video'][0], 'flow': _data(1)['flow'][0]}]
  with pytest.raises(ConfigError, match=r"reconstructs 'depth', but the "
                     r"train videos .* have no such field"):
    model.check_data(source, 'train')
  source[0]['depth'] = _data(1)['depth'][0]
  model.check_data(source, 'train')


def _picture_rows(grid, num_rows):
  height = grid.shape[0] // num_rows
  return [grid[i * height:(i + 1) * height, GRID_LABEL_WIDTH:]
          for i in range(num_rows)]


def test_training_pictures_show_each_target():
  batch = _data(1)
  rgb = savi_slots.Savi(_config()).parts[0]
  both = savi_slots.Savi(_config(targets=('rgb',) + FLOW_DEPTH)).parts[0]
  grids = {}
  for name, part in (('rgb', rgb), ('both', both)):
    params = part.module.init(jax.random.key(0), *part.example)['params']
    grids[name] = part.images(params, batch)['reconstruction']
  # input, reconstruction, slot masks; + flow, its reconstruction, depth,
  # its reconstruction.
  assert grids['rgb'].shape[0] == 3 * 2 * RESOLUTION[0]
  assert grids['both'].shape[0] == 7 * 2 * RESOLUTION[0]
  rows = _picture_rows(grids['both'], 7)
  np.testing.assert_array_equal(rows[0], _picture_rows(grids['rgb'], 3)[0])
  frames = lambda x: np.concatenate(list(
      x.repeat(2, axis=1).repeat(2, axis=2)), axis=1)
  np.testing.assert_array_equal(rows[2], frames(to_uint8(
      targets_lib.picture(targets_lib.FLOW, batch['flow'][0]))))
  np.testing.assert_array_equal(rows[4], frames(to_uint8(
      targets_lib.picture(targets_lib.DEPTH, batch['depth'][0]))))
  # Depth is grey, and the label carries its scale.
  assert (rows[4][..., 0] == rows[4][..., 1]).all()
  labels = list(targets_lib.picture_rows(
      targets_lib.of(FLOW_DEPTH), {'depth': np.array([[0.5], [2.0]])},
      {'flow': np.zeros((1, 1, 3)), 'depth': np.ones((2, 1))}))
  assert labels == ['flow recon.', 'depth 0.5..2', 'depth recon.']


# ---- the data contract's helpers --------------------------------------------


def test_flow_to_rgb_is_savis_colour_wheel():
  rng = np.random.default_rng(0)
  flow = rng.normal(scale=2.0, size=(2, 8, 6, 2)).astype(np.float32)
  flow[0, 0, 0] = 0.0
  got = targets_lib.flow_to_rgb(flow)
  assert got.shape == (2, 8, 6, 3) and got.dtype == np.float32
  assert got.min() >= -1.0 and got.max() <= 1.0
  np.testing.assert_array_equal(got[0, 0, 0], [1.0, 1.0, 1.0])  # still: white
  scale = targets_lib.FLOW_SCALING / np.hypot(8, 6)
  for index in np.ndindex(flow.shape[:-1]):
    first, second = flow[index]
    hue = (np.arctan2(second, first) / np.pi + 1.0) / 2.0
    saturation = min(np.hypot(first, second) * scale, 1.0)
    expected = np.array(colorsys.hsv_to_rgb(hue, saturation, 1.0)) * 2 - 1
    np.testing.assert_allclose(got[index], expected, atol=1e-5)


def test_log_plus_depth():
  depth = np.array([0.0, 1.0, np.e - 1.0, 100.0])
  np.testing.assert_allclose(targets_lib.log_plus_depth(depth),
                             np.log(1.0 + depth), rtol=1e-6)


def test_targets_of():
  assert targets_lib.of(None) == (targets_lib.RGB,)
  assert [t.field for t in targets_lib.of(FLOW_DEPTH)] == ['flow', 'depth']
  for bad in ((), ('rgb', 'rgb'), ('normals',)):
    with pytest.raises(ValueError, match='targets'):
      targets_lib.of(bad)
