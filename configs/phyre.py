"""PHYRE, BALL tier, within-template (the paper's table, column PHYRE).

SAVi on 128x128 frames (black background), 8 slots, decoder broadcast
16x16 for the small objects; SlotFormer with T=1, K=10, D_e=256, 8 layers,
no L_I (lambda=0).
"""

from slotformer_jax.default_config import base_config


def get_config():
  config = base_config()
  config.data.name = 'phyre'
  config.data.resolution = (128, 128)
  config.data.max_instances = 8

  config.savi.num_slots = 8
  config.savi.slot_size = 128
  config.savi.encoder.strides = (2, 1, 1, 1)  # 128x128 -> 64x64 features
  config.savi.decoder.broadcast_resolution = (16, 16)
  config.savi.batch_size = 64
  config.savi.num_train_steps = 370_000

  # Transformer.
  config.slotformer.burn_in = 1
  config.slotformer.rollout = 10
  config.slotformer.embed_dim = 256
  config.slotformer.num_layers = 8
  config.slotformer.image_loss_weight = 0.0
  config.slotformer.batch_size = 64
  config.slotformer.num_train_steps = 300_000

  config.extraction.chunk_length = 16
  config.evaluation.rollout_steps = 10
  # The rendered layout has train / val folds only (no test split).
  config.extraction.splits = ('train', 'val')
  config.evaluation.split = 'val'
  config.evaluation.metrics = ('psnr', 'ssim', 'lpips')
  return config
