"""The slot-model interface: what differs between SAVi, STEVE and any other
object-centric model, only that.

A slot model is stage 1 of the pipeline. It *declares* the models it trains
(`Part`s: SAVi; or the dVAE, then STEVE on the dVAE's tokens) and the data
one part derives for the next (`Derived`: STEVE's tokens); one generic piece
trains, stamps, checks and loads any such chain (`chain.py` and
`stages/stage1.py`). Then it turns a video into slots and slots back into
alpha masks (and frames, when it decodes pixels). Everything above it --
slot extraction, SlotFormer / Slot-LSTM, the evaluation, the pictures, the
downstream tasks -- reads slots and frames only through this interface, so
a new slot model is one new file registered with `slot_models.register`
(`docs/developing.md`).

Shapes at this boundary:
  video        uint8 [B, T, H, W, 3]
  slots        float32 [B, T, N, D] (N, D = `slot_shape`)
  Decoded      recon [..., H, W, 3] in [0, 1] or None (a model that decodes
               no pixels), alpha_masks [..., N, H, W, 1] (softmax over the
               N slots), rgb [..., N, H, W, 3] or None, targets {name:
               [..., H, W, C]} of its other reconstruction targets or None
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Iterator, Mapping
import dataclasses
from typing import Any, ClassVar

from flax import struct
import flax.linen as nn
import jax
import ml_collections
import numpy as np

from slotformer_jax import frames

# loss(params, batch, frozen_params, rng) -> (loss, metrics)
LossFn = Callable[[Any, dict[str, jax.Array], Any, jax.Array],
                  tuple[jax.Array, dict[str, jax.Array]]]


@struct.dataclass
class Decoded:
  """Frames decoded from slots; leading dims `...` are the slots' own.

  Attributes:
    recon: [..., H, W, 3] in [0, 1], the decoded frame, or None for a model
      that decodes no pixels (the frame metrics are then skipped).
    alpha_masks: [..., N, H, W, 1], each pixel's weights over the slots (sum
      to 1): the predicted segmentation is their argmax.
    rgb: [..., N, H, W, 3] in [0, 1], each slot's own reconstruction, or None
      for decoders that have none (STEVE generates one frame for all slots).
    targets: {name: [..., H, W, C]} what it reconstructs besides the frames
      (SAVi's 'flow', 'depth'), in the range of their batch fields
      (slotformer_jax/targets.py), or None.
  """

  alpha_masks: jax.Array
  recon: jax.Array | None = None
  rgb: jax.Array | None = None
  targets: dict[str, jax.Array] | None = None


@dataclasses.dataclass(frozen=True)
class Part:
  """One model a slot model trains in stage 1 (SAVi; the dVAE; STEVE).

  Attributes:
    name: its config section, its folder in the stage-1 workdir, its key in
      `Loaded.params` / `Loaded.steps`, and its mode `train_<name>`.
    label: how messages name it ('SAVi').
    module: the linen module the loss applies.
    section: its config section (batch_size, num_train_steps, learning rate,
      schedule, clipping, logging; see `train.trainer.Stage`).
    example: positional example inputs of `module.init` (also its parameter
      shapes); example_kwargs the keyword ones.
    loss: (params, batch, frozen_params, rng) -> (loss, metrics).
    batch_fields: what a training batch holds ('video', 'boxes', 'tokens').
    clip_length: frames per training clip.
    model_fields: the settings that shape its parameters (checked before a
      checkpoint is restored).
    identity_fields: everything that shapes it (its run identity).
    parent: the part it is trained on (its identity is recorded and checked
      as this one's parent), or None.
    reads: the `Derived` data its batches read besides the videos.
    init: 'flax' or 'pytorch' parameter initialisation (modules/
      initializers.py); None: the module's own initialisers only.
    with_batches: wraps the batch iterator (start step -> batches ->
      batches), e.g. the dVAE's temperature schedule; None: as they are.
    images: (params, host batch) -> {name: labelled uint8 picture} for
      TensorBoard, or None.
    transform: (clip of `batch_fields`, generator) -> the clip trained on
      (SAVi's random resized crop; `pipeline.train_batches`), or None.
  """

  name: str
  label: str
  module: nn.Module
  section: ml_collections.ConfigDict
  example: tuple[Any, ...]
  loss: LossFn
  batch_fields: tuple[str, ...]
  clip_length: int
  model_fields: Mapping[str, Any]
  identity_fields: Mapping[str, Any]
  example_kwargs: Mapping[str, Any] = dataclasses.field(default_factory=dict)
  parent: str | None = None
  reads: tuple[str, ...] = ()
  init: str | None = None
  with_batches: Callable[[Iterator[dict[str, np.ndarray]], int],
                         Iterator[dict[str, np.ndarray]]] | None = None
  images: Callable[[Any, dict[str, np.ndarray]],
                   dict[str, np.ndarray]] | None = None
  transform: Callable[[dict[str, np.ndarray], np.random.Generator],
                      dict[str, np.ndarray]] | None = None

  @property
  def mode(self) -> str:
    return f'train_{self.name}'


@dataclasses.dataclass(frozen=True)
class Derived:
  """Data a trained part computes once from the videos, for the next part
  (STEVE's dVAE tokens), stored in the stage-1 workdir under `name/<split>/`.

  Attributes:
    name: its folder and the batch field it adds ('tokens').
    mode: the stage that computes it ('tokenize_frames').
    source: the part whose frozen parameters compute it ('dvae').
    splits: the splits it is computed for (those the next part trains on).
    encode: (source params, uint8 frames [B, C, H, W, 3]) -> [B, C, ...]
      (jitted by the caller, frames split over the devices).
    writer: (directory, num_videos, source step, parent) -> a writer with
      `add(index, out)` / `close()`.
    reader: (directory, video source) -> the video source's items with the
      field `name` added.
    read_meta: directory -> its meta.json (None when absent).
    batch_size: videos per batch (global).
    chunk_length: frames per call.
  """

  name: str
  mode: str
  source: str
  splits: tuple[str, ...]
  encode: Callable[[Any, jax.Array], jax.Array]
  writer: Callable[[str, int, int, dict[str, Any]], Any]
  reader: Callable[[str, Any], Any]
  read_meta: Callable[[str], dict[str, Any] | None]
  batch_size: int
  chunk_length: int


@dataclasses.dataclass(frozen=True)
class Loaded:
  """A trained slot model of a workdir, checked to be one consistent chain.

  Attributes:
    params: {part name: its parameters} (replicated): what `encode` /
      `decode` / `observe` take.
    steps: the step of every part's checkpoint, e.g. {'savi': 4500} or
      {'dvae': 1500, 'steve': 3000}.
    identity: the evaluation identity of stage 1, one entry per part
      ({'savi': {'run_id', 'step', 'fingerprint'}}), as the metrics and
      pictures record it.
    step: the step of the part that encodes (the last).
    slots_parent: what slots extracted by it descend from (the run id and
      step of the part that encodes), as the slots' meta.json records it.
    diverged_at: {part name: update} of the parts in which this seed of a
      several-seed stage 1 diverged (its parameters are its last finite
      ones); empty when none did (always, for one seed).
  """

  params: dict[str, Any]
  steps: dict[str, int]
  identity: dict[str, Any]
  step: int
  slots_parent: dict[str, Any]
  diverged_at: dict[str, int] = dataclasses.field(default_factory=dict)


class SlotModel(abc.ABC):
  """One slot model, configured by a config (savi.py is the reference one).

  Class attributes:
    name: the config's `slot_model` value; the evaluation's reference method
      is `<name>_reconstruction` (its slots of the real future, decoded).
    label: how messages and tables name it ('SAVi').
    mask_source: where the alpha masks of `decode` and `observe` come from
      (the metrics' protocol records it).
    compute_dtypes: the `compute_dtype` values its losses and decoding
      support.
    colour: the explorer's and the curves' colour of its reference method.
  """

  name: ClassVar[str]
  label: ClassVar[str]
  mask_source: ClassVar[str]
  compute_dtypes: ClassVar[tuple[str, ...]] = ('float32', 'bfloat16')
  colour: ClassVar[str] = '#777777'

  def __init__(self, config: ml_collections.ConfigDict):
    self.config = config

  # ---- what it is --------------------------------------------------------

  @property
  @abc.abstractmethod
  def parts(self) -> tuple[Part, ...]:
    """The models it trains, in training order (the last one encodes)."""

  @property
  def derived(self) -> tuple[Derived, ...]:
    """Data a part derives for the next one (none by default)."""
    return ()

  @property
  @abc.abstractmethod
  def slot_shape(self) -> tuple[int, int]:
    """(num_slots N, slot_size D) of the slots it extracts."""

  @property
  def conditioning_fields(self) -> tuple[str, ...]:
    """Video fields whose first frame starts its slots (conditional SAVi:
    ('boxes',)); () for an unconditional model."""
    return ()

  @property
  def decodes_pixels(self) -> bool:
    """Whether `decode` returns frames (`Decoded.recon`): the frame metrics
    (PSNR, SSIM, LPIPS) and the pictures of frames need them."""
    return True

  @property
  def image_loss_fields(self) -> tuple[str, ...]:
    """The video fields SlotFormer's image loss L_I compares the decoded
    rollout with (`image_decoder`): the frames by default; SAVi with other
    targets reads theirs (slotformer_jax/targets.py)."""
    return ('video',)

  def check_config(self, stages: frozenset[str]) -> list[str]:
    """One line per problem of its own settings for the stages a run will
    execute (checked before any work); none by default."""
    del stages
    return []

  def check_data(self, source: Any, split: str) -> None:
    """Raises ConfigError when the videos of `split` (`source`) cannot feed
    it (e.g. conditional SAVi on data without boxes); checked before its
    training starts. Nothing by default."""
    del source, split

  # ---- derived from the parts --------------------------------------------------

  def part(self, name: str) -> Part:
    """Its part `name` ('savi', 'dvae', ...)."""
    for part in self.parts:
      if part.name == name:
        return part
    raise KeyError(f'{self.label} has no part {name!r}; its parts are '
                   f'{[p.name for p in self.parts]}')

  @property
  def stage_labels(self) -> dict[str, str]:
    """{part name: label} ({'dvae': 'dVAE', 'steve': 'STEVE'})."""
    return {part.name: part.label for part in self.parts}

  @property
  def num_train_steps(self) -> dict[str, int]:
    """The configured length of each part, by part name."""
    return {part.name: part.section.num_train_steps for part in self.parts}

  @property
  def stage1_modes(self) -> tuple[str, ...]:
    """Its stage-1 modes in the order `--mode=all` runs them: each part's
    training, each derived data right after the part that computes it."""
    modes = []
    for part in self.parts:
      modes.append(part.mode)
      modes += [d.mode for d in self.derived if d.source == part.name]
    return tuple(modes)

  @property
  def decode_steps(self) -> int:
    """Sequential decoder passes per decoded frame: 1 for a decoder that
    maps slots to pixels at once, the number of tokens for one that
    generates a frame token by token (STEVE). Stages that decode many frames
    say so before they start when it is above 1."""
    return 1

  @property
  def reference_method(self) -> str:
    """The evaluation row of its own slots of the real future, decoded."""
    return f'{self.name}_reconstruction'

  @property
  def reference_label(self) -> str:
    """How tables and pictures name that row ('SAVi recon.')."""
    return f'{self.label} recon.'

  # ---- pure functions of the parameters (the caller jits them) -------------

  def to_model(self, video: jax.Array) -> jax.Array:
    """uint8 frames -> the pixel range its modules (and L_I) work in;
    [-1, 1] by default, as the official models."""
    return frames.frames_to_model(video)

  @abc.abstractmethod
  def encode(self, params: Any, video: jax.Array, rng: jax.Array,
             carry: Any) -> tuple[jax.Array, Any]:
    """uint8 video [B, T, H, W, 3] -> (slots [B, T, N, D], carry).

    `params`: `Loaded.params`. `carry` continues the state of the previous
    chunk of the same videos; a fresh start is None, or, for a model with
    `conditioning_fields`, a dict of those fields of the first frame
    ({'boxes': [B, O, 4]}). `rng` is for stochastic models (same key: same
    slots).
    """

  @abc.abstractmethod
  def decode(self, params: Any, slots: jax.Array,
             presence: jax.Array | None = None) -> Decoded:
    """slots [..., N, D] -> Decoded [...] (frames of predicted slots).

    presence: optional bool [..., N] (broadcast to the slots' leading
    dims): absent slots are dropped from the decoder's softmax over slots
    as if they were not there; their alpha masks are 0.
    """

  @abc.abstractmethod
  def observe(self, params: Any, slots: jax.Array, video: jax.Array,
              carry: Any) -> tuple[jax.Array, jax.Array | None, Any]:
    """Its own account of real frames, for its segmentation quality.

    slots [B, T, N, D] (its extracted slots of `video`), video uint8
    [B, T, H, W, 3] -> (alpha_masks [B, T, N, H, W], recon [B, T, H, W, 3]
    in [0, 1] or None, carry); `carry` continues the previous chunk.
    """

  def image_decoder(self, params: Any) -> tuple[Any, Any] | None:
    """(decoder module, its frozen params) for SlotFormer's image loss L_I
    (the decoder maps slots [..., N, D] to an object with `.recon` in the
    range of `to_model`, or with `reconstructions()`, {target: [..., H, W,
    C]}: 'rgb' in that range, the others in their batch fields'
    (slotformer_jax/targets.py; the fields `image_loss_fields`)), or None
    when the model has no differentiable pixel decoder."""
    del params
    return None
