"""Kubric's MOVi-A ... MOVi-E (the SAVi datasets): SAVi's MOVi models, SlotFormer on top.

`--config=configs/movi.py:<variant>`, the variant '_'-joined words:

| words | stage 1 | SAVi's config (google-research/slot-attention-video, `savi/configs/movi/`) |
|---|---|---|
| `a` ... `e` (default `a`) | SAVi-S, RGB frames (SlotFormer's target) | `savi_conditional_small.py`, but `targets` |
| `savis` (MOVi-A) | SAVi-S, flow | `savi_conditional_small.py` |
| `savim` (MOVi-A) | SAVi-M, flow | `savi_conditional_medium.py` |
| `savil` (MOVi-A) | SAVi-L, flow | `savi_conditional_large.py` |
| `savipp` (MOVi-E) | SAVi++, flow + depth | `savi++_conditional.py` |

plus a letter for another MOVi (`savim_c`, `savipp_a`), `uncond` for
learned initial slots instead of the first frame's boxes (`a_uncond`,
`savipp_uncond`), and `fixture` for the tiny run of the tests on the MOVi
fixture (`fixture`, `savipp_fixture`). Convert the download first
(docs/datasets.md; the flow and depth targets need converter version 2):

    python -m slotformer_jax.data.prepare --dataset=movi \\
        --source=/path/to/movi_a/128x128/1.0.0

Every variant is conditional SAVi as SAVi's configs are
(`conditioning_key = "boxes"`, `CoordinateEncoderStateInit` with
`prepend_background=True`, `center_of_mass=False`: here
`savi.initial_slots='boxes'`, slot 0 the background). Until issue 51 this
file was unconditional: `:a` ... `:e` and `:fixture` are now conditional,
`:a_uncond` ... `:e_uncond` and `:fixture_uncond` are what they were but
for SAVi-S's position MLP (now SAVi's 64 hidden, 32 out; it was one width
of 64). SAVI_FIELDS below names SAVi's field for every value set here
(tests/datasets/test_movi_configs.py checks the two agree). In short, from
the SAVi config files:
* all: batch 64 (`batch_size`), Adam 2e-4 (`learning_rate`) with 2,500
  warm-up steps (`warmup_steps`) then cosine decay, gradient clipping 0.05
  (`max_grad_norm`), 6-frame training clips (`temporal_random_strided_window
  (length=6)` of `preproc_train`), 24-frame evaluation in slices of 6
  (`eval_slice_size`), one Slot Attention iteration (`corrector.
  num_iterations`), 128-d slots (`initializer.embedding_transform.
  output_size`; box MLP `hidden_size` 256), a one-block post-LN Transformer
  predictor (`predictor`: `TransformerBlock`, 4 heads), the position MLP of
  64 hidden units (`encoder.pos_emb.output_transform.hidden_size`), a 4-layer
  5x5 spatial-broadcast decoder of 64 channels from 8x8 (`decoder.resolution`,
  `decoder.backbone.features`), max_instances + 1 slots (`num_slots`; SAVi
  sets 23 everywhere, its note says 10 suffices on MOVi-A/B/C: 10 + 1 there);
* SAVi-S: 64x64 (`resize_small(64)`), a 4-layer 5x5 CNN of 32 channels at
  stride 1 (`encoder.backbone`), qkv 128 (`corrector.qkv_size`,
  `predictor.qkv_size`), predictor MLP 256 (`predictor.mlp_size`), 100k
  steps (`num_train_steps`), `targets = {"flow": 3}`;
* SAVi-M: 128x128, the CNN of 64 channels, the first at stride 2; else S's;
* SAVi-L: 128x128, ResNet-34 (`ResNet34`, `norm_type="group"`,
  `small_inputs=True`), 500k steps; else S's;
* SAVi++: SAVi-L's and a 4-layer Pre-LN Transformer after the ResNet
  (`encoder.output_transform`: 4 heads, `qkv_size` 16 * 4, `mlp_size`
  1024), qkv 256 and predictor MLP 1024, `random_resized_crop(height=128,
  width=128, min_object_covered=0.75)` in training, MOVi-E
  (`tfds_name`), `targets = {"flow": 3, "depth": 1}` with
  `transform_depth(transform='log_plus')`.
What differs from SAVi (docs/savi_plus_plus.md has the parameter counts):
* its position embeddings project 4 coordinates, SAVi's 2;
* SAVi++'s `decoder.early_fusion=True` (mix the slots' decoder features by
  their masks, then read out) is a memory saving that equals late fusion
  for linear readouts: not needed here, the readouts are linear;
* the loss is the mean squared error over every target channel, SAVi's the
  sum (docs/savi_plus_plus.md: the terms' relative weights are SAVi's);
* `seed = 42`, the eval and checkpoint cadences are this project's.

Stage 2: neither the SlotFormer paper nor its code has MOVi settings; the
values are the paper's OBJ3D column (the CLEVR-like rigid-body dataset
closest to MOVi-A): T=6 burn-in, K=10 rollout, D_e=128, 4 layers, lambda=1,
with the official recipe; its L_I compares SAVi's targets (flow, depth for
SAVi++). Evaluation: 6 burn-in + 18 rollout frames = the whole 24-frame
video, on MOVi's validation split ('val'; MOVi-A/B have no test split,
C/D/E's test split holds held-out objects); without RGB targets the frame
metrics (PSNR, SSIM, LPIPS) are not asked for (SAVi decodes no frames).
`evaluation.skip_first_frame=True` leaves the first (conditioning) frame
out of SAVi's whole-video metrics, the SAVi paper's convention (False:
every frame, the SAVi repository's released numbers); eval/metrics.json
records it in `protocol.skip_first_frame`.

No full MOVi run was measured for this project: these configs were only
run end to end on the tiny fixture of tests/datasets/test_datasets_movi.py
(`:fixture`, `:savipp_fixture`); their compiled memory on TPUs is in
docs/savi_plus_plus.md.
"""

from slotformer_jax.config.defaults import base_config
from slotformer_jax.config.defaults import use_cpu_demo_savi
from slotformer_jax.config.defaults import use_official_slotformer_recipe

# Most instances of a video (Kubric's README; SAVi's configs use 10 for
# MOVi-A/B/C and 23 for D/E). The converter's default rows are the same.
MAX_INSTANCES = {'a': 10, 'b': 10, 'c': 10, 'd': 23, 'e': 23}
NUM_FRAMES = 24
# SAVi's models: (their config file, the MOVi they train on by default).
MODELS = {'savis': ('savi_conditional_small.py', 'a'),
          'savim': ('savi_conditional_medium.py', 'a'),
          'savil': ('savi_conditional_large.py', 'a'),
          'savipp': ('savi++_conditional.py', 'e')}
# Variants the config tests run (every word and a few combinations).
VARIANTS = ('a', 'b', 'c', 'd', 'e', 'a_uncond', 'savis', 'savim', 'savil',
            'savipp', 'savim_c', 'savipp_a', 'savipp_uncond', 'fixture',
            'fixture_uncond', 'savipp_fixture')

# Each value set here from SAVi's configs and the field that holds it there
# ('model.' fields are under `config.model`): {our field: SAVi's field}.
SAVI_FIELDS = {
    'savi.batch_size': 'batch_size',
    'savi.num_train_steps': 'num_train_steps',
    'savi.learning_rate': 'learning_rate',
    'savi.warmup_fraction': 'warmup_steps / num_train_steps',
    'savi.grad_clip': 'max_grad_norm',
    'savi.clip_length': 'preproc_train: temporal_random_strided_window(length)',
    'data.resolution': 'preproc_*: resize_small / random_resized_crop(height, width)',
    'savi.random_resized_crop.enabled': 'preproc_train: random_resized_crop',
    'savi.random_resized_crop.min_object_covered':
        'preproc_train: random_resized_crop(min_object_covered)',
    'evaluation.chunk_length': 'eval_slice_size',
    'savi.targets': 'targets',
    'savi.num_slots': 'max_instances + 1 (num_slots)',
    'savi.initial_slots': 'conditioning_key, model.initializer.center_of_mass',
    'savi.slot_size': 'model.initializer.embedding_transform.output_size',
    'savi.encoder.kind': 'model.encoder.backbone.module',
    'savi.encoder.features': 'model.encoder.backbone.features',
    'savi.encoder.kernel_size': 'model.encoder.backbone.kernel_size',
    'savi.encoder.strides': 'model.encoder.backbone.strides',
    'savi.encoder.output_size':
        'model.encoder.pos_emb.output_transform (MLP output: its input width)',
    'savi.encoder.mlp_size':
        'model.encoder.pos_emb.output_transform.hidden_size',
    'savi.encoder.transformer.num_layers':
        'model.encoder.output_transform.num_layers',
    'savi.encoder.transformer.num_heads':
        'model.encoder.output_transform.num_heads',
    'savi.encoder.transformer.qkv_size':
        'model.encoder.output_transform.qkv_size',
    'savi.encoder.transformer.mlp_size':
        'model.encoder.output_transform.mlp_size',
    'savi.slot_attention.num_iterations': 'model.corrector.num_iterations',
    'savi.slot_attention.qkv_size': 'model.corrector.qkv_size',
    'savi.slot_attention.mlp_size': 'model.corrector.mlp_size (unset: none)',
    'savi.predictor.num_heads': 'model.predictor.num_heads',
    'savi.predictor.qkv_size': 'model.predictor.qkv_size',
    'savi.predictor.mlp_size': 'model.predictor.mlp_size',
    'savi.predictor.pre_norm': 'model.predictor (TransformerBlock pre_norm=False)',
    'savi.decoder.broadcast_resolution': 'model.decoder.resolution',
    'savi.decoder.features': 'model.decoder.backbone.features',
    'savi.decoder.kernel_size': 'model.decoder.backbone.kernel_size',
}


def get_config(variant: str = 'a'):
  words = [w for w in (variant or 'a').lower().split('_') if w]
  letters = [w for w in words if w in MAX_INSTANCES]
  models = [w for w in words if w in MODELS]
  unknown = [w for w in words if w not in MAX_INSTANCES and w not in MODELS
             and w not in ('uncond', 'fixture')]
  if unknown or len(letters) > 1 or len(models) > 1:
    raise ValueError(
        f'unknown MOVi variant {variant!r}; words joined by "_": a MOVi '
        f'letter ({", ".join(MAX_INSTANCES)}), a SAVi model '
        f'({", ".join(MODELS)}), "uncond", "fixture"; e.g. '
        f'{", ".join(VARIANTS)}')
  model = models[0] if models else None
  fixture = 'fixture' in words
  letter = letters[0] if letters else (
      'a' if fixture or model is None else MODELS[model][1])
  config = base_config()
  data = config.data
  data.name = f'movi_{letter}'
  data.max_instances = MAX_INSTANCES[letter]

  savi = config.savi
  savi.num_slots = data.max_instances + 1  # one per instance + background
  savi.initial_slots = 'learned' if 'uncond' in words else 'boxes'
  _savi_s(config)
  if model == 'savis':
    savi.targets = ('flow',)
  elif model == 'savim':
    _savi_m(config)
  elif model == 'savil':
    _savi_l(config)
  elif model == 'savipp':
    _savi_plus_plus(config)

  dyn = config.slotformer
  dyn.burn_in = 6
  dyn.rollout = 10
  dyn.embed_dim = 128
  dyn.num_layers = 4
  dyn.image_loss_weight = 1.0
  dyn.batch_size = 128
  dyn.num_train_steps = 200_000
  use_official_slotformer_recipe(config)

  config.extraction.splits = ('train', 'val')
  config.extraction.chunk_length = NUM_FRAMES
  ev = config.evaluation
  ev.split = 'val'
  ev.rollout_steps = NUM_FRAMES - dyn.burn_in
  ev.chunk_length = 6  # SAVi's eval_slice_size
  frame_metrics = ('psnr', 'ssim', 'lpips') if 'rgb' in savi.targets else ()
  ev.metrics = frame_metrics + ('ari', 'fg_ari', 'fg_miou', 'ar')
  # AR's ground-truth boxes: the converted MOVi boxes (fields boxes /
  # visible, Kubric's boxes of each instance's visible pixels).
  ev.ar_gt_boxes = 'object_masks'
  # SAVi's MOVi evaluation: FG-ARI per video over its frames, skipping the
  # first one (the conditioning frame) as the SAVi paper; False: every
  # frame, as the SAVi repository's released numbers. eval/metrics.json
  # records the choice in protocol.skip_first_frame.
  ev.skip_first_frame = True

  if fixture:
    _fixture(config, plus_plus=model == 'savipp')
  return config


def _savi_s(config) -> None:
  """SAVi-S (savi_conditional_small.py) on 64x64 frames; RGB targets until a
  model word sets SAVi's."""
  config.data.resolution = (64, 64)
  savi = config.savi
  savi.slot_size = 128
  savi.encoder.features = (32, 32, 32, 32)
  savi.encoder.kernel_size = 5
  savi.encoder.strides = (1, 1, 1, 1)
  savi.encoder.output_size = 32  # the MLP's output: the CNN's width
  savi.encoder.mlp_size = 64
  savi.slot_attention.num_iterations = 1
  savi.slot_attention.qkv_size = 128
  savi.slot_attention.mlp_size = None  # SAVi's SlotAttention: no MLP
  savi.predictor.kind = 'transformer'
  savi.predictor.num_layers = 1
  savi.predictor.num_heads = 4
  savi.predictor.qkv_size = 128
  savi.predictor.mlp_size = 256
  savi.predictor.pre_norm = False  # SAVi's TransformerBlock: post-LN
  savi.predictor.dropout_rate = 0.0
  savi.decoder.broadcast_resolution = (8, 8)
  savi.decoder.features = (64, 64, 64, 64)
  savi.decoder.kernel_size = 5
  savi.batch_size = 64
  savi.clip_length = 6
  savi.num_train_steps = 100_000
  savi.learning_rate = 2e-4
  savi.warmup_fraction = 2_500 / savi.num_train_steps
  savi.min_lr_fraction = 0.0
  savi.grad_clip = 0.05


def _savi_m(config) -> None:
  """SAVi-M (savi_conditional_medium.py): 128x128, a 64-channel CNN whose
  first layer has stride 2."""
  config.data.resolution = (128, 128)
  savi = config.savi
  savi.targets = ('flow',)
  savi.encoder.features = (64, 64, 64, 64)
  savi.encoder.strides = (2, 1, 1, 1)
  savi.encoder.output_size = 64


def _savi_l(config) -> None:
  """SAVi-L (savi_conditional_large.py): 128x128, ResNet-34, 500k steps."""
  config.data.resolution = (128, 128)
  savi = config.savi
  savi.targets = ('flow',)
  savi.encoder.kind = 'resnet34'
  savi.encoder.output_size = 512  # ResNet-34's last stage
  savi.num_train_steps = 500_000
  savi.warmup_fraction = 2_500 / savi.num_train_steps


def _savi_plus_plus(config) -> None:
  """SAVi++ (savi++_conditional.py): SAVi-L + the encoder's Transformer,
  256-wide attention, MLP 1024, the random resized crop, flow + depth."""
  _savi_l(config)
  savi = config.savi
  savi.targets = ('flow', 'depth')
  transformer = savi.encoder.transformer
  transformer.num_layers, transformer.num_heads = 4, 4
  transformer.qkv_size, transformer.mlp_size = 16 * 4, 1024
  savi.slot_attention.qkv_size = 256
  savi.predictor.qkv_size = 256
  savi.predictor.mlp_size = 1024
  savi.random_resized_crop.enabled = True
  savi.random_resized_crop.min_object_covered = 0.75


def _fixture(config, plus_plus: bool) -> None:
  """The end-to-end tests' runs on the tiny MOVi-layout fixture: 8 frames of
  16x16 (tests/datasets/test_datasets_movi.py), a few steps of everything;
  their numbers mean nothing. Without a model word, the embedded demos'
  small SAVi; with `savipp`, SAVi++'s parts (ResNet-34, the Transformer,
  flow + depth, the crop, qkv 256) at their real widths, fewer layers."""
  num_frames = 8
  config.data.resolution = (16, 16)
  savi = config.savi
  if plus_plus:
    savi.encoder.transformer.num_layers = 1
    savi.encoder.transformer.mlp_size = 64
    savi.predictor.mlp_size = 64
    savi.decoder.broadcast_resolution = (4, 4)
    savi.decoder.features = (16, 16)
    savi.decoder.kernel_size = 3
  else:
    use_cpu_demo_savi(config)
    if savi.initial_slots == 'learned':
      savi.num_slots = 4  # conditional: one per box row + the background
    savi.encoder.features = (8, 8)
    savi.encoder.strides = (1, 1)
    savi.encoder.output_size = 64
    savi.encoder.mlp_size = None
    savi.slot_attention.qkv_size = None
    savi.predictor.qkv_size = None
    savi.decoder.features = (8, 8)
  savi.batch_size = 2
  savi.clip_length = 3
  savi.num_train_steps = 2
  savi.warmup_fraction = 0.025
  savi.log_every, savi.checkpoint_every = 1, 2
  dyn = config.slotformer
  dyn.burn_in, dyn.rollout = 2, 2
  dyn.embed_dim = 16
  dyn.num_layers = 1
  dyn.num_heads = 2
  dyn.batch_size = 2
  dyn.num_train_steps = 2
  dyn.log_every, dyn.checkpoint_every = 1, 2
  # L_I decodes every predicted frame through SAVi's decoder: a second,
  # larger program to compile; SAVi++'s fixture keeps it (L_I on its
  # targets is part of what it tests).
  dyn.image_loss_weight = 1.0 if plus_plus else 0.0
  config.extraction.batch_size = 2
  config.extraction.chunk_length = num_frames
  ev = config.evaluation
  ev.batch_size = 2
  ev.rollout_steps = num_frames - dyn.burn_in
  ev.chunk_length = 4
  ev.metrics = (('psnr',) if 'rgb' in savi.targets else ()) + (
      'ari', 'fg_ari', 'fg_miou', 'ar')
  config.render.num_videos = 1
