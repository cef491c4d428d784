"""SAVi: Slot Attention for Video (Kipf et al., 2022), composed from parts.

    SAVi(encoder=CNNEncoder(...),
         initializer=LearnedSlots | GaussianSlots | CoordinateSlots,
         frame_step=FrameStep(
             corrector=SlotAttention(...),
             predictor=SlotTransition | ResidualMLPTransition,
             posterior_head=GaussianSlotSampler(...) | None),
         decoder=SpatialBroadcastDecoder(...) | None)

Per frame t: CNN features h_t = encoder(x_t); S~'_t = head(S~_t) (the
posterior head's mean, or a sample for stochastic SAVi); slots S_t =
SlotAttention(S~'_t, h_t); the next frame's initial slots S~_{t+1} =
f_trans(S_t); S~_1 comes from the initialiser (`modules/slot_init.py`). The
time loop is one `nn.scan` of `FrameStep` over the frames (STEVE runs it with
`decoder=None`). `slot_models.savi.build_savi` builds the parts from
`config.savi`. Which choices reproduce each official model, and the
parameter tree (the flat SAVi's names, which checkpoints rely on):
docs/official_architectures.md.

Shapes: video [batch, time, height, width, 3] in [-1, 1]; encoder features
[batch * time, num_inputs, feature_size]; slots [batch, time, num_slots,
slot_size]; kl [batch, time, num_slots]; attention [batch, time, num_slots,
num_inputs] (the corrector's last iteration, softmax over slots).
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
from flax import struct
import jax
import jax.numpy as jnp

from slotformer_jax.modules.decoders import DecodedSlots
from slotformer_jax.modules.slot_attention import SlotAttention
from slotformer_jax.modules.stochastic_savi import GaussianSlotSampler
from slotformer_jax.modules.time_loop import scan_with_shared_params

# (initial slots of the next frame [B, N, D], the predictor's state: an LSTM
# carry or ()).
SAViCarry = tuple[jax.Array, Any]


@struct.dataclass
class FrameOutput:
  """What the time loop yields per frame (leading [B] in a step, [B, T]
  after the loop).

  Attributes:
    slots: [..., N, D] the corrected slots S_t.
    kl: [..., N] KL of the posterior head's Gaussian (zeros without a head
      or when deterministic): stochastic SAVi's loss term.
    attention: [..., N, M] the corrector's last-iteration attention,
      softmax over slots (STEVE's masks), or None when the corrector does
      not return it.
  """

  slots: jax.Array
  kl: jax.Array
  attention: jax.Array | None


class FrameStep(nn.Module):
  """One frame of SAVi: posterior head, correct, predict.

  Scanned over time by `encode_frames`; its parameters are shared by
  all frames.

  Attributes:
    corrector: Slot Attention (initial slots [B, N, D], features [B, M, C]
      -> slots [B, N, D]); with `return_attention` it also yields the
      attention, kept in `FrameOutput.attention`.
    predictor: f_trans (`modules/transitions.py`): (slots, state) -> (next
      initial slots, state).
    posterior_head: optional `GaussianSlotSampler` applied to the initial
      slots before the corrector (every official SAVi has one; the
      deterministic ones keep its mean).
  """

  corrector: SlotAttention
  predictor: nn.Module
  posterior_head: GaussianSlotSampler | None = None

  def initial_state(self, slots: jax.Array) -> Any:
    """The predictor's state for a video's first frame (slots [B, N, D])."""
    return self.predictor.initial_state(slots)

  def __call__(self, carry: SAViCarry, features: jax.Array, *,
               deterministic: bool = True) -> tuple[SAViCarry, FrameOutput]:
    """carry, features [B, M, C] -> (carry, FrameOutput of this frame)."""
    initial_slots, predictor_state = carry
    if self.posterior_head is not None:
      initial_slots, kl = self.posterior_head(initial_slots)
    else:
      kl = jnp.zeros(initial_slots.shape[:-1], initial_slots.dtype)
    corrected = self.corrector(initial_slots, features)
    if self.corrector.return_attention:
      slots, attention = corrected
    else:
      slots, attention = corrected, None
    next_slots, predictor_state = self.predictor(
        slots, predictor_state, deterministic=deterministic)
    return ((next_slots, predictor_state),
            FrameOutput(slots=slots, kl=kl, attention=attention))


def encode_frames(model: nn.Module, video: jax.Array,
                  carry: SAViCarry | None = None, *,
                  deterministic: bool = True,
                  boxes: jax.Array | None = None
                  ) -> tuple[FrameOutput, SAViCarry]:
  """SAVi's time loop, for any module built from its parts (SAVi, STEVE):
  `model.encoder` per frame, then `model.frame_step` scanned over time
  from `model.initial_carry`. Called from a method of `model`.

  video [B, T, H, W, 3] -> (FrameOutput with leading [B, T], carry).
  `carry` continues a video from an earlier chunk (None: start fresh, from
  `boxes` [B, O, 4] of the first frame for conditional SAVi).
  `deterministic=False` enables the predictor's dropout ('dropout' RNG);
  stochastic heads and Gaussian initial slots draw from 'sample'.
  """
  batch, time = video.shape[:2]
  features = model.encoder(video.reshape(batch * time, *video.shape[2:]))
  features = features.reshape(batch, time, *features.shape[1:])
  if carry is None:
    carry = model.initial_carry(batch, boxes)
  scan = scan_with_shared_params(
      lambda step, c, x: step(c, x, deterministic=deterministic), model,
      split_rngs={'params': False, 'sample': True, 'dropout': True},
      in_axes=1, out_axes=1)
  carry, frames = scan(model.frame_step, carry, features)
  return frames, carry


@struct.dataclass
class SAViOutput:
  """slots [B, T, N, D]; kl [B, T, N] (zeros unless stochastic); what the
  decoder makes of every frame's slots, leading [B, T] (`DecodedSlots` for
  the spatial-broadcast decoder), or None (not asked for, or no decoder);
  the carry that continues the video in a later call."""

  slots: jax.Array
  kl: jax.Array
  decoded: DecodedSlots | Any | None
  carry: SAViCarry


class SAVi(nn.Module):
  """SAVi from its parts. See the module docstring.

  Attributes:
    encoder: frames [B, H, W, 3] -> features [B, M, C] (`CNNEncoder`).
    initializer: (batch_size, boxes) -> the first frame's initial slots
      [B, N, D] (`modules/slot_init.py`); its variables live in SAVi's own
      scope, so its parameter names sit at the top of the tree.
    frame_step: the per-frame corrector + predictor (`FrameStep`).
    decoder: slots [..., N, D] -> `DecodedSlots` (`SpatialBroadcastDecoder`)
      or another decoder's output (e.g. features), or None for a model whose
      decoder is elsewhere (STEVE's token decoder): `__call__` then returns
      slots without decoding.
  """

  encoder: nn.Module
  initializer: nn.Module
  frame_step: FrameStep
  decoder: nn.Module | None = None

  def setup(self):
    # The initialiser's parameters keep the flat SAVi's top-level names.
    nn.share_scope(self, self.initializer)

  def initial_carry(self, batch_size: int,
                    boxes: jax.Array | None = None) -> SAViCarry:
    """The first frame's initial slots [B, N, D] (from the first frame's
    boxes [B, O, 4] for conditional SAVi, which needs them; ignored
    otherwise) and the predictor's initial state."""
    slots = self.initializer(batch_size, boxes)
    return slots, self.frame_step.initial_state(slots)

  def encode_frames(self, video: jax.Array, carry: SAViCarry | None = None,
                    *, deterministic: bool = True,
                    boxes: jax.Array | None = None
                    ) -> tuple[FrameOutput, SAViCarry]:
    """video [B, T, H, W, 3] -> (FrameOutput with leading [B, T], carry):
    `encode_frames` below."""
    return encode_frames(self, video, carry, deterministic=deterministic,
                         boxes=boxes)

  def encode(self, video: jax.Array, carry: SAViCarry | None = None, *,
             deterministic: bool = True, boxes: jax.Array | None = None):
    """video [B, T, H, W, 3] -> (slots [B,T,N,D], kl [B,T,N], carry); see
    `encode_frames`."""
    frames, carry = self.encode_frames(video, carry,
                                       deterministic=deterministic,
                                       boxes=boxes)
    return frames.slots, frames.kl, carry

  def decode(self, slots: jax.Array) -> DecodedSlots | Any:
    """slots [..., N, D] -> the decoder's output with leading [...]."""
    if self.decoder is None:
      raise ValueError('this SAVi has no decoder (decoder=None)')
    return self.decoder(slots)

  def __call__(self, video: jax.Array, carry: SAViCarry | None = None,
               decode: bool = True, *,
               deterministic: bool = True,
               boxes: jax.Array | None = None) -> SAViOutput:
    slots, kl, carry = self.encode(video, carry, deterministic=deterministic,
                                   boxes=boxes)
    decoded = (self.decode(slots)
               if decode and self.decoder is not None else None)
    return SAViOutput(slots=slots, kl=kl, decoded=decoded, carry=carry)
