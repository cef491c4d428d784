"""Physion (the paper's hyper-parameter table, column Physion).

Slots come from STEVE (128x128, 6 slots of 192) on a frozen dVAE (4096 codes,
32x32 tokens per frame), with the official values of
`dvae_physion_params.py` / `steve_physion_params.py` (the defaults of
`config.dvae` / `config.steve`). `--config.slot_model=savi` swaps in SAVi.
SlotFormer: T=15, K=10, D_e=256, 8 layers, no L_I (lambda=0), videos
subsampled by 3.
"""

from slotformer_jax.config.defaults import base_config
from slotformer_jax.config.defaults import use_official_slotformer_recipe


def get_config():
  config = base_config()
  config.data.name = 'physion'
  config.data.resolution = (128, 128)
  config.data.max_instances = 10

  # Slot model: STEVE in the paper. dVAE: single frames, batch 64, Adam 1e-3,
  # 20 epochs (~700k steps); STEVE: clips of 6, batch 48, Adam 1e-4 (decoder
  # 3e-4), clip 0.05, 10 epochs (~460k steps). The `savi` values below are
  # for --config.slot_model=savi.
  config.slot_model = 'steve'
  config.dvae.vocab_size = 4096
  config.dvae.batch_size = 64
  config.dvae.num_train_steps = 700_000
  config.dvae.learning_rate = 1e-3
  config.steve.num_slots = 6
  config.steve.slot_size = 192
  config.steve.encoder.strides = (2, 1, 1, 1)  # 128x128 -> 64x64 features
  config.steve.encoder.output_size = 192
  config.steve.encoder.padding = 'pytorch'  # Conv2d(padding=2) at stride 2
  config.steve.layer_norm_epsilon = 1e-5  # PyTorch's
  config.steve.slot_attention.mlp_size = 384
  config.steve.predictor.mlp_size = 768
  config.steve.predictor.lstm_size = 384
  config.steve.batch_size = 48
  config.steve.clip_length = 6
  config.steve.num_train_steps = 460_000
  config.savi.num_slots = 6
  config.savi.slot_size = 192
  config.savi.encoder.strides = (2, 1, 1, 1)  # 128x128 -> 64x64 features
  config.savi.decoder.broadcast_resolution = (16, 16)
  config.savi.batch_size = 48
  config.savi.num_train_steps = 460_000
  config.savi.encoder.padding = 'pytorch'  # Conv2d(padding=2) at stride 2

  # Transformer.
  config.slotformer.burn_in = 15
  config.slotformer.rollout = 10
  config.slotformer.embed_dim = 256
  config.slotformer.num_layers = 8
  config.slotformer.image_loss_weight = 0.0
  config.slotformer.frame_stride = 3
  config.slotformer.batch_size = 128
  config.slotformer.num_train_steps = 250_000
  use_official_slotformer_recipe(config)

  config.extraction.chunk_length = 50
  config.evaluation.rollout_steps = 35
  config.evaluation.metrics = ('psnr', 'ssim', 'lpips')
  return config
