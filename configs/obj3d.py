"""OBJ3D (the paper's hyper-parameter table, column OBJ3D): the official
models `savi_obj3d_params` and `slotformer_obj3d_params`.

SAVi on 64x64 frames, 6 slots; SlotFormer with T=6 burn-in, K=10 rollout,
D_e=128, 4 layers, lambda=1. Evaluation: 6 burn-in + 44 rollout frames of the
first 50. OBJ3D has no ground-truth masks, so only frame metrics.
docs/official_architectures.md maps every official layer onto these modules.
"""

from slotformer_jax.config.defaults import base_config
from slotformer_jax.config.defaults import use_official_savi_recipe
from slotformer_jax.config.defaults import use_official_slotformer_recipe


def get_config():
  config = base_config()
  config.data.name = 'obj3d'
  config.data.resolution = (64, 64)
  config.data.max_instances = 6

  # Slot model: deterministic SAVi. The official model (as its PHYRE twin)
  # differs from the paper's "Transformer predictor": a 2-layer Pre-LN
  # Transformer followed by a per-slot LSTM of 256 units and a linear layer
  # back to 128 (no residual), and it applies the Gaussian head's mean
  # (Linear-LN-ReLU-Linear) to the predicted slots before Slot Attention.
  # The paper's text: --config.savi.predictor.kind=transformer
  # --config.savi.predictor.lstm_size=0 --config.savi.posterior_head=none.
  config.savi.num_slots = 6
  config.savi.slot_size = 128
  config.savi.predictor.kind = 'transformer_lstm'
  config.savi.predictor.lstm_size = 256
  config.savi.posterior_head = 'mlp'
  config.savi.batch_size = 64
  config.savi.num_train_steps = 80_000
  use_official_savi_recipe(config)

  # Transformer.
  config.slotformer.burn_in = 6
  config.slotformer.rollout = 10
  config.slotformer.embed_dim = 128
  config.slotformer.num_layers = 4
  config.slotformer.image_loss_weight = 1.0
  config.slotformer.batch_size = 128
  config.slotformer.num_train_steps = 200_000
  use_official_slotformer_recipe(config)

  config.extraction.chunk_length = 50
  config.evaluation.rollout_steps = 44
  config.evaluation.chunk_length = 25
  config.evaluation.metrics = ('psnr', 'ssim', 'lpips')
  return config
