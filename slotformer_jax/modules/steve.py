"""STEVE (Singh et al., 2022) as SlotFormer uses it for Physion.

    STEVE(encoder=CNNEncoder(...), initializer=LearnedSlots(...),
          frame_step=FrameStep(
              corrector=SlotAttention(..., return_attention=True),
              predictor=SlotTransition(..., lstm_size=...)),
          decoder=TokenDecoder(...), token_grid=(h, w),
          feature_grid=(h', w'))

The slot encoder is SAVi's parts without a pixel decoder, run by SAVi's own
time loop (`modules.savi.encode_frames`); the last Slot Attention iteration's
attention (softmax over slots) is kept as per-slot masks. The decoder is an
autoregressive Transformer over the frozen dVAE's tokens of the frame,
conditioned on its slots (`TokenDecoder`): the dVAE is trained first, so
STEVE only learns to predict its tokens. Its parameter names are those of
the flat STEVE this replaced (docs/steve.md, "Parameter tree").

Shapes: video [batch, time, height, width, 3] in [-1, 1];
slots [batch, time, num_slots, slot_size];
masks [batch, time, num_slots, feature_height, feature_width];
tokens int [batch, time, num_tokens].
"""

from __future__ import annotations

import flax.linen as nn
import jax

from slotformer_jax.modules.savi import FrameStep
from slotformer_jax.modules.savi import SAViCarry
from slotformer_jax.modules.savi import encode_frames
from slotformer_jax.modules.token_decoder import TokenDecoder


class STEVE(nn.Module):
  """STEVE's slot encoder + token decoder. See the module docstring.

  Attributes:
    encoder, initializer, frame_step: SAVi's parts (its CNN encoder, learned
      initial slots, Slot Attention returning its attention as the masks +
      the Transformer-LSTM predictor), run by SAVi's own time loop
      (`modules.savi.encode_frames`); STEVE has no pixel decoder.
    decoder: the token decoder; its `num_tokens` is h * w of `token_grid`.
    token_grid: (h, w) of a frame's dVAE token map.
    feature_grid: (h', w') of the encoder's feature map, the resolution of
      the masks.
  """

  encoder: nn.Module
  initializer: nn.Module
  frame_step: FrameStep
  decoder: TokenDecoder
  token_grid: tuple[int, int]
  feature_grid: tuple[int, int]

  def setup(self):
    # The initialiser's parameters keep the flat STEVE's top-level names.
    nn.share_scope(self, self.initializer)

  def initial_carry(self, batch_size: int,
                    boxes: jax.Array | None = None) -> SAViCarry:
    """The learned first-frame slots (the same in every video) + zero LSTM."""
    del boxes  # unconditional
    slots = self.initializer(batch_size, None)
    return slots, self.frame_step.initial_state(slots)

  def encode(self, video: jax.Array, carry: SAViCarry | None = None):
    """video [B, T, H, W, 3] -> (slots [B, T, N, D], masks [B, T, N, h', w'],
    carry). `carry` continues a video from an earlier chunk (None: fresh)."""
    frames, carry = encode_frames(self, video, carry)
    masks = frames.attention.reshape(*frames.attention.shape[:3],
                                     *self.feature_grid)
    return frames.slots, masks, carry

  def token_logits(self, slots: jax.Array, tokens: jax.Array, *,
                   deterministic: bool = True) -> jax.Array:
    """slots [..., N, D], tokens int [..., L] -> logits [..., L, vocab]
    (teacher forcing: position i sees tokens < i)."""
    lead = slots.shape[:-2]
    logits = self.decoder(slots.reshape(-1, *slots.shape[-2:]),
                          tokens.reshape(-1, tokens.shape[-1]),
                          deterministic=deterministic)
    return logits.reshape(*lead, *logits.shape[1:])

  def __call__(self, video: jax.Array, tokens: jax.Array, *,
               deterministic: bool = True):
    """video [B, T, H, W, 3], tokens int [B, T, L] -> (logits [B, T, L, V],
    slots [B, T, N, D], masks [B, T, N, h', w'])."""
    slots, masks, _ = self.encode(video)
    logits = self.token_logits(slots, tokens, deterministic=deterministic)
    return logits, slots, masks
