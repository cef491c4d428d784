"""Spatial-broadcast slot decoder with sub-pixel upsampling.

XLA:CPU runs strided transposed convolutions an order of magnitude slower
than plain convolutions, so every stride-s transposed convolution here is
computed as its exact sub-pixel re-parameterisation: one stride-1 convolution
producing s*s*C channels followed by depth-to-space. The parameters are the
transposed convolution's own kernel, so the layer *is* a transposed
convolution (same parameter count, initialisation and outputs), only evaluated
differently.
"""

from __future__ import annotations

from collections.abc import Sequence
import math

import flax.linen as nn
from flax import struct
import jax
import jax.numpy as jnp
import numpy as np

from slotformer_jax.modules.encoders import SoftPositionEmbedding


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
  """A 'same' transposed convolution evaluated as sub-pixel convolution.

  Matches PyTorch's `ConvTranspose2d(kernel_size=K, stride=s, padding=K // 2,
  output_padding=s - 1)` (the layer of the official SAVi decoder), whose
  output is exactly s times larger than its input.

  Args:
    x: [B, H, W, C_in].
    kernel: [K, K, C_in, C_out], w[ky, kx, c_in, c_out] as in the definition
      out[s*i + ky - p, s*j + kx - p] += x[i, j] * w[ky, kx].
    bias: [C_out] or None.
    stride: s.

  Returns:
    [B, s*H, s*W, C_out].
  """
  kernel_size, _, c_in, c_out = kernel.shape
  taps, d_min, d_max = _sub_pixel_taps(kernel_size, stride, kernel_size // 2)
  padded = jnp.pad(kernel, ((0, 1), (0, 1), (0, 0), (0, 0)))
  offsets_by_phase = taps.T  # [num_offsets, stride]
  # [offsets_y, offsets_x, phase_y, phase_x, C_in, C_out]
  sub_kernel = padded[offsets_by_phase[:, None, :, None],
                      offsets_by_phase[None, :, None, :]]
  num_offsets = taps.shape[1]
  sub_kernel = sub_kernel.transpose(0, 1, 4, 2, 3, 5).reshape(
      num_offsets, num_offsets, c_in, stride * stride * c_out)
  out = jax.lax.conv_general_dilated(
      x, sub_kernel, window_strides=(1, 1),
      padding=((-d_min, d_max), (-d_min, d_max)),
      dimension_numbers=('NHWC', 'HWIO', 'NHWC'))
  batch, height, width, _ = out.shape
  out = out.reshape(batch, height, width, stride, stride, c_out)
  out = out.transpose(0, 1, 3, 2, 4, 5).reshape(
      batch, height * stride, width * stride, c_out)
  if bias is not None:
    out = out + bias
  return out


class SubPixelConvTranspose(nn.Module):
  """Stride-s 'same' transposed convolution (see `sub_pixel_conv_transpose`)."""

  features: int
  kernel_size: int = 5
  stride: int = 2

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    if self.kernel_size % 2 != 1:
      raise ValueError(f'kernel_size must be odd, got {self.kernel_size}')
    kernel = self.param(
        'kernel', nn.initializers.lecun_normal(),
        (self.kernel_size, self.kernel_size, x.shape[-1], self.features))
    bias = self.param('bias', nn.initializers.zeros_init(), (self.features,))
    return sub_pixel_conv_transpose(x, kernel, bias, self.stride)


@struct.dataclass
class DecodedSlots:
  """Decoder outputs. Leading dims `...` are whatever the slots had.

  Attributes:
    recon: [..., H, W, 3] the alpha-composited frame.
    rgb: [..., N, H, W, 3] each slot's own reconstruction.
    alpha_masks: [..., N, H, W, 1] softmax over slots of the alpha logits.
    segmentation: [..., H, W] int32 argmax slot of the alpha masks.
  """

  recon: jax.Array
  rgb: jax.Array
  alpha_masks: jax.Array
  segmentation: jax.Array


class SpatialBroadcastDecoder(nn.Module):
  """Decodes every slot independently into RGB + alpha, then composites.

  Attributes:
    output_resolution: (H, W) of the frames.
    broadcast_resolution: grid each slot is tiled onto (8x8; 16x16 on PHYRE).
    features: channels of the transposed-conv layers. Layers upsample by 2
      until the output resolution is reached, the rest keep the resolution.
    kernel_size: of every transposed-conv layer.
  """

  output_resolution: tuple[int, int] = (64, 64)
  broadcast_resolution: tuple[int, int] = (8, 8)
  features: Sequence[int] = (64, 64, 64, 64)
  kernel_size: int = 5

  @nn.compact
  def __call__(self, slots: jax.Array) -> DecodedSlots:
    """slots [..., N, D] -> DecodedSlots (see its docstring for shapes)."""
    *batch_shape, num_slots, slot_size = slots.shape
    height, width = self.broadcast_resolution
    x = slots.reshape(-1, 1, 1, slot_size)
    x = jnp.broadcast_to(x, (x.shape[0], height, width, slot_size))
    x = SoftPositionEmbedding(name='position_embedding')(x)
    for i, channels in enumerate(self.features):
      if x.shape[1] < self.output_resolution[0]:
        x = SubPixelConvTranspose(channels, self.kernel_size, stride=2,
                                  name=f'deconv_{i}')(x)
      else:
        # A stride-1 'same' transposed convolution is an ordinary one.
        x = nn.Conv(channels, (self.kernel_size, self.kernel_size),
                    padding='SAME', name=f'deconv_{i}')(x)
      x = nn.relu(x)
    if tuple(x.shape[1:3]) != tuple(self.output_resolution):
      raise ValueError(
          f'decoder produces {tuple(x.shape[1:3])} from broadcast '
          f'{tuple(self.broadcast_resolution)} with {len(self.features)} '
          f'layers, expected {tuple(self.output_resolution)}; change '
          'broadcast_resolution or the number of layers')
    x = nn.Conv(4, (1, 1), name='readout')(x)
    x = x.reshape(*batch_shape, num_slots, *x.shape[1:])
    rgb, alpha_logits = x[..., :3], x[..., 3:]
    alpha_masks = jax.nn.softmax(alpha_logits, axis=-4)
    recon = jnp.sum(rgb * alpha_masks, axis=-4)
    segmentation = jnp.argmax(alpha_masks[..., 0], axis=-3).astype(jnp.int32)
    return DecodedSlots(recon=recon, rgb=rgb, alpha_masks=alpha_masks,
                        segmentation=segmentation)
