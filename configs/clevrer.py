"""CLEVRER (the paper's hyper-parameter table, column CLEVRER).

Stochastic SAVi on 64x64 frames, 7 slots (objects enter during the video);
SlotFormer on videos subsampled by 2 with T=6, K=10, D_e=256, 4 layers,
lambda=1. Evaluation: 6 burn-in + 42 rollout frames, with the object metrics
(ARI, FG-ARI, FG-mIoU, AR) on the published masks.
"""

from slotformer_jax.default_config import base_config


def get_config():
  config = base_config()
  config.data.name = 'clevrer'
  config.data.resolution = (64, 64)
  # Up to 6 annotated objects + 1 other proposal per frame (the instance
  # labels of slotformer_jax/data/clevrer.py; the official boxes pad to 7).
  config.data.max_instances = 7

  # Slot model: stochastic SAVi (KL weight 1e-4 toward sigma_hat = 0.1).
  config.savi.stochastic = True
  config.savi.prior_sigma = 0.1
  config.savi.kl_weight = 1e-4
  config.savi.num_slots = 7
  config.savi.slot_size = 128
  config.savi.batch_size = 64
  config.savi.num_train_steps = 200_000

  # Transformer.
  config.slotformer.burn_in = 6
  config.slotformer.rollout = 10
  config.slotformer.embed_dim = 256
  config.slotformer.num_layers = 4
  config.slotformer.image_loss_weight = 1.0
  config.slotformer.frame_stride = 2
  config.slotformer.batch_size = 128
  config.slotformer.num_train_steps = 500_000

  config.extraction.chunk_length = 32
  config.evaluation.rollout_steps = 42
  # CLEVRER's test videos come without annotations or masks: the paper
  # evaluates video prediction on the validation videos.
  config.evaluation.split = 'val'
  config.evaluation.clips = 'clevrer'  # drop clips where an object enters
  config.evaluation.chunk_length = 24
  return config
