"""Every config field with its meaning; dataset configs override values.

`configs/<dataset>.py` call `base_config()` and set the values of the paper's
hyper-parameter table (Appendix, "Variations in model architectures and
training settings"). Any field can be overridden on the command line, e.g.
`--config.slotformer.num_layers=8`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import ml_collections

from slotformer_jax import targets

# Every field with a fixed set of values: {dotted field: its values}, each
# declared where its default is set (`one_of`). config/checks.py refuses any
# other value before any work; a tuple field takes any of them, each once.
CHOICES: dict[str, tuple[Any, ...]] = {}


def one_of(field: str, default: Any, values: Sequence[Any]) -> Any:
  """`default`, after declaring that `field` takes one of `values` (or,
  for a tuple field, a selection of them)."""
  values = tuple(values)
  chosen = default if isinstance(default, tuple) else (default,)
  if not set(chosen) <= set(values):
    raise ValueError(f'{field}: default {default!r} is not among {values}')
  # Values registered by other code (a metric: evaluation/rollout_metrics.py)
  # stay when a later base_config() declares the field again.
  CHOICES[field] = values + tuple(value for value in CHOICES.get(field, ())
                                  if value not in values)
  return default


# The rollout metrics evaluated by default: the built-in ones, registered
# with their labels in evaluation/rollout_metrics.py (a metric registered
# from elsewhere adds itself to the values `evaluation.metrics` takes).
ROLLOUT_METRICS = ('psnr', 'ssim', 'lpips', 'ari', 'fg_ari', 'fg_miou', 'ar')


def base_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.seed = 0
  # Several seeds trained at once, in one program (train/seeds.py `Seeds`):
  # None (the default) is one seed, `seed`, exactly as before. A tuple of
  # distinct ints, e.g. (0, 1, 2): a training stage stacks the seeds'
  # parameters and optimiser states on a leading axis, runs one jitted step
  # vmapped over it and checkpoints them as one state. Seed s drives what
  # `seed=s` drives in a one-seed run: the initialisation and the step RNG
  # (dropout, slot-initialisation noise, Gumbel / posterior samples); the
  # data order is `seed_data_order`. Seed k of the run trains as the
  # one-seed run with seed k (to float32 rounding). Stage 1's first part
  # (SAVi, the dVAE) takes several seeds, and so does the chain after it
  # (SAVi's and STEVE's), seed s on stage-1 seed s: STEVE's tokens into
  # seed_<s>/tokens/ and STEVE (one program, one stacked checkpoint),
  # extraction into seed_<s>/slots/, SlotFormer (one program, one stacked
  # checkpoint), evaluation, pictures and explorer in seed_<s>/ and
  # eval/metrics.json with mean +- std over the seeds. The tasks do not yet
  # (config/checks.py names them; docs/seeds.md).
  config.seeds = ml_collections.config_dict.placeholder(tuple)
  # 'shared': every seed sees the batches of `seed`'s stream (a one-seed
  # run's order; what the seed-k-equals-run-k check needs); 'per_seed':
  # seed s draws its batches with s.
  config.seed_data_order = one_of('seed_data_order', 'shared',
                                  ('shared', 'per_seed'))
  # A seed whose loss or parameters become non-finite is named in one line;
  # 'stop': the run stops (nothing non-finite saved); 'continue': it keeps
  # its last finite parameters and the others go on (all diverged: stop).
  config.on_seed_divergence = one_of('on_seed_divergence', 'stop',
                                     ('stop', 'continue'))
  # Split the stacked state on a 'seed' mesh axis beside 'data' when each
  # process's devices split into len(seeds) groups (e.g. 4 seeds x 2 data
  # on 8 devices); otherwise, or False, the seeds are replicated on every
  # device and only the batch is split.
  config.seed_axis = True
  # How the one program runs the seeds' steps: 'vmap' (one batched step,
  # wider kernels: fills an accelerator), 'unroll' (the one-seed step written K
  # times into the program: the one-seed kernels) or 'auto': 'unroll' on
  # CPU when the seeds are not split over devices, else 'vmap'
  # (docs/seeds.md has the timings).
  config.seed_loop = one_of('seed_loop', 'auto', ('auto', 'vmap', 'unroll'))
  # 'float32' or 'bfloat16': the dtype the training losses and the rollout
  # evaluation compute in; parameters, optimiser state and checkpoints stay
  # float32 either way (slotformer_jax/runtime/precision.py).
  config.compute_dtype = one_of('compute_dtype', 'float32',
                                ('float32', 'bfloat16'))
  # Which stage-1 model extracts the slots: 'savi' (incl. stochastic SAVi)
  # or 'steve' (dVAE + STEVE, `config.dvae` / `config.steve`).
  config.slot_model = 'savi'
  # Another run's workdir whose SAVi checkpoint and extracted slots this run
  # uses (e.g. for stage-2 ablations); None: this run's own --workdir.
  config.stage1_workdir = ml_collections.config_dict.placeholder(str)
  # The downstream task after stage 2: None (video prediction: evaluate,
  # render, explore), 'contact' (`config.readout = contact_readout_config()`),
  # 'planning' (`planning_readout_config()`) or 'vqa' (`vqa_config()`).
  config.task = ml_collections.config_dict.placeholder(str)

  # ---- data (see slotformer_jax/data/sources.py for every field) ----------
  config.data = ml_collections.ConfigDict()
  config.data.name = 'synthetic'
  # None: $SLOTFORMER_DATA_DIR or ~/.cache/... (a typed placeholder, so that
  # --config.data.data_dir=... can set it).
  config.data.data_dir = ml_collections.config_dict.placeholder(str)
  # Real datasets: 'rgb' (as converted) or 'bgr' (the official CLEVRER
  # models saw OpenCV's BGR frames; the official Physion ones saw RGB).
  config.data.channel_order = one_of('data.channel_order', 'rgb',
                                     ('rgb', 'bgr'))
  # Real datasets: which conversion under <data_dir>/<name> to read when
  # `resolution` does not single one out (None: the only / matching one).
  config.data.prepared_config = ml_collections.config_dict.placeholder(str)
  config.data.resolution = (64, 64)
  # Largest ground-truth instance id in the segmentations (0 = background).
  config.data.max_instances = 6
  # Worker processes that build the training batches of the step-trained
  # stages (SAVi/STEVE, SlotFormer; data/workers.py): 0 builds them in one
  # background thread of the training process (enough on CPU, where the
  # step itself wants every core, and no process start-up per stage);
  # N >= 1 spreads them over N processes, for an accelerator host whose
  # chips wait for the reader (benchmarks/gpu_check.sh says 'input-bound';
  # docs/performance.md, "Feeding the chips"). The batches are the same.
  config.data.reader_workers = 0
  # Worker processes that generate the embedded datasets (None: one per
  # core); not part of a run's identity.
  config.data.num_workers = ml_collections.config_dict.placeholder(int)

  # ---- stage 1: SAVi ------------------------------------------------------
  config.savi = savi = ml_collections.ConfigDict()
  savi.stochastic = False  # True: stochastic SAVi (CLEVRER)
  savi.prior_sigma = 0.1  # sigma_hat of the stochastic KL term
  savi.kl_weight = 1e-4
  savi.num_slots = 6
  savi.slot_size = 128
  # 'learned': a learned vector per slot (SlotFormer's SAVi); 'gaussian':
  # slots sampled from one learned Gaussian (the original Slot Attention);
  # 'boxes' / 'points': conditional SAVi, slots from the first frame's boxes
  # (or their centres) through an MLP (hidden 256); slot 0 is a zero
  # background box, slot 1 + i box row i, so num_slots >= box rows + 1.
  savi.initial_slots = one_of('savi.initial_slots', 'learned',
                              ('learned', 'gaussian', 'boxes', 'points'))
  # What the decoder reconstructs, one readout head and one loss term per
  # target (slotformer_jax/targets.py has the batch fields and ranges):
  # 'rgb' (the frames), 'flow' (optical flow as SAVi's colour picture: SAVi's
  # MOVi models), 'depth' (log(1 + depth)); ('flow', 'depth') is SAVi++'s.
  # Without RGB the frame metrics (PSNR, SSIM, LPIPS) and the frame pictures
  # are skipped; SlotFormer's L_I compares the same targets.
  savi.targets = one_of('savi.targets', targets.DEFAULT, targets.NAMES)
  # SAVi++'s training augmentation (SAVi's RandomResizedCrop as
  # savi++_conditional.py sets it): per training clip one crop keeping at
  # least min_object_covered of the frame (width / height in
  # aspect_ratio_range, area share in area_range, max_attempts draws, else
  # the whole frame), resized back to data.resolution; frames, boxes, flow
  # (rescaled) and depth alike (slotformer_jax/data/augment.py). Off: the
  # clips as read, bit for bit.
  savi.random_resized_crop = ml_collections.ConfigDict(dict(
      enabled=False, min_object_covered=0.75,
      aspect_ratio_range=(3 / 4, 4 / 3), area_range=(0.08, 1.0),
      max_attempts=100))
  # The per-frame encoder: a backbone, the soft position embedding, then per
  # position LayerNorm + MLP (mlp_size hidden, None: output_size; then
  # output_size) and, with transformer.num_layers > 0, ReLU(Dense(qkv_size))
  # and a Pre-LN Transformer of that width over the positions (SAVi++: 4
  # layers, 4 heads, qkv_size 64, mlp_size 1024). kind: 'cnn' (the conv
  # layers of features / kernel_size / strides / padding) or 'resnet34'
  # (SAVi++'s ResNet-34: group norm, the small-input stem, 128x128 frames ->
  # a 16x16 map of 512 channels; modules/resnet.py). padding: 'same' (XLA)
  # or 'pytorch' (K//2 on both sides: the official models; differs from
  # 'same' only at stride 2).
  savi.encoder = ml_collections.ConfigDict(dict(
      kind=one_of('savi.encoder.kind', 'cnn', ('cnn', 'resnet34')),
      features=(64, 64, 64, 64), kernel_size=5, strides=(1, 1, 1, 1),
      output_size=128,
      padding=one_of('savi.encoder.padding', 'same', ('same', 'pytorch')),
      mlp_size=ml_collections.config_dict.placeholder(int),
      transformer=ml_collections.ConfigDict(dict(
          num_layers=0, num_heads=4, qkv_size=64, mlp_size=1024))))
  # qkv_size (here and in the predictor): the width of the queries, keys
  # and values; None: slot_size (SAVi++: 256 on 128-d slots). mlp_size: the
  # residual MLP after the GRU; None: none (SAVi's MOVi configs).
  savi.slot_attention = ml_collections.ConfigDict(dict(
      num_iterations=2,
      mlp_size=ml_collections.FieldReference(256, field_type=int),
      qkv_size=ml_collections.config_dict.placeholder(int)))
  # f_trans. kind: 'transformer' (over one frame's slots), 'transformer_lstm'
  # (+ a per-slot LSTM of lstm_size units and a linear layer back to D) or
  # 'residual_mlp' (LN -> Linear(mlp_size) -> ReLU -> Linear, + residual).
  # pre_norm: Pre-LN Transformer; for 'residual_mlp' the residual is taken
  # from the normalised input. dropout_rate: the Transformer's.
  savi.predictor = ml_collections.ConfigDict(dict(
      kind=one_of('savi.predictor.kind', 'transformer',
                  ('transformer', 'transformer_lstm', 'residual_mlp')),
      num_layers=2, num_heads=4, mlp_size=512,
      lstm_size=0, pre_norm=True, dropout_rate=0.0,
      qkv_size=ml_collections.config_dict.placeholder(int)))
  # Head on the initial slots before Slot Attention: 'none', 'linear' or
  # 'mlp' (Linear -> LN -> ReLU -> Linear); it predicts (mean, log-variance):
  # stochastic SAVi samples, deterministic SAVi keeps the mean.
  savi.posterior_head = one_of('savi.posterior_head', 'none',
                               ('none', 'linear', 'mlp'))
  savi.decoder = ml_collections.ConfigDict(dict(
      broadcast_resolution=(8, 8), features=(64, 64, 64, 64), kernel_size=5))
  # Of every LayerNorm: 1e-6 (flax) or 1e-5 (PyTorch, the official models).
  savi.layer_norm_epsilon = 1e-6
  # 'flax' (lecun-normal kernels, zero biases, orthogonal recurrent kernels)
  # or 'pytorch' (PyTorch's defaults, see modules/initializers.py).
  savi.init = one_of('savi.init', 'flax', ('flax', 'pytorch'))
  # Training (Adam, linear warm-up then cosine decay; both start / end at
  # min_lr_fraction * learning_rate).
  savi.batch_size = 64
  savi.clip_length = 6
  savi.num_train_steps = 80_000
  savi.learning_rate = 2e-4
  savi.min_lr_fraction = 0.0
  # {top-level parameter name: peak learning rate} of parts trained at
  # their own rate (STEVE's token decoder); {}: one rate for all.
  savi.group_learning_rates = {}
  savi.warmup_fraction = 0.025
  savi.grad_clip = 0.05  # max global gradient norm
  savi.log_every = 100
  savi.checkpoint_every = 1000
  # Several processes: how often (in steps) they agree whether a SIGTERM /
  # SIGINT reached one of them (one small all-gather, a host sync on an
  # accelerator); a signal is acted on up to stop_check_every - 1 steps late,
  # after the same step everywhere. Not part of a run's identity.
  savi.stop_check_every = 1

  # ---- stage 1 with slot_model='steve': dVAE, then STEVE -----------------
  # The official Physion values (dvae_physion_params, steve_physion_params).
  config.dvae = dvae = ml_collections.ConfigDict()
  dvae.vocab_size = 4096  # codes; 4x4 pixels per token
  dvae.hidden_size = 64
  # Gumbel-softmax temperature, cosine-annealed over the first 15% of steps.
  dvae.gumbel_start = 1.0
  dvae.gumbel_final = 0.1
  dvae.gumbel_anneal_fraction = 0.15
  dvae.batch_size = 64  # single frames
  dvae.num_train_steps = 700_000
  dvae.learning_rate = 1e-3
  dvae.min_lr_fraction = 0.0  # the official schedule ends at 0
  dvae.group_learning_rates = {}
  dvae.warmup_fraction = 0.05
  dvae.grad_clip = 0.0  # none
  dvae.tokenize_batch_size = 16  # videos per batch when tokenizing
  dvae.log_every = 100
  dvae.checkpoint_every = 1000
  dvae.stop_check_every = 1  # see savi.stop_check_every
  config.steve = steve = ml_collections.ConfigDict()
  steve.num_slots = 6
  steve.slot_size = 192
  # padding as savi.encoder's ('pytorch': the official Conv2d).
  steve.encoder = ml_collections.ConfigDict(dict(
      features=(64, 64, 64, 64), kernel_size=5, strides=(2, 1, 1, 1),
      output_size=192,
      padding=one_of('steve.encoder.padding', 'same', ('same', 'pytorch'))))
  # Of the encoder, Slot Attention and the predictor (1e-5: PyTorch's, the
  # official model); the token decoder uses 1e-5 always.
  steve.layer_norm_epsilon = 1e-6
  steve.slot_attention = ml_collections.ConfigDict(dict(
      num_iterations=2, mlp_size=384))
  steve.predictor = ml_collections.ConfigDict(dict(
      num_layers=2, num_heads=4, mlp_size=768, lstm_size=384))
  # The autoregressive token decoder; its width is slot_size.
  steve.decoder = ml_collections.ConfigDict(dict(
      num_layers=4, num_heads=4, dropout_rate=0.1))
  steve.batch_size = 48
  steve.clip_length = 6
  steve.num_train_steps = 460_000
  steve.learning_rate = 1e-4
  steve.min_lr_fraction = 0.0  # the official schedule ends at 0
  steve.group_learning_rates = {'decoder': 3e-4}  # the token decoder
  steve.warmup_fraction = 0.05
  steve.grad_clip = 0.05
  steve.log_every = 100
  steve.checkpoint_every = 1000
  steve.stop_check_every = 1  # see savi.stop_check_every

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
  # 'naive': the ablation's per-token positional encoding.
  dyn.positional_encoding = one_of('slotformer.positional_encoding',
                                   'temporal', ('temporal', 'naive'))
  dyn.residual = False  # predict S_t + f(...) (the paper's remark)
  # 0: the context is the last burn_in frames. > burn_in: it grows from the
  # burn_in observed frames by one predicted frame per step up to
  # max_context frames, then slides (PHYRE: burn_in 1, max_context 6).
  dyn.max_context = 0
  dyn.layer_norm_epsilon = 1e-6  # 1e-5: PyTorch's, the official models
  dyn.init = one_of('slotformer.init', 'flax', ('flax', 'pytorch'))  # as savi.init
  dyn.teacher_forcing = False  # ablation: feed ground-truth slots back
  dyn.image_loss_weight = 1.0  # lambda of L_I (0 disables L_I)
  dyn.frame_stride = 1  # temporal subsampling of the slot sequences
  dyn.batch_size = 128
  dyn.num_train_steps = 200_000
  dyn.learning_rate = 2e-4
  dyn.min_lr_fraction = 0.0
  dyn.group_learning_rates = {}
  dyn.warmup_fraction = 0.05
  dyn.grad_clip = 0.0  # the paper uses none
  dyn.log_every = 100
  dyn.checkpoint_every = 1000
  dyn.stop_check_every = 1  # see savi.stop_check_every

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
  # 'first': each video from frame 0, or a rule of the dataset's (its
  # module's `clip_rules`: 'clevrer', the official CLEVRER clips, where no
  # object enters during the rollout); checked against the dataset.
  ev.clips = 'first'
  ev.chunk_length = 16  # frames per call in SAVi's whole-video evaluation
  ev.metrics = one_of(
      'evaluation.metrics', ROLLOUT_METRICS, ROLLOUT_METRICS)
  # None: a plain argmax over the alpha masks gives the predicted segments.
  # 0.5 reproduces the official post-processing (pixels where every alpha is
  # below it go to the weakest slot, taken as background).
  ev.background_threshold = ml_collections.config_dict.placeholder(float)
  # AR's ground-truth boxes: 'segmentation' (the boxes of the id map) or
  # 'object_masks' (each object's full mask, overlapped parts included: the
  # official convention; needs a dataset that stores 'boxes', e.g. CLEVRER).
  ev.ar_gt_boxes = one_of('evaluation.ar_gt_boxes', 'segmentation',
                          ('segmentation', 'object_masks'))
  # FG-mIoU over the objects of a frame: 'skip' (mean over the ids with
  # pixels) or 'zero' (an id below the frame's largest one but without
  # pixels counts IoU 0: the official convention).
  ev.miou_absent_ids = one_of('evaluation.miou_absent_ids', 'skip',
                              ('skip', 'zero'))
  # The slot model's whole-video metrics (FG-ARI, ARI, FG-mIoU, PSNR): over
  # every frame (False) or leaving out the first (True: the SAVi paper's
  # MOVi convention, whose conditional SAVi sees that frame's boxes). The
  # rollout metrics start after the burn-in either way.
  ev.skip_first_frame = False

  # ---- TensorBoard (train/summaries.py) -----------------------------------
  # Every training stage writes <stage dir>/tensorboard/ beside its JSONL
  # log: the logged scalars, and every image_every steps (0: never) its
  # labelled pictures (reconstruction, slot masks, rollout strip).
  config.logging = ml_collections.ConfigDict(dict(
      tensorboard=True, image_every=500))

  # ---- pictures -----------------------------------------------------------
  config.render = ml_collections.ConfigDict(dict(
      num_videos=4, fps=6, scale=2, strip_every=2))
  # The run explorer (--mode=explore, explore/index.html): `num_videos`
  # held-out videos with every slot's counterfactual rollouts; frames drawn
  # `scale` times their size, played at `fps`.
  config.explore = ml_collections.ConfigDict(dict(
      num_videos=8, fps=4, scale=4))
  return config


def use_cpu_demo_savi(config: ml_collections.ConfigDict) -> None:
  """The small SAVi of the embedded CPU demos (configs/synthetic*.py): 64-d
  slots, a 4-layer 3x3 encoder whose first layer has stride 2, one predictor
  layer, a 2-layer decoder from an 8x8 grid, 2-frame clips of batch 8, Adam
  1e-3. Each demo sets its own number of slots and steps."""
  savi = config.savi
  savi.slot_size = 64
  savi.encoder.features = (32, 32, 32, 32)
  savi.encoder.kernel_size = 3
  savi.encoder.strides = (2, 1, 1, 1)
  savi.encoder.output_size = 64
  savi.slot_attention.mlp_size = 128
  savi.predictor.num_layers = 1
  savi.predictor.mlp_size = 256
  savi.decoder.broadcast_resolution = (8, 8)
  savi.decoder.features = (32, 32)
  savi.decoder.kernel_size = 3
  savi.batch_size = 8
  savi.clip_length = 2
  savi.learning_rate = 1e-3


def use_official_savi_recipe(config: ml_collections.ConfigDict) -> None:
  """The official SAVi training recipe and PyTorch layer conventions.

  The paper's text says Adam at 2e-4, warmed up from 0 and decayed to 0; the
  official code that produced its numbers uses 1e-4 ("a small learning rate
  is very important for SAVi training") with a scheduler that starts and
  ends at lr / 100, and its Transformer predictor keeps PyTorch's dropout of
  0.1. The dataset configs follow the code; the paper's text is
  --config.savi.learning_rate=2e-4 --config.savi.min_lr_fraction=0
  --config.savi.predictor.dropout_rate=0.
  """
  savi = config.savi
  savi.learning_rate = 1e-4
  savi.min_lr_fraction = 0.01
  savi.warmup_fraction = 0.025
  savi.grad_clip = 0.05
  savi.predictor.dropout_rate = 0.1
  savi.layer_norm_epsilon = 1e-5  # PyTorch's
  savi.encoder.padding = 'pytorch'  # Conv2d(padding=K // 2)
  savi.init = 'pytorch'


def use_official_slotformer_recipe(config: ml_collections.ConfigDict) -> None:
  """The official SlotFormer recipe: as the paper (Adam 2e-4, 5% warm-up,
  cosine, no clipping) except that the scheduler starts and ends at lr / 100
  (the paper: 0), PyTorch's Transformer dropout of 0.1, LayerNorm epsilon
  1e-5 and PyTorch's initialisation."""
  dyn = config.slotformer
  dyn.learning_rate = 2e-4
  dyn.min_lr_fraction = 0.01
  dyn.warmup_fraction = 0.05
  dyn.grad_clip = 0.0
  dyn.dropout_rate = 0.1
  dyn.layer_norm_epsilon = 1e-5
  dyn.init = 'pytorch'


def vqa_config() -> ml_collections.ConfigDict:
  """The VQA section (`config.vqa`, CLEVRER-style questions with Aloe).

  Defaults are the official CLEVRER values (configs/clevrer_vqa.py);
  configs/synthetic_vqa.py shrinks them for a 2-core CPU.
  """
  vqa = ml_collections.ConfigDict()
  # Which slots Aloe reads: 'observed' (SAVi's slots of the video),
  # 'rollout' (plus SlotFormer's rollout after it, read by predictive
  # questions), 'blind' (zeros: the question-only baseline).
  vqa.inputs = one_of('vqa.inputs', 'rollout',
                      ('observed', 'rollout', 'blind', 'future'))
  vqa.seed = 0  # Aloe's initialisation and question order (runs per seed)
  vqa.video_length = 128  # observed frames of a video
  vqa.rollout_frames = 32  # frames rolled out after it (official: to 160)
  vqa.num_frames = 25  # slot frames per question ...
  vqa.frame_stride = 5  # ... with this stride (128 // 25), random start
  vqa.max_question_len = 20
  vqa.max_choice_len = 12
  vqa.max_choices = 6  # padded choices per multiple-choice question
  # Aloe: d_model = (word_dim + 2 flags + 2 type) * num_heads = 144.
  vqa.word_dim = 14
  vqa.d_model = 144
  vqa.num_layers = 12
  vqa.num_heads = 8
  vqa.mlp_size = 512
  vqa.head_size = 128
  vqa.dropout_rate = 0.1  # nn.TransformerEncoderLayer's default
  vqa.positions = one_of('vqa.positions', 'token', ('token', 'frame'))  # official: token
  # The Transformer's LayerNorms: flax's 1e-6 here (what docs/vqa.md
  # measured); the official model has PyTorch's 1e-5 (configs/clevrer_vqa.py).
  vqa.layer_norm_epsilon = 1e-6
  # Training: Adam, 10% warm-up then cosine (official: 400 epochs, batch 256
  # over 2 GPUs, lr 1e-3; its cosine ends at lr / 100: min_lr_fraction=0.01
  # in configs/clevrer_vqa.py, 0 here).
  vqa.open_batch_size = 128  # descriptive questions per step
  vqa.choice_batch_size = 128  # multiple-choice questions per step
  # {question type: weight of its multiple-choice questions in the training
  # draws}; {} (or 1): as many as the training split has.
  vqa.choice_type_weights = {}
  vqa.num_train_steps = 240_000
  vqa.learning_rate = 1e-3
  vqa.warmup_fraction = 0.1
  vqa.min_lr_fraction = 0.0
  vqa.group_learning_rates = {}
  vqa.grad_clip = 0.0
  vqa.log_every = 100
  vqa.checkpoint_every = 2000
  vqa.stop_check_every = 1  # see savi.stop_check_every
  vqa.eval_split = 'val'
  vqa.eval_batch_size = 64
  # Questions join videos by name; a question whose video is not in the
  # converted split (skipped at conversion: CLEVRER's validation video 10800
  # always is) is reported and left out. Evaluation refuses a split where
  # more than this share of the questions is left out (1: score whatever
  # has a video, e.g. a trial conversion with --limit).
  vqa.max_missing_video_fraction = 0.05
  # Where CLEVRER's questions/ and vocabulary live (real data); the embedded
  # family ('clevrer_like') keeps them in its dataset folder.
  vqa.questions_root = ml_collections.config_dict.placeholder(str)
  vqa.vocab_file = ml_collections.config_dict.placeholder(str)
  return vqa


def contact_readout_config() -> ml_collections.ConfigDict:
  """The contact-prediction readout (`config.readout` with task='contact').

  Defaults are the official Physion readout (readout_physion_params):
  configs/physion_contact.py; configs/synthetic_contact.py sets the
  embedded family's splits and a smaller readout.
  """
  r = ml_collections.ConfigDict()
  r.observed_frames = 45  # frames observed; the rest is rolled out
  r.video_len = 0  # frames of slots read per video (0: every frame)
  r.label_field = 'label'  # the video field holding the 0/1 contact label
  r.splits = ml_collections.ConfigDict(dict(
      train='readout_train', val='readout_val', test='test'))
  # 'observed', 'rollout' (+ SlotFormer), 'copy_last', 'ground_truth'.
  r.conditions = ('observed', 'rollout', 'copy_last', 'ground_truth')
  # One readout per seed on the run's one chain; results are mean +- std.
  # With config.seeds (several chains) one readout per chain instead, chain
  # s's with seed s, and these are not used (stages/contact.py).
  r.seeds = (0, 1, 2)
  # None: the slot size, as the official readout (typed, so that
  # --config.readout.features=N can set it).
  r.features = ml_collections.config_dict.placeholder(int)
  # 'unordered' (official) or 'both_orders' (invariant to the slot order).
  r.pairs = one_of('readout.pairs', 'unordered', ('unordered', 'both_orders'))
  r.epochs = 50
  r.batch_size = 64
  r.learning_rate = 1e-3
  r.warmup_fraction = 0.0
  r.rollout_batch_size = 32  # videos per SlotFormer rollout call
  r.num_pictures = 0  # readout/test_<i>.png strips
  return r


def planning_readout_config() -> ml_collections.ConfigDict:
  """The planning success classifier (`config.readout` with
  task='planning').

  Defaults are the official PHYRE classifier (readout_phyre_params):
  configs/phyre.py (the rendered layout); configs/synthetic_phyre.py sets
  the embedded tasks' values.
  """
  r = ml_collections.ConfigDict()
  r.conditions = ('first_frame', 'rollout')
  # Embedded tasks: SlotFormer's frames after the first; the classifier
  # reads the frames `selected_steps` of [first frame, rollout].
  r.rollout_steps = 10
  r.selected_steps = (0, 3)
  r.embed_dim = 128
  r.num_layers = 4
  r.num_heads = 8
  r.mlp_ratio = 4
  r.layer_norm_epsilon = 1e-6  # 1e-5: PyTorch's, the official classifier
  # The official classifier trains with nn.TransformerEncoderLayer's 0.1.
  r.dropout_rate = 0.0
  # Classifier seeds on the run's one chain; with config.seeds one per chain
  # (seed s on chain s) instead (stages/planning/embedded.py).
  r.seeds = (0, 1, 2)
  r.dev_share = 0.1  # training tasks held out to choose the epoch
  r.negatives_per_task = 40  # embedded tasks: failing actions kept per task
  r.epochs = 50
  r.batch_size = 256
  r.learning_rate = 1e-3
  r.warmup_fraction = 0.1
  r.encode_batch_size = 256  # candidates per slot-model / rollout call
  r.num_pictures = 0  # planning/test_task_<k>.png rankings (embedded tasks)
  # The rendered PHYRE layout: its fold, the candidates ranked, its splits.
  r.fold = 0
  r.candidates = one_of('readout.candidates', 'rendered', ('rendered',))
  r.splits = ml_collections.ConfigDict(dict(train='train', test='val'))
  return r
