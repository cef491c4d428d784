"""evaluation.skip_first_frame: the slot model's whole-video metrics with or
without frame 0 (SAVi's MOVi convention), against sklearn."""

import jax
import jax.numpy as jnp

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

from slotformer_jax.config.defaults import base_config
from slotformer_jax.errors import ConfigError
from slotformer_jax.evaluation import evaluate
from slotformer_jax.runtime import sharding
from slotformer_jax.workdir.identity import ADDED_FIELDS

NUM_SLOTS, T, H, W = 3, 5, 6, 6


class _IdSlotModel:
  """A slot model whose 'slots' are the predicted id of every pixel: alpha
  masks are their one-hot (so the evaluation sees exactly those ids)."""

  name = 'fake'
  label = 'fake'
  reference_method = 'fake_reconstruction'
  slot_shape = (NUM_SLOTS, H * W)
  mask_source = 'ids'

  def decode(self, params, slots):
    raise NotImplementedError

  def observe(self, params, slots, video, carry):
    del params, video
    ids = jnp.argmax(slots, axis=-2).reshape(*slots.shape[:2], H, W)
    alpha = jax.nn.one_hot(ids, NUM_SLOTS, axis=2)  # [B, T, N, H, W]
    return alpha, None, carry


def _videos(rng, count):
  videos = []
  for _ in range(count):
    true = rng.integers(0, 3, size=(T, H, W)).astype(np.uint8)
    pred = rng.integers(0, NUM_SLOTS, size=(T, H, W))
    # Frame 0 predicted perfectly, the rest at random: skipping it matters.
    pred[0] = true[0]
    slots = np.eye(NUM_SLOTS, dtype=np.float32)[pred.reshape(T, -1)]
    videos.append({'slots': np.swapaxes(slots, 1, 2),  # [T, N, H*W]
                   'video': np.zeros((T, H, W, 3), np.uint8),
                   'segmentations': true, 'pred': pred})
  return videos


def _fg_ari(video, first):
  true = video['segmentations'][first:].ravel()
  pred = video['pred'][first:].ravel()
  foreground = true > 0
  return adjusted_rand_score(true[foreground], pred[foreground])


NUM_TRUE = 3  # ids 0 (background), 1, 2


def _config(skip):
  """The evaluation section (the defaults', 2-frame chunks)."""
  evaluation = base_config().evaluation
  evaluation.chunk_length = 2
  evaluation.skip_first_frame = skip
  return evaluation


@pytest.mark.parametrize('skip', [False, True])
def test_fg_ari_over_the_frames_of_the_convention(skip):
  videos = _videos(np.random.default_rng(0), 5)
  mesh = sharding.make_mesh()
  results = evaluate.evaluate_slot_model(
      _config(skip), NUM_TRUE, mesh, _IdSlotModel(), {}, videos, T,
      batch_size=4, fields=('slots', 'video', 'segmentations'))
  first = 1 if skip else 0
  expected = np.mean([_fg_ari(v, first) for v in videos])
  np.testing.assert_allclose(results['fg_ari'], expected, rtol=1e-5)
  assert results['num_videos'] == 5 and results['num_frames'] == T
  # Per-frame FG-ARI: the mean over exactly the kept frames.
  per_frame = [adjusted_rand_score(
      v['segmentations'][t][v['segmentations'][t] > 0],
      v['pred'][t][v['segmentations'][t] > 0])
               for v in videos for t in range(first, T)]
  np.testing.assert_allclose(results['fg_ari_per_frame'], np.mean(per_frame),
                             rtol=1e-5)


def test_default_is_every_frame():
  """The default (and a workdir's config from before the field, read with
  it: workdir/identity.py ADDED_FIELDS) counts every frame."""
  videos = _videos(np.random.default_rng(1), 4)
  evaluation = base_config().evaluation
  evaluation.chunk_length = 2
  assert ADDED_FIELDS['evaluation.skip_first_frame'] is False
  mesh = sharding.make_mesh()
  kwargs = dict(batch_size=4, fields=('slots', 'video', 'segmentations'))
  default = evaluate.evaluate_slot_model(evaluation, NUM_TRUE, mesh,
                                         _IdSlotModel(), {}, videos, T,
                                         **kwargs)
  every = evaluate.evaluate_slot_model(_config(False), NUM_TRUE, mesh,
                                       _IdSlotModel(), {}, videos, T, **kwargs)
  assert default == every
  assert evaluate.evaluate_slot_model(
      _config(True), NUM_TRUE, mesh, _IdSlotModel(), {}, videos, T,
      **kwargs)['fg_ari'] != every['fg_ari']


def test_one_frame_cannot_skip_its_first():
  videos = _videos(np.random.default_rng(2), 4)
  with pytest.raises(ConfigError, match='at least 2 frames'):
    evaluate.evaluate_slot_model(
        _config(True), NUM_TRUE, sharding.make_mesh(), _IdSlotModel(), {},
        videos, 1,
        batch_size=4, fields=('slots', 'video', 'segmentations'))
