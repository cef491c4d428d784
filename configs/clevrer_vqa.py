"""CLEVRER VQA with Aloe over SlotFormer's slots: the official values.

The video pipeline is configs/clevrer.py's (stochastic SAVi, SlotFormer);
`config.vqa` is the official Aloe re-implementation (SlotFormer's
`aloe_clevrer_params-rollout.py`): 12 Pre-LN layers, 8 heads, d_model 144
(= (14-d word embedding + 2 flags + 2 type) x 8 heads), FFN 512, answer MLPs
of 128, learned per-token positions, 25 slot frames with stride 5 from a
random start within the 128 observed frames, rollout to 160 frames read by
predictive questions; PyTorch's LayerNorm epsilon 1e-5; Adam 1e-3, 10%
warm-up, cosine to lr / 100, 400 epochs of batch 256 (~240k steps).

The authors' Aloe (`pretrained/aloe_clevrer_params-rollout/model_400.pth`)
converts into this config's VQA variant folder (docs/official_weights.md):

  python -m slotformer_jax.official.convert --config=configs/clevrer_vqa.py \
      --config.data.channel_order=bgr --workdir=runs/clevrer \
      --config.vqa.vocab_file=CLEVRER_vocab.json \
      --checkpoint=pretrained/aloe_clevrer_params-rollout/model_400.pth

  python -m slotformer_jax.main --config=configs/clevrer_vqa.py \
      --workdir=runs/clevrer --config.vqa.questions_root=/data/CLEVRER \
      --mode=vqa_slots   # then train_vqa, evaluate_vqa
"""

import importlib.util
import os

from slotformer_jax.config.defaults import vqa_config


def _clevrer_config():
  path = os.path.join(os.path.dirname(os.path.abspath(__file__)),
                      'clevrer.py')
  spec = importlib.util.spec_from_file_location('clevrer_config', path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config()


def get_config(variant: str = ''):
  if variant:
    raise ValueError(f'unknown variant {variant!r}; this config has none '
                     '(use configs/clevrer_vqa.py)')
  config = _clevrer_config()
  config.task = 'vqa'
  config.vqa = vqa_config()  # the defaults are the official values, but:
  config.vqa.layer_norm_epsilon = 1e-5  # PyTorch's LayerNorm
  config.vqa.min_lr_fraction = 0.01  # the official cosine ends at lr / 100
  # The official rollout: SlotFormer from the last frames of the 128 observed,
  # every `slotformer.frame_stride`-th frame, interleaved (see
  # tasks/vqa.py:rollout_after_video), 32 frames to reach 160.
  config.vqa.video_length = 128
  config.vqa.rollout_frames = 32
  config.vqa.eval_split = 'val'
  return config
