"""Every config field with its meaning; dataset configs override values.

`configs/<dataset>.py` call `base_config()` and set the values of the paper's
hyper-parameter table (Appendix, "Variations in model architectures and
training settings"). Any field can be overridden on the command line, e.g.
`--config.slotformer.num_layers=8`.
"""

from __future__ import annotations

import ml_collections


def base_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.seed = 0
  # 'float32' or 'bfloat16': the dtype the training losses and the rollout
  # evaluation compute in; parameters, optimiser state and checkpoints stay
  # float32 either way (slotformer_jax/train/precision.py).
  config.compute_dtype = 'float32'
  # Which stage-1 model extracts the slots: 'savi' (incl. stochastic SAVi).
  config.slot_model = 'savi'
  # Another run's workdir whose SAVi checkpoint and extracted slots this run
  # uses (e.g. for stage-2 ablations); None: this run's own --workdir.
  config.stage1_workdir = ml_collections.config_dict.placeholder(str)

  # ---- data (see slotformer_jax/data/sources.py for every field) ----------
  config.data = ml_collections.ConfigDict()
  config.data.name = 'synthetic'
  config.data.data_dir = None  # None: $SLOTFORMER_DATA_DIR or ~/.cache/...
  # Real datasets: 'rgb' (as converted) or 'bgr' (the official CLEVRER /
  # Physion models saw OpenCV's BGR frames).
  config.data.channel_order = 'rgb'
  # Real datasets: which conversion under <data_dir>/<name> to read when
  # `resolution` does not single one out (None: the only / matching one).
  config.data.prepared_config = None
  config.data.resolution = (64, 64)
  # Largest ground-truth instance id in the segmentations (0 = background).
  config.data.max_instances = 6

  # ---- stage 1: SAVi ------------------------------------------------------
  config.savi = savi = ml_collections.ConfigDict()
  savi.stochastic = False  # True: stochastic SAVi (CLEVRER)
  savi.prior_sigma = 0.1  # sigma_hat of the stochastic KL term
  savi.kl_weight = 1e-4
  savi.num_slots = 6
  savi.slot_size = 128
  # 'learned': a learned vector per slot (SlotFormer's SAVi); 'gaussian':
  # slots sampled from one learned Gaussian (the original Slot Attention).
  savi.initial_slots = 'learned'
  savi.encoder = ml_collections.ConfigDict(dict(
      features=(64, 64, 64, 64), kernel_size=5, strides=(1, 1, 1, 1),
      output_size=128))
  savi.slot_attention = ml_collections.ConfigDict(dict(
      num_iterations=2, mlp_size=256))
  # f_trans: Transformer over one frame's slots (+ per-slot LSTM if > 0).
  savi.predictor = ml_collections.ConfigDict(dict(
      num_layers=2, num_heads=4, mlp_size=512, lstm_size=0))
  savi.decoder = ml_collections.ConfigDict(dict(
      broadcast_resolution=(8, 8), features=(64, 64, 64, 64), kernel_size=5))
  # Training (Adam, linear warm-up then cosine decay to 0).
  savi.batch_size = 64
  savi.clip_length = 6
  savi.num_train_steps = 80_000
  savi.learning_rate = 2e-4
  savi.warmup_fraction = 0.025
  savi.grad_clip = 0.05  # max global gradient norm
  savi.log_every = 100
  savi.checkpoint_every = 1000

  # ---- slot extraction ----------------------------------------------------
  config.extraction = ml_collections.ConfigDict(dict(
      batch_size=16,  # videos per batch (global)
      chunk_length=16,  # frames per SAVi call; the state carries over
      splits=('train', 'val', 'test'),  # the dataset's splits to extract
  ))

  # ---- stage 2: SlotFormer ------------------------------------------------
  config.slotformer = dyn = ml_collections.ConfigDict()
  dyn.burn_in = 6  # T
  dyn.rollout = 10  # K (training)
  dyn.embed_dim = 128  # D_e
  dyn.num_layers = 4  # N_T
  dyn.num_heads = 8
  dyn.mlp_ratio = 4  # FFN hidden size = mlp_ratio * D_e
  # The paper lists no dropout; the official PyTorch code keeps
  # nn.TransformerEncoderLayer's default of 0.1.
  dyn.dropout_rate = 0.1
  dyn.positional_encoding = 'temporal'  # 'naive': ablation (per-token P.E.)
  dyn.residual = False  # predict S_t + f(...) (the paper's remark)
  dyn.teacher_forcing = False  # ablation: feed ground-truth slots back
  dyn.image_loss_weight = 1.0  # lambda of L_I (0 disables L_I)
  dyn.frame_stride = 1  # temporal subsampling of the slot sequences
  dyn.batch_size = 128
  dyn.num_train_steps = 200_000
  dyn.learning_rate = 2e-4
  dyn.warmup_fraction = 0.05
  dyn.grad_clip = 0.0  # the paper uses none
  dyn.log_every = 100
  dyn.checkpoint_every = 1000

  # ---- baseline: Slot-LSTM (the paper's appendix) --------------------------
  # The same per-frame Transformer followed by a per-slot LSTM, trained on the
  # same slots with the same losses and schedule as SlotFormer: every field of
  # `slotformer` applies unless set here (e.g. num_train_steps, batch_size).
  config.slot_lstm = sl = ml_collections.ConfigDict()
  sl.train = False  # True: `--mode=all` trains it and evaluation compares
  for field, kind in (('num_train_steps', int), ('batch_size', int),
                      ('learning_rate', float), ('embed_dim', int),
                      ('num_layers', int)):
    sl[field] = ml_collections.config_dict.placeholder(kind)

  # ---- evaluation ---------------------------------------------------------
  config.evaluation = ev = ml_collections.ConfigDict()
  ev.split = 'test'
  ev.num_videos = 0  # 0: all videos of the split
  ev.batch_size = 16
  ev.rollout_steps = 44
  # Also score SAVi's own reconstruction / segmentation of every frame of the
  # evaluated clips (about 40% of the evaluation time on a CPU).
  ev.savi_metrics = True
  # 'first': each video from frame 0; 'clevrer': the official CLEVRER clips
  # (no object entering during the rollout).
  ev.clips = 'first'
  ev.chunk_length = 16  # frames per call in SAVi's whole-video evaluation
  ev.metrics = ('psnr', 'ssim', 'lpips', 'ari', 'fg_ari', 'fg_miou', 'ar')
  # None: a plain argmax over the alpha masks gives the predicted segments.
  # 0.5 reproduces the official post-processing (pixels where every alpha is
  # below it go to the weakest slot, taken as background).
  ev.background_threshold = ml_collections.config_dict.placeholder(float)

  # ---- pictures -----------------------------------------------------------
  config.render = ml_collections.ConfigDict(dict(
      num_videos=4, fps=6, scale=2, strip_every=2))
  return config
