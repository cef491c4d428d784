"""Where a video's first slots come from: SAVi's and STEVE's initialisers.

Three kinds, each a module that knows its `num_slots` and `slot_size` and is
called as `initializer(batch_size, boxes)` -> slots [B, num_slots, slot_size]:
  LearnedSlots      one learned vector per slot (SlotFormer's SAVi, STEVE):
                    slot n starts the same way in every video;
  GaussianSlots     every slot drawn from one learned Gaussian (the original
                    Slot Attention; 'sample' RNG): slots are exchangeable and
                    cannot specialise by position;
  CoordinateSlots   conditional SAVi: slot 1 + i embeds the first frame's box
                    i (or its centre), slot 0 the background.

The parameter names ('initial_slots', 'initial_slots_mean' /
'initial_slots_log_sigma', 'slot_init_mlp') are those of the checkpoints and
of the official-weight converters: SAVi shares its own scope with the
initialiser (`nn.share_scope`), so they sit at the top of SAVi's tree.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

LEARNED = 'learned'
GAUSSIAN = 'gaussian'
BOXES = 'boxes'
POINTS = 'points'
INITIAL_SLOTS = (LEARNED, GAUSSIAN, BOXES, POINTS)
CONDITIONAL = (BOXES, POINTS)


class LearnedSlots(nn.Module):
  """One learned N(0, 1)-initialised vector per slot, the same in every video.

  Attributes:
    num_slots, slot_size: N and D.
  """

  num_slots: int
  slot_size: int

  @nn.compact
  def __call__(self, batch_size: int,
               boxes: jax.Array | None = None) -> jax.Array:
    """-> slots [batch_size, N, D]; `boxes` is ignored."""
    del boxes
    slots = self.param('initial_slots', nn.initializers.normal(stddev=1.0),
                       (self.num_slots, self.slot_size))
    return jnp.broadcast_to(slots, (batch_size, *slots.shape))


class GaussianSlots(nn.Module):
  """Every slot an independent draw from one learned diagonal Gaussian.

  Attributes:
    num_slots, slot_size: N and D.
  """

  num_slots: int
  slot_size: int

  @nn.compact
  def __call__(self, batch_size: int,
               boxes: jax.Array | None = None) -> jax.Array:
    """-> slots [batch_size, N, D] from the 'sample' RNG; `boxes` ignored."""
    del boxes
    mean = self.param('initial_slots_mean', nn.initializers.normal(stddev=1.0),
                      (self.slot_size,))
    log_sigma = self.param('initial_slots_log_sigma',
                           nn.initializers.zeros_init(), (self.slot_size,))
    noise = jax.random.normal(self.make_rng('sample'),
                              (batch_size, self.num_slots, self.slot_size))
    return mean + jnp.exp(log_sigma) * noise


def conditioning_coordinates(boxes: jax.Array, num_slots: int,
                             kind: str) -> jax.Array:
  """The per-slot coordinates conditional SAVi embeds.

  boxes [B, O, 4] (ymin, xmin, ymax, xmax) normalised, an absent object all
  zeros (SAVi's padding box) -> [B, num_slots, 4] ('boxes') or [B,
  num_slots, 2] ('points': the box centres (y, x)). Slot 0 gets a zero
  background box (as SAVi's `prepend_background`), slot 1 + i object row i,
  rows past the objects zero boxes (as SAVi pads to its max_instances).
  """
  batch, rows = boxes.shape[:2]
  if rows + 1 > num_slots:
    raise ValueError(f'conditional SAVi needs a slot per box row plus one '
                     f'for the background: {rows} box rows, {num_slots} '
                     'slots')
  coords = jnp.concatenate([
      jnp.zeros((batch, 1, 4), boxes.dtype), boxes,
      jnp.zeros((batch, num_slots - rows - 1, 4), boxes.dtype)], axis=1)
  if kind == POINTS:
    coords = jnp.stack([(coords[..., 0] + coords[..., 2]) / 2,
                        (coords[..., 1] + coords[..., 3]) / 2], axis=-1)
  return coords


class CoordinateSlotInit(nn.Module):
  """Initial slots from coordinates: Linear -> ReLU -> Linear, per slot.

  SAVi's conditional initialiser (`CoordinateEncoderStateInit` with an MLP
  of hidden size 256 and no LayerNorm in its MOVi configs).
  """

  slot_size: int
  hidden_size: int = 256

  @nn.compact
  def __call__(self, coords: jax.Array) -> jax.Array:
    """coords [B, N, 4 or 2] -> slots [B, N, slot_size]."""
    hidden = nn.relu(nn.Dense(self.hidden_size, name='hidden')(coords))
    return nn.Dense(self.slot_size, name='out')(hidden)


class CoordinateSlots(nn.Module):
  """Conditional SAVi: slots from the first frame's boxes or their centres.

  Attributes:
    num_slots, slot_size: N and D.
    kind: 'boxes' (embed [ymin, xmin, ymax, xmax]) or 'points' (the centre).
    hidden_size: of the embedding MLP (`CoordinateSlotInit`).
  """

  num_slots: int
  slot_size: int
  kind: str = BOXES
  hidden_size: int = 256

  @nn.compact
  def __call__(self, batch_size: int,
               boxes: jax.Array | None = None) -> jax.Array:
    """boxes [B, O, 4] of the first frame (O + 1 <= N) -> slots [B, N, D]
    (see `conditioning_coordinates`)."""
    if boxes is None:
      raise ValueError(f"initial_slots={self.kind!r} needs the first "
                       "frame's boxes")
    del batch_size  # the boxes have it
    coords = conditioning_coordinates(boxes.astype(jnp.float32),
                                      self.num_slots, self.kind)
    return CoordinateSlotInit(self.slot_size, self.hidden_size,
                              name='slot_init_mlp')(coords)


def slot_initializer(kind: str, num_slots: int, slot_size: int
                     ) -> LearnedSlots | GaussianSlots | CoordinateSlots:
  """The initialiser of `kind`, one of INITIAL_SLOTS."""
  if kind == LEARNED:
    return LearnedSlots(num_slots, slot_size)
  if kind == GAUSSIAN:
    return GaussianSlots(num_slots, slot_size)
  if kind in CONDITIONAL:
    return CoordinateSlots(num_slots, slot_size, kind=kind)
  raise ValueError(f'initial_slots must be one of {INITIAL_SLOTS}, got '
                   f'{kind!r}')
