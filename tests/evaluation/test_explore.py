"""The run explorer's interventions: removing a slot from the decoder and
from SlotFormer's context, freezing one, and the batched jitted rollout."""

import base64
import errno
import io
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from explore_helpers import NUM_VIDEOS
from explore_helpers import micro_explorer
from pipeline_helpers import micro_config
from slotformer_jax import frames as frames_lib
from slotformer_jax import inference
from slotformer_jax import targets
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import explore
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.decoders import composite
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.modules.token_decoder import TokenDecoder
from slotformer_jax.slot_models import steve as steve_slots
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir.settings import accept_config


def _decoder_outputs():
  """A real decoder's per-slot rgb and alpha logits of random slots."""
  decoder = SpatialBroadcastDecoder(output_resolution=(8, 8),
                                    broadcast_resolution=(4, 4),
                                    features=(8, 8), kernel_size=3)
  slots = jax.random.normal(jax.random.key(0), (2, 4, 6))
  params = decoder.init(jax.random.key(1), slots)
  return decoder, params, slots


def test_removing_a_slot_whose_alpha_mask_is_zero_changes_nothing():
  decoder, params, slots = _decoder_outputs()
  decoded = decoder.apply(params, slots)
  rgb = decoded.rgb
  logits = jnp.log(decoded.alpha_masks)  # the logits, up to a constant
  # Slot 2's logits far below the others': its alpha is exactly 0.
  logits = logits.at[:, 2].set(-1e4)
  recon, alpha = composite(rgb, logits)
  assert float(jnp.max(alpha[:, 2])) == 0.0
  presence = jnp.array([True, True, False, True])
  removed_recon, removed_alpha = composite(rgb, logits, presence)
  np.testing.assert_array_equal(removed_recon, recon)
  np.testing.assert_array_equal(removed_alpha, alpha)
  # A slot that is visible does change the frame when removed.
  visible_removed, _ = composite(rgb, logits, jnp.array([False, True, True,
                                                         True]))
  assert float(jnp.max(jnp.abs(visible_removed - recon))) > 1e-3


def test_removing_all_but_one_slot_decodes_that_slot_alone():
  decoder, params, slots = _decoder_outputs()
  for k in range(slots.shape[1]):
    presence = jnp.arange(slots.shape[1]) == k
    decoded = decoder.apply(params, slots, presence)
    alone = decoder.apply(params, slots[:, k:k + 1])
    np.testing.assert_allclose(decoded.alpha_masks[:, k], 1.0)
    np.testing.assert_array_equal(
        np.delete(np.asarray(decoded.alpha_masks), k, axis=1), 0.0)
    np.testing.assert_allclose(decoded.recon, alone.recon, atol=1e-6)
    np.testing.assert_allclose(decoded.recon, decoded.rgb[:, k], atol=1e-6)


def test_removing_a_slot_decodes_as_the_other_slots_alone():
  decoder, params, slots = _decoder_outputs()
  presence = jnp.array([True, False, True, True])
  decoded = decoder.apply(params, slots, presence)
  others = decoder.apply(params, slots[:, np.array([0, 2, 3])])
  np.testing.assert_allclose(decoded.recon, others.recon, atol=1e-6)
  np.testing.assert_allclose(decoded.alpha_masks[:, np.array([0, 2, 3])],
                             others.alpha_masks, atol=1e-6)
  # Presence broadcasts over leading dims ([N] for slots [B, N, D]) too.
  np.testing.assert_array_equal(
      decoder.apply(params, slots, jnp.broadcast_to(presence, (2, 4))).recon,
      decoded.recon)


def test_steve_removing_a_slot_generates_from_the_other_slots_alone():
  decoder = TokenDecoder(vocab_size=16, num_tokens=6, dim=16, num_layers=2,
                         num_heads=2, dropout_rate=0.0)
  slots = jax.random.normal(jax.random.key(0), (2, 3, 16))
  params = decoder.init(jax.random.key(1), slots,
                        jnp.zeros((2, 6), jnp.int32))['params']
  presence = jnp.array([[True, False, True]] * 2)
  tokens, weights = steve_slots.generate_tokens(params, slots,
                                                decoder=decoder,
                                                presence=presence)
  alone_tokens, alone_weights = steve_slots.generate_tokens(
      params, slots[:, np.array([0, 2])], decoder=decoder)
  np.testing.assert_array_equal(tokens, alone_tokens)
  np.testing.assert_array_equal(weights[..., 1], 0.0)
  np.testing.assert_allclose(weights[..., np.array([0, 2])], alone_weights,
                             atol=1e-6)
  # All but one slot: every token attends to that slot only.
  _, only = steve_slots.generate_tokens(
      params, slots, decoder=decoder,
      presence=jnp.array([[False, True, False]] * 2))
  np.testing.assert_allclose(only[..., 1], 1.0)


def _slotformer():
  model = SlotFormer(burn_in=3, embed_dim=16, num_layers=2, num_heads=2,
                     mlp_size=32)
  history = jax.random.normal(jax.random.key(0), (2, 3, 4, 8))
  params = model.init(jax.random.key(1), history, 1)['params']
  return model, params, history


def test_slotformer_without_a_slot_predicts_as_from_the_others_alone():
  model, params, history = _slotformer()
  presence = jnp.array([[True, True, False, True], [False, True, True, True]])
  removed = model.apply({'params': params}, history, 4,
                        slot_presence=presence)
  for b, absent in enumerate((2, 0)):
    keep = np.array([n for n in range(4) if n != absent])
    alone = model.apply({'params': params}, history[b:b + 1, :, keep], 4)
    np.testing.assert_allclose(removed[b:b + 1, :, keep], alone, atol=1e-5)
  # Everyone present is the factual rollout.
  np.testing.assert_allclose(
      model.apply({'params': params}, history, 4,
                  slot_presence=jnp.ones((2, 4), bool)),
      model.apply({'params': params}, history, 4), atol=1e-6)


def test_slotformer_freezing_a_slot_holds_it_and_the_others_see_it():
  model, params, history = _slotformer()
  frozen = jnp.array([[False, True, False, False]] * 2)
  rollout = model.apply({'params': params}, history, 4, frozen=frozen)
  np.testing.assert_array_equal(
      rollout[:, :, 1], jnp.broadcast_to(history[:, -1:, 1], (2, 4, 8)))
  # The same rollout by hand: predict, overwrite slot 1, feed back.
  window = history
  for step in range(4):
    predicted = model.apply({'params': params}, window,
                            method=model.predict_next)
    predicted = predicted.at[:, 1].set(history[:, -1, 1])
    np.testing.assert_allclose(rollout[:, step], predicted, atol=1e-5)
    window = jnp.concatenate([window[:, 1:], predicted[:, None]], axis=1)
  factual = model.apply({'params': params}, history, 4)
  assert float(jnp.max(jnp.abs(factual[:, 1:, 0] - rollout[:, 1:, 0]))) > 1e-4


def test_intervention_masks_rows():
  presence, frozen = explore.intervention_masks(3)
  assert presence.shape == frozen.shape == (7, 3)
  assert presence[0].all() and not frozen[0].any()
  for k in range(3):
    assert list(presence[1 + k]) == [n != k for n in range(3)]
    assert not frozen[1 + k].any()
    assert presence[4 + k].all() and list(frozen[4 + k]) == [
        n == k for n in range(3)]


def test_explorer_is_jitted_once_per_shape_and_matches_the_rollouts(tmp_path):
  config, slot_model, explorer, args = micro_explorer(tmp_path)
  dynamics_params, slot_params, slots, video, segmentation = args
  out = jax.device_get(explorer(*args))
  assert explorer.trace_count == 1
  explorer(dynamics_params, slot_params, slots + 1.0, video, segmentation)
  assert explorer.trace_count == 1  # same shapes: no retrace
  explorer(dynamics_params, slot_params, slots[:1], video[:1],
           segmentation[:1])
  assert explorer.trace_count == 2  # one video: a new shape

  burn_in, rollout = config.slotformer.burn_in, config.evaluation.rollout_steps
  num_slots = slot_model.slot_shape[0]
  frames = burn_in + rollout
  height, width = config.data.resolution
  assert out['counterfactual'].shape == (NUM_VIDEOS, 2 * num_slots, frames,
                                         height, width, 3)
  # The factual row is the evaluation's rollout, decoded.
  future = inference.rollout_slots(dynamics_params['slotformer'],
                                   slots[:, :burn_in],
                                   model=explorer.intervened,
                                   num_steps=rollout)
  whole = jnp.concatenate([slots[:, :burn_in], future], axis=1)
  np.testing.assert_allclose(out['methods']['slotformer'],
                             slot_model.decode(slot_params, whole).recon,
                             atol=1e-5)
  # Remove slot k: its alpha mask is 0 in every frame, burn-in included.
  masks = out['counterfactual_masks']
  for k in range(num_slots):
    np.testing.assert_array_equal(masks[:, k, :, k], 0.0)
  # Freeze slot k: the burn-in frames are the factual ones, the rollout
  # differs (an untrained non-residual SlotFormer moves every slot).
  frozen = out['counterfactual'][:, num_slots:]
  factual = out['methods']['slotformer'][:, None]
  np.testing.assert_allclose(
      frozen[:, :, :burn_in],
      np.broadcast_to(factual[:, :, :burn_in], frozen[:, :, :burn_in].shape),
      atol=1e-6)
  assert np.abs(frozen[:, :, burn_in:] - factual[:, :, burn_in:]).max() > 1e-3
  for method in ('slotformer', 'slot_lstm', 'copy_last'):
    metrics = out['video_metrics'][method]
    assert metrics['psnr'].shape == metrics['fg_ari'].shape == (NUM_VIDEOS,
                                                                 rollout)


def _strip_pixels(uri):
  """A page strip's data URI -> uint8 [H, T * W, 3]."""
  data = base64.b64decode(uri.split(',', 1)[1])
  return np.asarray(Image.open(io.BytesIO(data)).convert('RGB'))


def test_a_savi_of_flow_and_depth_is_explored_as_its_targets(tmp_path):
  """A SAVi reconstructing flow + depth (no frames) gets a page: every
  method's flow (the primary picture: rollouts, slots, counterfactuals) and
  depth on the data's labelled grey scale, the data's flow and depth above,
  FG-ARI curves but no PSNR / SSIM of frames it does not decode."""
  config, slot_model, explorer, args = micro_explorer(
      tmp_path, targets=('flow', 'depth'))
  dynamics_params, slot_params, slots, video, segmentation = args
  out = jax.device_get(explorer(*args))
  burn_in, rollout = config.slotformer.burn_in, config.evaluation.rollout_steps
  height, width = config.data.resolution
  num_slots = slot_model.slot_shape[0]
  frames = burn_in + rollout
  future = inference.rollout_slots(dynamics_params['slotformer'],
                                   slots[:, :burn_in],
                                   model=explorer.intervened,
                                   num_steps=rollout)
  whole = jnp.concatenate([slots[:, :burn_in], future], axis=1)
  decoded = slot_model.decode(slot_params, whole)
  np.testing.assert_allclose(out['methods']['slotformer'],
                             decoded.targets['flow'], atol=1e-5)
  np.testing.assert_allclose(out['targets']['depth']['slotformer'],
                             decoded.targets['depth'], atol=1e-5)
  assert out['counterfactual'].shape == (NUM_VIDEOS, 2 * num_slots, frames,
                                         height, width, 3)
  assert set(out['video_metrics']['slotformer']) == {'fg_ari'}

  rng = np.random.default_rng(1)
  truth = {'flow': rng.uniform(-1, 1, (NUM_VIDEOS, frames, height, width,
                                       3)).astype(np.float32),
           'depth': rng.uniform(2.0, 3.0, (NUM_VIDEOS, frames, height, width,
                                           1)).astype(np.float32)}
  data = explore.page_data(
      out, video, list(range(NUM_VIDEOS)), slot_model=slot_model,
      title='flow and depth', burn_in=burn_in, rollout=rollout,
      split=config.evaluation.split, explore_config=config.explore,
      identity={}, curves=None, curves_note='', seconds=0.0,
      truth_targets=truth)
  low, high = (f'{x:.2g}' for x in targets.depth_range(truth['depth'][0]))
  scale = f'{low}..{high}'
  rows = data['videos'][0]['rows']
  assert [r['label'] for r in rows] == [
      'truth', 'flow', f'depth {scale}', 'SAVi masks', 'SlotFormer flow',
      f'SlotFormer depth {scale}', 'SlotFormer masks', 'Slot-LSTM flow',
      f'Slot-LSTM depth {scale}', 'copy-last flow', f'copy-last depth {scale}']
  assert data['slot_views'] == 'decoded flow x alpha'
  assert set(data['videos'][0]['curves']) == {'fg_ari'}
  by_key = {r['key']: _strip_pixels(r['strip']) for r in rows}
  # The data's depth on its own range: black at its nearest, white at its
  # farthest; its flow in SAVi's colours.
  depth = by_key['truth/depth']
  assert depth.shape == (height, frames * width, 3)
  assert depth.min() == 0 and depth.max() == 255
  expected_flow = frames_lib.to_uint8(targets.picture(
      targets.FLOW, np.concatenate(list(truth['flow'][0]), axis=1)))
  np.testing.assert_array_equal(by_key['truth/flow'], expected_flow)
  # The counterfactual rollouts are drawn as flow too.
  removed = data['videos'][0]['counterfactual']['remove'][0]
  expected = frames_lib.to_uint8(targets.picture(
      targets.FLOW, np.concatenate(list(out['counterfactual'][0, 0]),
                                   axis=1)))
  np.testing.assert_array_equal(_strip_pixels(removed['frames']), expected)
  explore.write_page(str(tmp_path), data)
  assert 'SlotFormer depth' in (tmp_path / 'index.html').read_text()


def test_explore_settings_never_make_a_workdir_stale(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  workdir = str(tmp_path / 'run')
  paths = Paths.of(workdir)
  before_explorer = config.to_dict()
  del before_explorer['explore']  # a workdir made before the explorer
  assert accept_config(before_explorer, paths) == []
  assert accept_config(config.to_dict(), paths) == []
  config.explore.num_videos = 3
  assert accept_config(config.to_dict(), paths) == []


def test_run_curves_only_from_the_same_models(tmp_path):
  path = str(tmp_path / 'eval' / 'metrics.json')
  labels = {'slotformer': 'SlotFormer', 'copy_last': 'copy-last'}
  identity = {'slotformer': {'run_id': 'a', 'step': 4}}
  curves, note = explore.run_curves(path, identity, labels)
  assert curves is None and '--mode=evaluate' in note
  os.makedirs(tmp_path / 'eval')
  rollout = {'slotformer': {'psnr': {'mean': 20.0, 'per_step': [21.0, None]}},
             'copy_last': {'psnr': {'mean': 19.0, 'per_step': [20.0, 18.0]}}}
  for saved_identity, expected in (
      ({'slotformer': {'run_id': 'b', 'step': 4}}, None),
      (identity, {'psnr': {'SlotFormer': [21.0, None],
                           'copy-last': [20.0, 18.0]}})):
    with open(tmp_path / 'eval' / 'metrics.json', 'w') as f:
      json.dump({'rollout': rollout, 'identity': saved_identity,
                 'protocol': {'num_videos': 2, 'split': 'test'}}, f)
    curves, note = explore.run_curves(path, identity, labels)
    assert curves == expected, note
  assert note == 'the run: eval/metrics.json, mean over 2 test videos'


@pytest.mark.parametrize('metrics', [
    [1, 2],                                             # not an object
    {'identity': 'SAME', 'rollout': [1]},                 # rollout a list
    {'identity': 'SAME', 'rollout': {'slotformer': 3}},   # a method a number
    {'identity': 'SAME', 'rollout': {'slotformer': {'psnr': {
        'per_step': ['x', {}]}}}},                        # steps not numbers
    {'identity': 'SAME', 'rollout': {'slotformer': {'psnr': {
        'per_step': [[[[1]]]]}}}},                        # nested
    {'identity': 'SAME', 'rollout': {'x' * 1000: {'psnr': {
        'per_step': [1.0]}}}},                            # a name too long
    {'identity': 'SAME', 'rollout': {}, 'protocol': [3]},  # protocol a list
    '[' * 100000 + ']' * 100000,                         # nested too deep
])
def test_run_curves_of_a_malformed_metrics_file_are_left_out(tmp_path,
                                                             metrics):
  """eval/metrics.json of a run folder someone shares can hold anything:
  the page then has no run curves and says why; before, each of these
  ended the stage in a traceback (or, for the protocol, a wrong note)."""
  identity = {'slotformer': {'run_id': 'a', 'step': 4}}
  os.makedirs(tmp_path / 'eval')
  if isinstance(metrics, dict):
    metrics = {**metrics, 'identity': identity}
  with open(tmp_path / 'eval' / 'metrics.json', 'w') as f:
    f.write(metrics if isinstance(metrics, str) else json.dumps(metrics))
  curves, note = explore.run_curves(
      str(tmp_path / 'eval' / 'metrics.json'), identity, {})
  if metrics == {'identity': identity, 'rollout': {}, 'protocol': [3]}:
    assert curves == {} and note.endswith('mean over the  videos'), note
  else:
    assert curves is None and 'not what --mode=evaluate writes' in note


@pytest.mark.parametrize('value', ['1' + '0' * 400, '-1' + '0' * 400, 'NaN',
                                   'Infinity', '1e400'],
                         ids=['10**400', '-10**400', 'nan', 'inf', '1e400'])
def test_a_number_too_large_for_a_float_is_left_out_as_nan_is(tmp_path,
                                                              value):
  """10**400 is valid JSON; before, the page ended in `OverflowError: int
  too large to convert to float` and a traceback. It is now a gap in the
  curve, as NaN and infinity are, and a num_videos that large is not
  printed."""
  identity = {'slotformer': {'run_id': 'a', 'step': 4}}
  os.makedirs(tmp_path / 'eval')
  text = json.dumps({
      'identity': identity, 'protocol': {'num_videos': 'VALUE',
                                         'split': 'test'},
      'rollout': {'slotformer': {'psnr': {'per_step': [1.5, 'VALUE']}}}})
  with open(tmp_path / 'eval' / 'metrics.json', 'w') as f:
    f.write(text.replace('"VALUE"', value))
  curves, note = explore.run_curves(
      str(tmp_path / 'eval' / 'metrics.json'), identity,
      {'slotformer': 'SlotFormer'})
  assert curves == {'psnr': {'SlotFormer': [1.5, None]}}, note
  assert note == 'the run: eval/metrics.json, mean over the test videos'


def test_a_full_disk_while_writing_the_page_is_one_line(tmp_path,
                                                        monkeypatch):
  """ENOSPC from the page's atomic write: one UserError line (main prints
  it), no half-written page. Before, the OSError ended the run in a
  traceback."""
  from slotformer_jax import files  # pylint: disable=g-import-not-at-top

  def full_disk_fsync(fd):
    raise OSError(errno.ENOSPC, 'No space left on device')
  monkeypatch.setattr(files.os, 'fsync', full_disk_fsync)
  directory = tmp_path / 'explore'
  directory.mkdir()
  data = {'title': 't', 'videos': []}
  with pytest.raises(UserError) as caught:
    explore.write_outputs(str(directory), data, {'savi': {}}, [0])
  message = str(caught.value)
  assert '\n' not in message and 'No space left on device' in message
  assert 're-run --mode=explore' in message
  assert sorted(os.listdir(directory)) == []


def _acting_characters(value):
  """The characters of every text and key of `value` that a page would act
  on (bidi overrides and other format characters, controls but newline)."""
  import unicodedata  # pylint: disable=g-import-not-at-top
  texts = []
  stack = [value]
  while stack:
    node = stack.pop()
    if isinstance(node, str):
      texts.append(node)
    elif isinstance(node, dict):
      texts.extend(k for k in node if isinstance(k, str))
      stack.extend(node.values())
    elif isinstance(node, list):
      stack.extend(node)
  return {c for t in texts for c in t
          if c != '\n' and unicodedata.category(c) in ('Cc', 'Cf', 'Zl', 'Zp')}


def test_names_from_the_metrics_file_reach_the_page_neutralised(tmp_path):
  """Issue 61, case 8: a split named 'test\u202e videos' showed as 'mean
  over 8 tesoediv test' (the override reversed the text on screen), and ESC
  reached the page's text nodes too."""
  identity = {'slotformer': {'run_id': 'a', 'step': 4}}
  os.makedirs(tmp_path / 'eval')
  with open(tmp_path / 'eval' / 'metrics.json', 'w') as f:
    json.dump({'identity': identity,
               'protocol': {'num_videos': 8, 'split': 'test\u202e videos'},
               'rollout': {'slotformer': {'ps\x1bnr': {'per_step': [1.5]}},
                           'copy\u2067last': {'psnr': {'per_step': [2.0]}}}},
              f)
  curves, note = explore.run_curves(
      str(tmp_path / 'eval' / 'metrics.json'), identity,
      {'slotformer': 'SlotFormer'})
  assert curves and '\u202e' in note  # what the file holds reaches the page
  path = explore.write_page(str(tmp_path), {
      'title': 'run \u202etitle', 'run_curves': curves,
      'run_curves_note': note, 'identity': {'slot\x1b[2J': 'a\u200fb'}})
  with open(path, encoding='utf-8') as f:
    page = f.read()
  blob = page.split('type="application/json">', 1)[1].split('</script>', 1)[0]
  data = json.loads(blob)
  assert not _acting_characters(data), _acting_characters(data)
  assert not {c for c in page if c in '\u202e\u2067\u200f\x1b'}
  assert data['run_curves_note'].endswith(
      'mean over 8 test\\u202e videos videos')
  assert set(data['run_curves']) == {'ps\\x1bnr', 'psnr'}
  assert 'copy\\u2067last' in data['run_curves']['psnr']
  assert data['title'] == 'run \\u202etitle'
