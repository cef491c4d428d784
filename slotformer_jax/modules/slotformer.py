"""SlotFormer: an autoregressive Transformer over object slots.

Given the slots of the last T frames, the slots are linearly projected to
D_e, a sinusoidal *temporal* position encoding shared by all slots of a frame
is added (so the model stays permutation-equivariant over slots), a Pre-LN
Transformer encoder mixes all T*N tokens, and a linear layer maps the last
frame's N output tokens to the next frame's slots. The rollout feeds each
prediction back into a fixed-size window of T frames.

Growing context (PHYRE): with `max_context` > T the context starts with the
T observed frames and grows by one predicted frame per step up to
`max_context` frames, then slides. The scan keeps a fixed window of
`max_context` frames whose not-yet-filled front is masked out of attention,
so it compiles once; with the newest frame at position 0 the valid frames
get exactly the position codes of an unpadded window of their length (the
official model builds the encoding for `max_context` frames and uses its
last t positions: the same codes).

Shapes: slots [batch, time, num_slots, slot_size].
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotformer_jax.modules import platform
from slotformer_jax.modules.time_loop import scan_with_shared_params
from slotformer_jax.modules.transformer import TransformerEncoder

TEMPORAL = 'temporal'
NAIVE = 'naive'


def sinusoidal_encoding(positions: jax.Array, dim: int) -> jax.Array:
  """[len(positions), dim]: sin features then cos features (dim even)."""
  if dim % 2:
    raise ValueError(f'sinusoidal encoding needs an even size, got {dim}')
  inverse_frequency = 1.0 / (10000.0 ** (jnp.arange(0, dim, 2) / dim))
  angles = positions[:, None].astype(jnp.float32) * inverse_frequency[None]
  return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)


def token_position_encoding(
    num_frames: int, num_slots: int, dim: int, kind: str) -> jax.Array:
  """Position encoding of the T*N tokens, [num_frames * num_slots, dim].

  'temporal': every slot of frame t gets the encoding of t. Frames count
  backwards from the newest (position 0), as the official implementation
  does, so the newest frame's code does not depend on the window length.
  'naive': every token gets its own position (t * N + n): the ablation that
  breaks permutation equivariance among slots.
  """
  if kind == TEMPORAL:
    per_frame = sinusoidal_encoding(jnp.arange(num_frames - 1, -1, -1), dim)
    return jnp.repeat(per_frame, num_slots, axis=0)
  if kind == NAIVE:
    return sinusoidal_encoding(
        jnp.arange(num_frames * num_slots - 1, -1, -1), dim)
  raise ValueError(
      f"positional_encoding must be '{TEMPORAL}' or '{NAIVE}', got {kind!r}")


class NextSlotPredictor(nn.Module):
  """One SlotFormer step: slots of T frames -> slots of the next frame."""

  embed_dim: int = 128
  num_layers: int = 4
  num_heads: int = 8
  mlp_size: int = 512
  dropout_rate: float = 0.0
  positional_encoding: str = TEMPORAL
  residual: bool = False
  layer_norm_epsilon: float = 1e-6
  kernels: str = platform.AUTO

  @nn.compact
  def __call__(self, history: jax.Array, num_valid: jax.Array | None = None,
               *, deterministic: bool = True,
               slot_presence: jax.Array | None = None) -> jax.Array:
    """history [B, T, N, D] -> predicted next slots [B, N, D].

    num_valid: None (all T frames are context) or an int scalar: only the
      last `num_valid` frames are; the others are masked out as keys.
    slot_presence: None or bool [B, N]: an absent slot's tokens (of every
      frame) are masked out as keys, so no other slot attends to it. With
      the temporal position encoding, LayerNorm and the MLP acting per
      token, the present slots' predictions are then exactly those of the
      model given the present slots alone (the counterfactual "remove").
    """
    batch, num_frames, num_slots, slot_size = history.shape
    tokens = nn.Dense(self.embed_dim, name='in_proj')(
        history.reshape(batch, num_frames * num_slots, slot_size))
    tokens = tokens + token_position_encoding(
        num_frames, num_slots, self.embed_dim, self.positional_encoding)
    mask = None
    num_tokens = num_frames * num_slots
    key_valid = jnp.ones((batch, num_tokens), bool)
    if num_valid is not None:
      frame_valid = jnp.arange(num_frames) >= num_frames - num_valid
      key_valid &= jnp.repeat(frame_valid, num_slots)[None]  # [1, T * N]
    if slot_presence is not None:
      # Tokens are frame-major: (frame t, slot n).
      key_valid &= jnp.tile(slot_presence.astype(bool), (1, num_frames))
    if num_valid is not None or slot_presence is not None:
      mask = jnp.broadcast_to(key_valid[:, None, None, :],
                              (batch, 1, num_tokens, num_tokens))
    tokens = TransformerEncoder(
        num_layers=self.num_layers, num_heads=self.num_heads,
        mlp_size=self.mlp_size, dropout_rate=self.dropout_rate,
        pre_norm=True, layer_norm_epsilon=self.layer_norm_epsilon,
        kernels=self.kernels, name='transformer')(tokens, mask, deterministic=deterministic)
    if self.residual:
      # The paper's remark: refine the last input slots rather than predict
      # from scratch, which also keeps the slot order. The refinement starts
      # at zero, so an untrained model is the copy-last-slots baseline.
      refinement = nn.Dense(slot_size, kernel_init=nn.initializers.zeros,
                            name='out_proj')(tokens[:, -num_slots:])
      return history[:, -1] + refinement
    prediction = nn.Dense(slot_size, name='out_proj')(tokens[:, -num_slots:])
    return prediction


class SlotFormer(nn.Module):
  """The dynamics model with its autoregressive rollout.

  Attributes:
    burn_in: T, the number of frames in the context window.
    embed_dim: D_e.
    num_layers: N_T.
    num_heads: 8 in the paper.
    mlp_size: 4 * D_e in the paper.
    dropout_rate: 0 in the paper's description; PyTorch's default of 0.1 in
      the official implementation.
    positional_encoding: 'temporal' (SlotFormer) or 'naive' (ablation).
    residual: add the last input slots to the prediction.
    max_context: 0 (the context is always the last `burn_in` frames) or the
      most frames the context grows to (see the module docstring; 6 in the
      official PHYRE model, whose burn_in is 1).
    layer_norm_epsilon: 1e-6 (flax) or 1e-5 (PyTorch, the official models).
    kernels: the attention's form: 'auto' (explicit on CPU, fused
      `jax.nn.dot_product_attention` on GPU / TPU), 'cpu' or 'accelerator'
      (`slotformer_jax.modules.transformer`).
  """

  burn_in: int = 6
  embed_dim: int = 128
  num_layers: int = 4
  num_heads: int = 8
  mlp_size: int = 512
  dropout_rate: float = 0.0
  positional_encoding: str = TEMPORAL
  residual: bool = False
  max_context: int = 0
  layer_norm_epsilon: float = 1e-6
  kernels: str = platform.AUTO

  def setup(self):
    if self.max_context and self.max_context < self.burn_in:
      raise ValueError(f'max_context={self.max_context} is shorter than '
                       f'burn_in={self.burn_in}; use 0 for a fixed window')
    self.predictor = NextSlotPredictor(
        embed_dim=self.embed_dim, num_layers=self.num_layers,
        num_heads=self.num_heads, mlp_size=self.mlp_size,
        dropout_rate=self.dropout_rate,
        positional_encoding=self.positional_encoding, residual=self.residual,
        layer_norm_epsilon=self.layer_norm_epsilon, kernels=self.kernels)

  @property
  def context_length(self) -> int:
    """The most frames the model conditions on."""
    return max(self.burn_in, self.max_context)

  def predict_next(self, history: jax.Array, *,
                   deterministic: bool = True) -> jax.Array:
    """history [B, T, N, D] -> next slots [B, N, D].

    T is `burn_in`, or up to `max_context` frames with a growing context.
    """
    if (history.ndim != 4
        or not self.burn_in <= history.shape[1] <= self.context_length):
      raise ValueError(
          f'SlotFormer.predict_next expects slots [batch, T, num_slots, '
          f'slot_size] with {self.burn_in} <= T <= {self.context_length}, '
          f'got {history.shape}')
    return self.predictor(history, deterministic=deterministic)

  def __call__(self, burn_in_slots: jax.Array, num_steps: int,
               teacher_slots: jax.Array | None = None, *,
               deterministic: bool = True,
               slot_presence: jax.Array | None = None,
               frozen: jax.Array | None = None) -> jax.Array:
    """Rolls out `num_steps` future frames.

    Args:
      burn_in_slots: [B, burn_in, N, D], the observed slots.
      num_steps: K, the number of frames to predict.
      teacher_slots: optional [B, K, N, D] ground-truth future slots. When
        given (teacher forcing), the window is filled with them instead of
        the model's own predictions.
      deterministic: disables dropout (needs a 'dropout' RNG otherwise).
      slot_presence: optional bool [B, N]; absent slots are removed from
        every frame of the context (masked out of attention, see
        `NextSlotPredictor`). Their own rows of the output are meaningless.
      frozen: optional bool [B, N]; a frozen slot keeps its last observed
        value in every predicted frame (and so in the context the others
        are predicted from).

    Returns:
      [B, K, N, D] predicted slots.
    """
    self._check_window(burn_in_slots)
    growing = self.context_length > self.burn_in
    window = burn_in_slots
    if growing:
      # Not-yet-observed frames at the front, masked out until filled.
      padding = jnp.zeros(
          (burn_in_slots.shape[0], self.context_length - self.burn_in,
           *burn_in_slots.shape[2:]), burn_in_slots.dtype)
      window = jnp.concatenate([padding, burn_in_slots], axis=1)

    last_observed = burn_in_slots[:, -1]

    def step(predictor, carry, teacher):
      window, num_valid = carry
      prediction = predictor(window, num_valid if growing else None,
                             deterministic=deterministic,
                             slot_presence=slot_presence)
      if frozen is not None:
        prediction = jnp.where(frozen[:, :, None], last_observed, prediction)
      fed_back = prediction if teacher is None else teacher
      window = jnp.concatenate([window[:, 1:], fed_back[:, None]], axis=1)
      num_valid = jnp.minimum(num_valid + 1, self.context_length)
      return (window, num_valid), prediction

    rollout = scan_with_shared_params(
        step, self,
        split_rngs={'params': False, 'dropout': True},
        in_axes=1, out_axes=1, length=num_steps)
    _, predictions = rollout(
        self.predictor, (window, jnp.asarray(self.burn_in, jnp.int32)),
        teacher_slots)
    return predictions

  def _check_window(self, slots: jax.Array):
    if slots.ndim != 4 or slots.shape[1] != self.burn_in:
      raise ValueError(
          f'SlotFormer expects slots [batch, {self.burn_in}, num_slots, '
          f'slot_size], got {slots.shape}')
