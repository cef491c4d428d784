"""OBJ3D (the paper's hyper-parameter table, column OBJ3D).

SAVi on 64x64 frames, 6 slots; SlotFormer with T=6 burn-in, K=10 rollout,
D_e=128, 4 layers, lambda=1. Evaluation: 6 burn-in + 44 rollout frames of the
first 50. OBJ3D has no ground-truth masks, so only frame metrics.
"""

from slotformer_jax.default_config import base_config


def get_config():
  config = base_config()
  config.data.name = 'obj3d'
  config.data.resolution = (64, 64)
  config.data.max_instances = 6

  # Slot model: SAVi (the official OBJ3D SAVi wraps its Transformer
  # predictor in a per-slot LSTM of 256 units).
  config.savi.num_slots = 6
  config.savi.slot_size = 128
  config.savi.predictor.lstm_size = 256
  config.savi.batch_size = 64
  config.savi.num_train_steps = 80_000

  # Transformer.
  config.slotformer.burn_in = 6
  config.slotformer.rollout = 10
  config.slotformer.embed_dim = 128
  config.slotformer.num_layers = 4
  config.slotformer.image_loss_weight = 1.0
  config.slotformer.batch_size = 128
  config.slotformer.num_train_steps = 200_000

  config.extraction.chunk_length = 50
  config.evaluation.rollout_steps = 44
  config.evaluation.chunk_length = 25
  config.evaluation.metrics = ('psnr', 'ssim', 'lpips')
  return config
