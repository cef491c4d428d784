"""Aloe (Ding et al., 2021) over object slots, as SlotFormer's CLEVRER VQA model.

One sequence per (video, question[, choice]):

  [CLS] | slots of T frames (T * N tokens) | words of the text (L tokens)

Slot and word tokens carry type and question/choice flags, are projected to
``d_model`` and get learned positions; a Pre-LN Transformer encoder with a
key-padding mask over the words feeds [CLS] to an MLP of open-answer
logits, or (one sequence per choice) to one logit per choice. Positions
``'token'`` (official) give every token its own vector; ``'frame'`` shares
one among a frame's slots, which makes the answer invariant to the slot
order within a frame. The token features: docs/vqa.md, "Aloe".

Shapes: slots [batch, time, num_slots, slot_size]; open questions: tokens
[batch, L]; multiple choice: tokens [batch, num_choices, L]. Token ids come
from :mod:`slotformer_jax.data.vqa` (L = L_q + L_c; the first L_q words are
the question, the rest the choice).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotformer_jax.modules import platform
from slotformer_jax.modules.transformer import TransformerEncoder

TOKEN = 'token'
FRAME = 'frame'
# The fixed 2-d flags concatenated to the token features (the official
# model's non-trainable `text_token`, `vision_token`, `cls_token` (the
# open-question flag, not [CLS]), `mc_question_token`, `mc_choice_token`).
TEXT_FLAG = (1.0, 0.0)
VISION_FLAG = (0.0, 1.0)
OPEN_QUESTION_FLAG = (0.0, 1.0)
MC_QUESTION_FLAG = (1.0, 0.0)
MC_CHOICE_FLAG = (0.0, 1.0)


def _with_flag(x: jax.Array, flag: jax.Array) -> jax.Array:
  """Concatenates ``flag`` [..., 2] (broadcast) to the features of ``x``."""
  flag = jnp.broadcast_to(flag, x.shape[:-1] + (flag.shape[-1],))
  return jnp.concatenate([x, flag.astype(x.dtype)], axis=-1)


class Aloe(nn.Module):
  """Aloe's reasoning Transformer over slots and question words.

  Attributes:
    vocab_size: question vocabulary size (id 0 = PAD).
    num_answers: open-answer classes (id 0 = PAD, never a target).
    num_frames: T, frames of slots per sequence.
    num_slots: N, slots per frame.
    text_length: L = max question length + max choice length.
    question_length: L_q, the question part of multiple-choice tokens.
    d_model: token width (official: (word_dim + 2 + 2) * num_heads = 144).
    word_dim: word embedding size (official: 14).
    num_layers, num_heads, mlp_size: Transformer (official 12, 8, 512).
    head_size: hidden width of both answer MLPs (official 128).
    dropout_rate: PyTorch's nn.TransformerEncoderLayer default, 0.1.
    positions: 'token' (official) or 'frame' (see the module docstring).
    layer_norm_epsilon: of the Transformer's LayerNorms: 1e-6 (flax) or
      1e-5 (PyTorch's, the official model's; configs/clevrer_vqa.py).
    kernels: the attention's form, 'auto' (explicit on CPU, fused on GPU /
      TPU when no attention dropout applies), 'cpu' or 'accelerator'
      (`slotformer_jax.modules.transformer`).
  """

  vocab_size: int
  num_answers: int
  num_frames: int
  num_slots: int
  text_length: int
  question_length: int
  d_model: int = 144
  word_dim: int = 14
  num_layers: int = 12
  num_heads: int = 8
  mlp_size: int = 512
  head_size: int = 128
  dropout_rate: float = 0.1
  positions: str = TOKEN
  layer_norm_epsilon: float = 1e-6
  kernels: str = platform.AUTO

  def setup(self):
    if self.positions not in (TOKEN, FRAME):
      raise ValueError(f"positions must be '{TOKEN}' or '{FRAME}', got "
                       f'{self.positions!r}')
    if not 0 < self.question_length <= self.text_length:
      raise ValueError('need 0 < question_length <= text_length')
    self.word_embedding = nn.Embed(self.vocab_size, self.word_dim,
                                   name='word_embedding')
    self.text_projection = nn.Dense(self.d_model, name='text_projection')
    self.slot_projection = nn.Dense(self.d_model, name='slot_projection')
    self.cls = self.param('cls', nn.initializers.zeros, (self.d_model,))
    zeros = nn.initializers.zeros
    if self.positions == TOKEN:
      length = 1 + self.num_frames * self.num_slots + self.text_length
      self.position = self.param('position', zeros, (length, self.d_model))
    else:
      self.cls_position = self.param('cls_position', zeros, (self.d_model,))
      self.frame_position = self.param('frame_position', zeros,
                                       (self.num_frames, self.d_model))
      self.text_position = self.param('text_position', zeros,
                                      (self.text_length, self.d_model))
    self.encoder = TransformerEncoder(
        num_layers=self.num_layers, num_heads=self.num_heads,
        mlp_size=self.mlp_size, dropout_rate=self.dropout_rate,
        pre_norm=True, layer_norm_epsilon=self.layer_norm_epsilon,
        kernels=self.kernels, name='encoder')
    self.open_head = nn.Sequential(
        [nn.Dense(self.head_size), nn.relu, nn.Dense(self.num_answers)],
        name='open_head')
    self.choice_head = nn.Sequential(
        [nn.Dense(self.head_size), nn.relu, nn.Dense(1)], name='choice_head')

  def _positions(self) -> jax.Array:
    """[1 + T*N + L, d_model]."""
    if self.positions == TOKEN:
      return self.position
    return jnp.concatenate([
        self.cls_position[None],
        jnp.repeat(self.frame_position, self.num_slots, axis=0),
        self.text_position], axis=0)

  def encode(self, slots: jax.Array, tokens: jax.Array, pad_mask: jax.Array,
             text_flags: jax.Array, *, deterministic: bool = True
             ) -> jax.Array:
    """The [CLS] output, [B, d_model].

    Args:
      slots: [B, T, N, D].
      tokens: int [B, L]; pad_mask: bool [B, L], True at padding.
      text_flags: [L, 2], the question/choice flag of each word position.
    """
    b, t, n, d = slots.shape
    if (t, n) != (self.num_frames, self.num_slots):
      raise ValueError(f'slots have {t} frames x {n} slots, the model '
                       f'{self.num_frames} x {self.num_slots}')
    if tokens.shape[-1] != self.text_length:
      raise ValueError(f'{tokens.shape[-1]} words, expected '
                       f'{self.text_length}')
    # [B, T*N, D] (D spelled out: B may be 0, a kind of question not drawn)
    vision = _with_flag(slots.reshape(b, t * n, d), jnp.array(VISION_FLAG))
    vision = self.slot_projection(vision)
    words = _with_flag(self.word_embedding(tokens), text_flags)
    words = self.text_projection(_with_flag(words, jnp.array(TEXT_FLAG)))
    cls = jnp.broadcast_to(self.cls.astype(vision.dtype), (b, 1, self.d_model))
    x = jnp.concatenate([cls, vision, words], axis=1) + self._positions()
    keep = jnp.concatenate(
        [jnp.ones((b, 1 + t * n), bool), jnp.logical_not(pad_mask)], axis=1)
    # A padded word is never attended to (as a key); its own output is
    # unused.
    attention_mask = nn.make_attention_mask(jnp.ones_like(keep), keep)
    x = self.encoder(x, deterministic=deterministic, mask=attention_mask)
    return x[:, 0]

  def open_logits(self, slots: jax.Array, tokens: jax.Array,
                  pad_mask: jax.Array, *, deterministic: bool = True
                  ) -> jax.Array:
    """Open (descriptive) questions: tokens [B, L] -> logits [B, answers]."""
    flags = jnp.broadcast_to(jnp.array(OPEN_QUESTION_FLAG),
                             (self.text_length, 2))
    cls = self.encode(slots, tokens, pad_mask, flags,
                      deterministic=deterministic)
    return self.open_head(cls)

  def choice_logits(self, slots: jax.Array, tokens: jax.Array,
                    pad_mask: jax.Array, *, deterministic: bool = True
                    ) -> jax.Array:
    """Multiple choice: tokens [B, C, L] -> one logit per choice [B, C]."""
    b, c, length = tokens.shape
    flags = jnp.concatenate([
        jnp.broadcast_to(jnp.array(MC_QUESTION_FLAG),
                         (self.question_length, 2)),
        jnp.broadcast_to(jnp.array(MC_CHOICE_FLAG),
                         (length - self.question_length, 2))], axis=0)
    per_choice = jnp.repeat(slots, c, axis=0)  # [B*C, T, N, D]
    cls = self.encode(per_choice, tokens.reshape(b * c, length),
                      pad_mask.reshape(b * c, length), flags,
                      deterministic=deterministic)
    return self.choice_head(cls).reshape(b, c)

  def __call__(self, open_slots: jax.Array, open_tokens: jax.Array,
               open_pad_mask: jax.Array, choice_slots: jax.Array,
               choice_tokens: jax.Array, choice_pad_mask: jax.Array, *,
               deterministic: bool = True) -> tuple[jax.Array, jax.Array]:
    """Both kinds at once: (open logits [Bo, A], choice logits [Bc, C])."""
    return (self.open_logits(open_slots, open_tokens, open_pad_mask,
                             deterministic=deterministic),
            self.choice_logits(choice_slots, choice_tokens, choice_pad_mask,
                               deterministic=deterministic))
