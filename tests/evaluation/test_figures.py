"""The appendix attention analysis and the per-step figure."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax.evaluation import visualize
from slotformer_jax.modules.slotformer import SlotFormer


def test_last_layer_attention_is_a_distribution_over_burn_in_slots():
  model = SlotFormer(burn_in=3, embed_dim=16, num_layers=2, num_heads=2,
                     mlp_size=32)
  history = jax.random.normal(jax.random.key(0), (2, 3, 4, 8))
  params = model.init(jax.random.key(1), history, 1)['params']
  attention = visualize.last_layer_attention(params, history, model=model)
  assert attention.shape == (2, 4, 3, 4)
  np.testing.assert_allclose(attention.sum(axis=(2, 3)), 1.0, atol=1e-5)
  # Equivariance: permuting the input slots permutes both slot axes.
  permutation = jnp.array([2, 0, 3, 1])
  permuted = visualize.last_layer_attention(
      params, history[:, :, permutation], model=model)
  np.testing.assert_allclose(
      permuted, attention[:, permutation][..., permutation], atol=1e-5)


def test_attention_maps_match_the_paper_formula():
  rng = np.random.default_rng(0)
  attention = rng.random((1, 2, 3, 2))  # [B, N, T, N]
  rgb = rng.random((1, 3, 2, 4, 5, 3))  # [B, T, N, H, W, 3]
  alpha = rng.random((1, 3, 2, 4, 5, 1))
  maps = np.asarray(visualize.attention_maps(attention, rgb, alpha))
  assert maps.shape == (1, 2, 3, 4, 5, 3)
  for i in range(2):
    for t in range(3):
      expected = sum(attention[0, i, t, j] * alpha[0, t, j] * rgb[0, t, j]
                     for j in range(2))
      np.testing.assert_allclose(maps[0, i, t], expected, rtol=1e-5)


def test_per_step_figure_from_metrics_json(tmp_path):
  workdir = str(tmp_path)
  metrics = os.path.join(workdir, 'eval', 'metrics.json')
  render = os.path.join(workdir, 'render')
  labels = {'slotformer': 'SlotFormer', 'copy_last': 'copy-last'}
  figure = lambda: visualize.write_per_step_figure(
      metrics, render, labels, 'savi_reconstruction')
  assert figure() is None  # not evaluated
  os.makedirs(tmp_path / 'eval')
  rollout = {
      'slotformer': {'psnr': {'mean': 30.0, 'per_step': [31.0, 30.0, 29.0]},
                     'fg_miou': {'mean': 0.5, 'per_step': [0.6, 0.5, None]}},
      'copy_last': {'psnr': {'mean': 25.0, 'per_step': [27.0, 25.0, 23.0]}},
  }
  with open(tmp_path / 'eval' / 'metrics.json', 'w') as f:
    json.dump({'rollout': rollout}, f)
  path = figure()
  assert path == os.path.join(workdir, 'render', 'per_step.png')
  assert os.path.getsize(path) > 1000
