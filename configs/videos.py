"""A folder of your own videos: one command from the folder to a world model.

    python -m slotformer_jax.main --config=configs/videos.py \
        --config.data.source=/my/videos --workdir=runs/mine

The data stage converts the folder once (datasets/videos.py: mp4, webm, mov,
avi, mkv, gif files and folders of numbered png / jpg frames; splits from
train/ val/ test/ folders or a hash of each path), then SAVi trains, its
slots are extracted, SlotFormer trains, and the rollouts are scored against
copy-last and SAVi's reconstruction by PSNR, SSIM and LPIPS; your videos
have no ground-truth masks, so FG-ARI, FG-mIoU and AR are left out (one line
in the evaluation's log). `:tiny` is a smoke run whose numbers mean nothing.

Defaults for unknown data, and how to choose them (docs/datasets.md, "Your
own videos"):
* data.resolution (64, 64): SAVi's; objects should be several pixels wide
  at it. data.fit 'crop' (fill the frame, cut the centre) or 'pad'.
* data.num_frames 24 frames kept per video, every data.frame_stride = 2nd
  (30 fps -> 15): shorter videos are skipped. An object should move a few
  pixels between kept frames, not across the frame.
* data.fps 0: the files' own rates. Videos of mixed rates: set it (e.g. 15)
  and data.frame_stride = 1; each file is resampled to it first, then every
  frame_stride-th frame kept. Folders of frames have no rate: skipped when
  it is set.
* savi.num_slots 7: the most objects in a frame, plus one for the
  background, plus one spare.
* savi.clip_length 3 frames per SAVi training clip; slotformer.burn_in 6 +
  rollout 6 (the paper's OBJ3D burn-in); evaluation.rollout_steps 18 = the
  rest of each video.
* steps: SAVi 5,000 and SlotFormer 2,000 (the CPU demo's scale,
  configs/synthetic.py); on a GPU raise both tenfold. Watch SAVi's
  reconstruction PSNR in its log: its slots bound what SlotFormer predicts.
"""

import ml_collections

from slotformer_jax.config.defaults import base_config
from slotformer_jax.config.defaults import use_cpu_demo_savi


def get_config(variant: str = ''):
  config = base_config()
  data = config.data
  data.name = 'videos'
  # --config.data.source=/my/videos (required).
  data.source = ml_collections.config_dict.placeholder(str)
  data.resolution = (64, 64)
  data.num_frames = 24
  data.frame_stride = 2
  # Resample to this rate before the stride (0: each file's own rate).
  data.fps = 0.0
  data.fit = 'crop'
  data.val_fraction = 0.1
  data.test_fraction = 0.1
  # A folder of your own holds some files that cannot be read: they are
  # skipped (one line each) unless more than this share of a split.
  data.max_skip_fraction = 0.5
  data.max_instances = 1  # no ground-truth masks

  savi = config.savi
  savi.num_slots = 7
  use_cpu_demo_savi(config)
  savi.clip_length = 3
  # One more doubling of the 8x8 grid per layer after the first: 64x64.
  savi.decoder.features = (32, 32, 32, 32)
  savi.num_train_steps = 5000
  savi.log_every = 50
  savi.checkpoint_every = 500

  config.extraction.batch_size = 16
  config.extraction.chunk_length = data.num_frames

  dyn = config.slotformer
  dyn.burn_in = 6
  dyn.rollout = 6
  dyn.embed_dim = 64
  dyn.num_layers = 2
  dyn.num_heads = 4
  dyn.dropout_rate = 0.0
  dyn.residual = True  # starts as copy-last (configs/synthetic.py)
  dyn.image_loss_weight = 1.0
  dyn.batch_size = 32
  dyn.num_train_steps = 2000
  dyn.learning_rate = 5e-4
  dyn.log_every = 50
  dyn.checkpoint_every = 500

  ev = config.evaluation
  ev.rollout_steps = data.num_frames - dyn.burn_in
  ev.chunk_length = data.num_frames
  ev.batch_size = 8
  ev.metrics = ('psnr', 'ssim', 'lpips')  # no masks: no FG-ARI, FG-mIoU, AR

  if variant == 'tiny':
    data.resolution = (32, 32)
    savi.decoder.features = (32, 32, 32)
    data.num_frames = 8
    savi.num_train_steps = 20
    dyn.burn_in, dyn.rollout = 2, 2
    dyn.num_train_steps = 10
    savi.log_every = dyn.log_every = 5
    savi.checkpoint_every = dyn.checkpoint_every = 10
    config.extraction.chunk_length = ev.chunk_length = data.num_frames
    ev.rollout_steps = data.num_frames - dyn.burn_in
  elif variant:
    raise ValueError(f'unknown variant {variant!r} of configs/videos.py '
                     "(known: 'tiny')")
  return config
