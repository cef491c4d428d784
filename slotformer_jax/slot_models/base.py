"""The slot-model interface: what differs between SAVi and STEVE, only that.

A slot model is stage 1 of the pipeline. It is trained on videos (its own
stages, e.g. `train_savi`, or `train_dvae` -> `tokenize_frames` ->
`train_steve`), turns a video into slots, and turns slots back into frames and
alpha masks. Everything above it -- slot extraction, stage 2 (SlotFormer /
Slot-LSTM), the video-prediction evaluation, the pictures, the downstream tasks
-- reads slots and frames only through this interface, so a new slot model is
one new file next to `savi.py` and `steve.py`, registered in `__init__.py`.

Shapes at this boundary:
  video        uint8 [B, T, H, W, 3]
  slots        float32 [B, T, N, D] (N, D = `slot_shape`)
  Decoded      recon [..., H, W, 3] in [0, 1], alpha_masks [..., N, H, W, 1]
               (softmax over the N slots), rgb [..., N, H, W, 3] or None
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping
import dataclasses
import logging
from typing import Any, ClassVar

from flax import struct
import jax
from jax.sharding import Mesh
import ml_collections

from slotformer_jax import workdir as workdir_lib
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import UserError

logger = logging.getLogger(__name__)

# A stage of `--mode`: (config, workdir, mesh) -> None.
StageFn = Callable[[ml_collections.ConfigDict, str, Mesh], Any]


@struct.dataclass
class Decoded:
  """Frames decoded from slots; leading dims `...` are the slots' own.

  Attributes:
    recon: [..., H, W, 3] in [0, 1], the decoded frame.
    alpha_masks: [..., N, H, W, 1], each pixel's weights over the slots (sum
      to 1): the predicted segmentation is their argmax.
    rgb: [..., N, H, W, 3] in [0, 1], each slot's own reconstruction, or None
      for decoders that have none (STEVE generates one frame for all slots).
  """

  recon: jax.Array
  alpha_masks: jax.Array
  rgb: jax.Array | None = None


@dataclasses.dataclass(frozen=True)
class Loaded:
  """A trained slot model of a workdir, checked to be one consistent chain.

  Attributes:
    params: what `encode` / `decode` / `observe` take (replicated).
    steps: the step of every stage-1 checkpoint, e.g. {'savi': 4500} or
      {'dvae': 1500, 'steve': 3000}.
    identity: the evaluation identity of stage 1, one entry per stage-1
      model ({'savi': {'run_id', 'step', 'fingerprint'}}), as the metrics and
      pictures record it.
    step: the step of the model that encodes.
    slots_parent: what slots extracted by it descend from (the run id and
      step of the model that encodes), as the slots' meta.json records it.
  """

  params: Any
  steps: dict[str, int]
  identity: dict[str, Any]
  step: int
  slots_parent: dict[str, Any]


class SlotModel(abc.ABC):
  """One slot model, built from a config (see savi.py for the reference one).

  Class attributes:
    name: the config's `slot_model` value and the config section of the model
      that encodes ('savi', 'steve'); the evaluation's reference method is
      `<name>_reconstruction` (its slots of the real future, decoded).
    label: how messages and tables name it ('SAVi').
    stage_labels: the label of each of its stage-1 models, by the keys of
      `Loaded.steps` and `num_train_steps` ({'dvae': 'dVAE', ...}).
    stage1: its training stages in the order `--mode=all` runs them,
      {mode: (config, workdir, mesh) -> None}.
    mask_source: where the alpha masks of `decode` and `observe` come from.
    compute_dtypes: the `compute_dtype` values its decoding supports.
    conditioning_fields: video fields whose first frame starts its slots
      (conditional SAVi: ('boxes',)); () for an unconditional model.
  """

  name: ClassVar[str]
  label: ClassVar[str]
  stage1: ClassVar[Mapping[str, StageFn]]
  # How messages name each stage-1 model, by `Loaded.steps` key.
  stage_labels: ClassVar[Mapping[str, str]]
  # Where the alpha masks of `decode` / `observe` come from (the metrics'
  # protocol records it).
  mask_source: ClassVar[str]
  compute_dtypes: ClassVar[tuple[str, ...]] = ('float32', 'bfloat16')

  def __init__(self, config: ml_collections.ConfigDict):
    self.config = config

  # ---- what it is --------------------------------------------------------

  @property
  def conditioning_fields(self) -> tuple[str, ...]:
    return ()

  @property
  @abc.abstractmethod
  def slot_shape(self) -> tuple[int, int]:
    """(num_slots N, slot_size D) of the slots it extracts."""

  @property
  @abc.abstractmethod
  def num_train_steps(self) -> dict[str, int]:
    """The configured length of each stage-1 model, by `Loaded.steps` key."""

  # ---- a workdir's trained model -------------------------------------------

  @abc.abstractmethod
  def check_identity(self, workdir: str) -> dict[str, Any]:
    """The identity of the model that encodes, checked against this config
    and (for chains) against its parents, without reading parameters.

    Raises:
      UserError: never trained, or trained with other settings.
    """

  @abc.abstractmethod
  def chain(self, workdir: str, steps: dict[str, int]
            ) -> tuple[dict[str, Any], dict[str, Any]]:
    """(identity entries, slots parent) of its stage-1 models at `steps`
    (the `Loaded.identity` and `Loaded.slots_parent` of checkpoints at those
    steps), checked to descend from each other.

    Raises:
      UserError: never trained, trained with other settings, or a part was
        trained on another parent.
    """

  @abc.abstractmethod
  def load(self, workdir: str, mesh: Mesh) -> Loaded:
    """The trained stage 1 of `workdir` (its `stage1_workdir`), checked.

    Raises:
      UserError: missing, trained with another architecture or settings, or
        its parts do not descend from each other.
    """

  # ---- pure functions of the parameters (the caller jits them) -------------

  @abc.abstractmethod
  def encode(self, params: Any, video: jax.Array, rng: jax.Array,
             carry: Any) -> tuple[jax.Array, Any]:
    """uint8 video [B, T, H, W, 3] -> (slots [B, T, N, D], carry).

    `carry` continues the state of the previous chunk of the same videos;
    a fresh start is None, or, for a model with `conditioning_fields`, a
    dict of those fields of the first frame ({'boxes': [B, O, 4]}). `rng` is
    for stochastic models (same key: same slots).
    """

  @abc.abstractmethod
  def decode(self, params: Any, slots: jax.Array,
             presence: jax.Array | None = None) -> Decoded:
    """slots [..., N, D] -> Decoded [...] (frames of predicted slots).

    presence: optional bool [..., N] (broadcast to the slots' leading
    dims): absent slots are dropped from the decoder's softmax over slots
    (SAVi's alpha masks, STEVE's cross-attention), as if they were not
    there; their alpha masks are 0.
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
    """(decoder module, its frozen params) for SlotFormer's image loss L_I,
    or None when the model has no differentiable pixel decoder."""
    del params
    return None

  # ---- shared ----------------------------------------------------------------

  def check_compute_dtype(self) -> None:
    """Refuses a `compute_dtype` the decoding does not implement."""
    dtype = self.config.get('compute_dtype', 'float32')
    if dtype not in self.compute_dtypes:
      raise ConfigError(
          f'compute_dtype={dtype!r} is not implemented for slot_model='
          f"{self.name!r}; use --config.compute_dtype="
          f'{self.compute_dtypes[0]}')

  @property
  def reference_method(self) -> str:
    """The evaluation row of its own slots of the real future, decoded."""
    return f'{self.name}_reconstruction'


# --------------------------------------------------------------------------
# A stage 1 read from another workdir (`config.stage1_workdir`)
# --------------------------------------------------------------------------


def check_foreign_stage1(slot_model: SlotModel, workdir: str,
                         mesh: Mesh) -> Loaded:
  """`stage1_workdir` is read-only: its slot model must be complete and made
  with this config's stage-1 settings, its slots complete and made by it.

  Raises:
    UserError: what is missing or different, and where to fix it.
  """
  config = slot_model.config
  other = workdir_lib.stage1_workdir(config, workdir)
  loaded = slot_model.load(workdir, mesh)
  for key, step in loaded.steps.items():
    total = slot_model.num_train_steps[key]
    if step < total:
      raise UserError(
          f'stage 1 in stage1_workdir={other} is incomplete '
          f'({slot_model.stage_labels[key]} step {step} of {total}); this '
          'run never trains there. Finish it with its own run: python -m '
          f'slotformer_jax.main --config=<its config> --workdir={other}')
  for split in config.extraction.splits:
    workdir_lib.check_slots_current(config, workdir, split,
                                    loaded.slots_parent, slot_model.label)
  return loaded


def uses_foreign_stage1(slot_model: SlotModel, workdir: str, mesh: Mesh,
                        what: str) -> bool:
  """True (after checking it) when stage 1 is another workdir's: the stage
  `what` then has nothing to do here."""
  if not workdir_lib.uses_foreign_stage1(slot_model.config, workdir):
    return False
  check_foreign_stage1(slot_model, workdir, mesh)
  logger.info('%s: using the read-only stage 1 in %s', what,
              workdir_lib.stage1_workdir(slot_model.config, workdir))
  return True
