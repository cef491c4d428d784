"""Spatial-broadcast slot decoder with transposed-convolution upsampling.

On CPU, every stride-s transposed convolution is evaluated as its exact
sub-pixel re-parameterisation: one stride-1 convolution per output phase
with the kernel taps that reach that phase, interleaved (depth-to-space).
XLA:CPU runs strided transposed convolutions an order of magnitude slower
than plain convolutions (docs/performance.md, "Kernels per platform"). On
GPU / TPU the layers
are the plain input-dilated `lax.conv_general_dilated` that XLA maps onto
the platform's own kernels; the choice is made when the computation is
lowered (`slotformer_jax.modules.platform`). The parameters are the
transposed convolution's own kernel whatever the form, so the layer *is* a
transposed convolution (same parameter count, initialisation and outputs),
only evaluated differently.
"""

from __future__ import annotations

from collections.abc import Sequence
import math

import flax.linen as nn
from flax import struct
import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax.modules import convolution
from slotformer_jax.modules import platform
from slotformer_jax.modules.encoders import SoftPositionEmbedding

# The target whose reconstruction is `DecodedSlots.recon` (the frames).
RGB = 'rgb'


def _sub_pixel_taps(kernel_size: int, stride: int, padding: int):
  """Which transposed-conv kernel tap feeds each (phase, offset) pair.

  A transposed convolution computes out[s*i + k - p] += x[i] * w[k]. Writing
  the output index as s*m + r (phase r in [0, s)) gives
  out[s*m + r] = sum_d x[m + d] * w[r + p - s*d], i.e. for every phase a
  small ordinary convolution over the input offsets d in [d_min, d_max].

  Returns:
    taps: int array [stride, num_offsets]; taps[r, d - d_min] is the kernel
      index k, or `kernel_size` (a zero row appended by the caller) where no
      tap exists.
    d_min, d_max: the range of input offsets.
  """
  d_min = min(math.ceil((r + padding - kernel_size + 1) / stride)
              for r in range(stride))
  d_max = max((r + padding) // stride for r in range(stride))
  taps = np.full((stride, d_max - d_min + 1), kernel_size, dtype=np.int32)
  for r in range(stride):
    for d in range(d_min, d_max + 1):
      k = r + padding - stride * d
      if 0 <= k < kernel_size:
        taps[r, d - d_min] = k
  return taps, d_min, d_max


def sub_pixel_conv_transpose(
    x: jax.Array, kernel: jax.Array, bias: jax.Array | None, stride: int
) -> jax.Array:
  """A 'same' transposed convolution evaluated phase by phase (the CPU form).

  Matches PyTorch's `ConvTranspose2d(kernel_size=K, stride=s, padding=K // 2,
  output_padding=s - 1)` (the layer of the official SAVi decoder), whose
  output is exactly s times larger than its input.

  Every output phase (r_y, r_x) -- the pixels s*m + r -- is an ordinary
  stride-1 convolution of the input with the kernel taps that reach it (for
  K=5, s=2: 3x3, 3x2, 2x3 and 2x2 taps, 25 in all), and the s*s results are
  interleaved. Only real taps are multiplied: the single-convolution form
  (every phase padded to the largest tap count, s*s*C_out channels) spends
  1.44x the multiply-adds on zeros and ran ~1.8x slower forward and ~1.5x
  slower backward on XLA:CPU (docs/performance.md).

  Args:
    x: [B, H, W, C_in].
    kernel: [K, K, C_in, C_out], w[ky, kx, c_in, c_out] as in the definition
      out[s*i + ky - p, s*j + kx - p] += x[i, j] * w[ky, kx].
    bias: [C_out] or None.
    stride: s.

  Returns:
    [B, s*H, s*W, C_out].
  """
  kernel_size, _, _, c_out = kernel.shape
  taps, d_min, _ = _sub_pixel_taps(kernel_size, stride, kernel_size // 2)
  batch, height, width, _ = x.shape

  def phase_taps(phase):
    """[(input offset d, kernel index k)] of one phase, d increasing."""
    return [(d_min + j, int(k)) for j, k in enumerate(taps[phase])
            if k < kernel_size]

  rows = []
  for phase_y in range(stride):
    taps_y = phase_taps(phase_y)
    columns = []
    for phase_x in range(stride):
      taps_x = phase_taps(phase_x)
      if not taps_y or not taps_x:  # kernel smaller than the stride
        columns.append(jnp.zeros((batch, height, width, c_out), x.dtype))
        continue
      phase_kernel = kernel[np.array([k for _, k in taps_y])][
          :, np.array([k for _, k in taps_x])]
      # out[m] = sum_d x[m + d] * w[k(d)]: a correlation over offsets
      # d_first..d_last, i.e. padding -d_first below and d_last above.
      padding = ((-taps_y[0][0], taps_y[-1][0]),
                 (-taps_x[0][0], taps_x[-1][0]))
      columns.append(convolution.conv2d_cpu(x, phase_kernel, padding))
    rows.append(jnp.stack(columns, axis=3))  # [B, H, W, s_x, C_out]
  out = jnp.stack(rows, axis=2)  # [B, H, s_y, W, s_x, C_out]
  out = out.reshape(batch, height * stride, width * stride, c_out)
  if bias is not None:
    out = out + bias
  return out


def dilated_conv_transpose(x: jax.Array, kernel: jax.Array,
                           stride: int) -> jax.Array:
  """The same transposed convolution as `sub_pixel_conv_transpose` (no
  bias), in the plain form: the input dilated by `stride` correlated with
  the spatially flipped kernel, padding (K - 1 - K // 2) below and that +
  s - 1 above (PyTorch's output_padding). What `lax.conv_transpose` and
  `nn.ConvTranspose` lower to, and what GPU / TPU compilers have kernels
  for.

  x [B, H, W, C_in], kernel [K, K, C_in, C_out] (K odd) -> [B, s*H, s*W,
  C_out].
  """
  kernel_size = kernel.shape[0]
  low = kernel_size - 1 - kernel_size // 2
  padding = ((low, low + stride - 1), (low, low + stride - 1))
  return jax.lax.conv_general_dilated(
      x, kernel[::-1, ::-1], window_strides=(1, 1), padding=padding,
      lhs_dilation=(stride, stride),
      dimension_numbers=('NHWC', 'HWIO', 'NHWC'))


def conv_transpose(x: jax.Array, kernel: jax.Array, stride: int,
                   kernels: str = platform.AUTO) -> jax.Array:
  """`sub_pixel_conv_transpose` on CPU, `dilated_conv_transpose` elsewhere
  (`kernels`: see `slotformer_jax.modules.platform`); no bias.

  x [B, H, W, C_in], kernel [K, K, C_in, C_out] -> [B, s*H, s*W, C_out].
  """
  return platform.by_platform(
      kernels, lambda x, k: sub_pixel_conv_transpose(x, k, None, stride),
      lambda x, k: dilated_conv_transpose(x, k, stride), x, kernel,
      layer=platform.CONV_TRANSPOSE)


class SubPixelConvTranspose(nn.Module):
  """Stride-s 'same' transposed convolution (`conv_transpose`): phase by
  phase on CPU, the input-dilated convolution on accelerators.

  Attributes:
    features: C_out.
    kernel_size: K (odd).
    stride: s.
    kernels: 'auto', 'cpu' or 'accelerator' (`modules.platform`).
  """

  features: int
  kernel_size: int = 5
  stride: int = 2
  kernels: str = platform.AUTO

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x [B, H, W, C_in] -> [B, s*H, s*W, features]."""
    kernel, bias = convolution.odd_kernel_params(
        self, self.kernel_size, x.shape[-1], self.features)
    return conv_transpose(x, kernel, self.stride, self.kernels) + bias


class PointwiseConv(nn.Module):
  """A 1x1 convolution computed as a matmul over the channel axis.

  Same parameters as `nn.Conv(features, (1, 1))` (kernel [1, 1, C_in,
  C_out], bias [C_out], same initialisers), so checkpoints are
  interchangeable. XLA:CPU's convolution path is ~3x slower than a matmul for
  this shape in the decoder's training step (docs/experiments/performance.md,
  "The 1x1 readout as a matmul").
  """

  features: int
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x [..., C_in] -> [..., features]."""
    kernel = self.param('kernel', self.kernel_init,
                        (1, 1, x.shape[-1], self.features))
    bias = self.param('bias', nn.initializers.zeros_init(), (self.features,))
    return jnp.einsum('...c,cd->...d', x, kernel[0, 0]) + bias


@struct.dataclass
class DecodedSlots:
  """Decoder outputs. Leading dims `...` are whatever the slots had.

  Attributes:
    recon: [..., H, W, 3] the alpha-composited frame, or None when RGB is
      not one of the decoder's targets.
    rgb: [..., N, H, W, 3] each slot's own reconstruction, or None (as
      recon).
    alpha_masks: [..., N, H, W, 1] softmax over slots of the alpha logits.
    segmentation: [..., H, W] int32 argmax slot of the alpha masks.
    targets: {name: [..., H, W, C]} the alpha-composited reconstruction of
      every target other than RGB ('flow', 'depth'), or None when RGB is
      the only one.
  """

  recon: jax.Array | None
  rgb: jax.Array | None
  alpha_masks: jax.Array
  segmentation: jax.Array
  targets: dict[str, jax.Array] | None = None

  def reconstructions(self) -> dict[str, jax.Array]:
    """{target name: [..., H, W, C]} of every target, RGB ('rgb') first
    when it is one."""
    out = {} if self.recon is None else {RGB: self.recon}
    out.update(self.targets or {})
    return out


class SpatialBroadcastDecoder(nn.Module):
  """Decodes every slot independently into its targets (RGB by default) +
  alpha, then composites.

  Attributes:
    output_resolution: (H, W) of the frames.
    broadcast_resolution: grid each slot is tiled onto (8x8; 16x16 on PHYRE).
    features: channels of the transposed-conv layers. Layers upsample by 2
      until the output resolution is reached, the rest keep the resolution.
    kernel_size: of every transposed-conv layer.
    kernels: 'auto' (the CPU forms on CPU, the plain convolutions on GPU /
      TPU), 'cpu' or 'accelerator' (`slotformer_jax.modules.platform`).
    targets: ((name, channels), ...) of what it reconstructs (SAVi's
      `Readout`: one linear head per target on every slot's features, the
      alpha masks shared): 'rgb' fills `recon` / `rgb`, the others
      `DecodedSlots.targets`. The first target's head and the alpha logit
      are one pointwise layer, `readout` (channels + 1 outputs, the alpha
      last): an RGB decoder keeps the tree it always had, and a decoder of
      one other target has the same tree. Every further target t has its
      own, `readout_<t>`.
  """

  output_resolution: tuple[int, int] = (64, 64)
  broadcast_resolution: tuple[int, int] = (8, 8)
  features: Sequence[int] = (64, 64, 64, 64)
  kernel_size: int = 5
  kernels: str = platform.AUTO
  targets: tuple[tuple[str, int], ...] = ((RGB, 3),)

  @nn.compact
  def __call__(self, slots: jax.Array,
               presence: jax.Array | None = None) -> DecodedSlots:
    """slots [..., N, D] -> DecodedSlots (see its docstring for shapes).

    presence: optional bool [..., N]; an absent slot's alpha logits are
      dropped from the softmax over slots (`composite`), so the frame is
      decoded as if the slot were not there.
    """
    *batch_shape, num_slots, slot_size = slots.shape
    height, width = self.broadcast_resolution
    x = slots.reshape(-1, 1, 1, slot_size)
    x = jnp.broadcast_to(x, (x.shape[0], height, width, slot_size))
    x = SoftPositionEmbedding(name='position_embedding')(x)
    for i, channels in enumerate(self.features):
      if x.shape[1] < self.output_resolution[0]:
        x = SubPixelConvTranspose(channels, self.kernel_size, stride=2,
                                  kernels=self.kernels,
                                  name=f'deconv_{i}')(x)
      else:
        # A stride-1 'same' transposed convolution is an ordinary one.
        x = convolution.SameConv(channels, self.kernel_size,
                                 kernels=self.kernels,
                                 name=f'deconv_{i}')(x)
      x = nn.relu(x)
    if tuple(x.shape[1:3]) != tuple(self.output_resolution):
      raise ValueError(
          f'decoder produces {tuple(x.shape[1:3])} from broadcast '
          f'{tuple(self.broadcast_resolution)} with {len(self.features)} '
          f'layers, expected {tuple(self.output_resolution)}; change '
          'broadcast_resolution or the number of layers')
    _check_targets(self.targets)
    features = x
    (first, first_channels), *others = self.targets
    x = PointwiseConv(first_channels + 1, name='readout')(x)
    x = x.reshape(*batch_shape, num_slots, *x.shape[1:])
    per_slot = {first: x[..., :first_channels]}
    alpha_logits = x[..., first_channels:]
    for name, channels in others:
      values = PointwiseConv(channels, name=f'readout_{name}')(features)
      per_slot[name] = values.reshape(*batch_shape, num_slots,
                                      *values.shape[1:])
    rgb = per_slot.pop(RGB, None)
    if rgb is not None:
      recon, alpha_masks = composite(rgb, alpha_logits, presence)
    else:
      recon, alpha_masks = None, slot_weights(alpha_logits, presence)
    composites = {name: jnp.sum(values * alpha_masks, axis=-4)
                  for name, values in per_slot.items()}
    segmentation = jnp.argmax(alpha_masks[..., 0], axis=-3).astype(jnp.int32)
    return DecodedSlots(recon=recon, rgb=rgb, alpha_masks=alpha_masks,
                        segmentation=segmentation,
                        targets=composites or None)


def _check_targets(targets: Sequence[tuple[str, int]]) -> None:
  names = [name for name, _ in targets]
  if (not names or len(set(names)) != len(names)
      or any(channels < 1 for _, channels in targets)):
    raise ValueError('decoder targets must be distinct (name, channels >= 1) '
                     f'pairs, at least one, got {tuple(targets)!r}')


def slot_weights(alpha_logits: jax.Array,
                 presence: jax.Array | None = None) -> jax.Array:
  """The alpha masks: the softmax over slots of alpha_logits [..., N, H, W,
  1] -> [..., N, H, W, 1]. An absent slot (presence, optional bool [...,
  N], False) has its logits replaced by the dtype's lowest value: its alpha
  is exactly 0 and the others' renormalise among themselves, the frame the
  present slots alone decode to (no NaN if every slot is absent: the
  weights are then uniform)."""
  if presence is not None:
    lowest = jnp.finfo(alpha_logits.dtype).min
    alpha_logits = jnp.where(presence[..., None, None, None], alpha_logits,
                             lowest)
  return jax.nn.softmax(alpha_logits, axis=-4)


def composite(rgb: jax.Array, alpha_logits: jax.Array,
              presence: jax.Array | None = None
              ) -> tuple[jax.Array, jax.Array]:
  """Alpha compositing of per-slot images: the softmax over slots
  (`slot_weights`).

  rgb [..., N, H, W, 3], alpha_logits [..., N, H, W, 1], presence optional
  bool [..., N] -> (recon [..., H, W, 3], alpha_masks [..., N, H, W, 1]).
  """
  alpha_masks = slot_weights(alpha_logits, presence)
  return jnp.sum(rgb * alpha_masks, axis=-4), alpha_masks
