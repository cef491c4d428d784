"""Per-frame encoders with a soft position embedding (SAVi / Slot Attention).

`CNNEncoder`: conv layers -> position embedding -> per-position LayerNorm +
MLP (every SAVi and STEVE of this project). `FrameEncoder`: any backbone
(`ConvStack`, SAVi++'s `resnet.ResNet`) -> the same position embedding and
MLP -> optionally ReLU(Dense) and a Transformer over the positions (SAVi's
`FrameEncoder` with `output_transform=Transformer`, as SAVi++ uses it).
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotformer_jax.modules.transformer import TransformerEncoder

SAME = 'same'
PYTORCH = 'pytorch'
PADDINGS = (SAME, PYTORCH)


def conv_padding(kind: str, kernel_size: int):
  """The padding argument of `nn.Conv` for an odd kernel.

  'same': XLA's SAME, which for stride 2 pads (K//2 - 1, K//2) on an even
  input (e.g. (1, 2) for K=5). 'pytorch': K//2 on both sides, PyTorch's
  `Conv2d(padding=K // 2)` of the official models; at stride 1 the two agree,
  at stride 2 SAME samples the image one pixel further down and right.
  """
  if kind == SAME:
    return 'SAME'
  if kind == PYTORCH:
    half = kernel_size // 2
    return ((half, half), (half, half))
  raise ValueError(f'padding must be one of {PADDINGS}, got {kind!r}')


def feature_grid(resolution: Sequence[int],
                 strides: Sequence[int]) -> tuple[int, int]:
  """(h', w') of `CNNEncoder`'s feature map for frames of `resolution`.

  ceil(size / stride) per layer, for both paddings ('same' by definition;
  'pytorch' pads K // 2 on each side of an odd kernel, the same count).
  """
  height, width = resolution
  for stride in strides:
    height, width = -(-height // stride), -(-width // stride)
  return height, width


def coordinate_grid(height: int, width: int) -> jax.Array:
  """[height, width, 4] grid of (y, x, 1 - y, 1 - x), each in [0, 1]."""
  ys = jnp.linspace(0.0, 1.0, height)
  xs = jnp.linspace(0.0, 1.0, width)
  grid = jnp.stack(jnp.meshgrid(ys, xs, indexing='ij'), axis=-1)
  return jnp.concatenate([grid, 1.0 - grid], axis=-1)


class SoftPositionEmbedding(nn.Module):
  """Adds a learned linear projection of the coordinate grid to a feature map.

  Input and output [..., height, width, channels].
  """

  @nn.compact
  def __call__(self, features: jax.Array) -> jax.Array:
    height, width, channels = features.shape[-3:]
    embedding = nn.Dense(channels, name='dense')(coordinate_grid(height, width))
    return features + embedding


def conv_layers(x: jax.Array, features: Sequence[int], kernel_size: int,
                strides: Sequence[int], padding: str) -> jax.Array:
  """The conv layers `conv_<i>` of `CNNEncoder` / `ConvStack`, declared in
  the calling module: ReLU after all but the last. x [B, H, W, C] -> [B,
  h', w', features[-1]] (`feature_grid`)."""
  if len(strides) != len(features):
    raise ValueError(
        f'encoder strides {tuple(strides)} and features '
        f'{tuple(features)} must have the same length')
  for i, (channels, stride) in enumerate(zip(features, strides)):
    x = nn.Conv(channels, (kernel_size, kernel_size),
                strides=(stride, stride),
                padding=conv_padding(padding, kernel_size),
                name=f'conv_{i}')(x)
    if i < len(features) - 1:
      x = nn.relu(x)
  return x


def position_mlp(x: jax.Array, *, mlp_size: int, output_size: int,
                 layer_norm_epsilon: float) -> jax.Array:
  """The encoders' common tail, declared in the calling module:
  `position_embedding`, flatten, per position `norm` and the MLP
  (`mlp_hidden` of mlp_size, ReLU, `mlp_out` of output_size).

  x [B, h, w, C] -> [B, h * w, output_size].
  """
  x = SoftPositionEmbedding(name='position_embedding')(x)
  batch, num_positions = x.shape[0], x.shape[1] * x.shape[2]
  # Per-position LayerNorm + MLP on a [B*H'*W', C] view: the same math;
  # XLA:CPU ran these layers' gradients 1.7x slower on the 3-D view
  # (docs/experiments/performance.md).
  x = x.reshape(batch * num_positions, x.shape[-1])
  x = nn.LayerNorm(epsilon=layer_norm_epsilon, name='norm')(x)
  x = nn.Dense(mlp_size, name='mlp_hidden')(x)
  x = nn.relu(x)
  x = nn.Dense(output_size, name='mlp_out')(x)
  return x.reshape(batch, num_positions, output_size)


class CNNEncoder(nn.Module):
  """Per-frame CNN -> position embedding -> flatten -> LayerNorm + MLP.

  Attributes:
    features: channels of each conv layer; ReLU after all but the last.
    kernel_size: square kernel of every conv layer.
    strides: stride of each conv layer (2 on the first layer for 128x128
      inputs in the paper's Physion / PHYRE settings).
    output_size: D_enc, the size of each output feature vector.
    padding: 'same' or 'pytorch' (see `conv_padding`).
    layer_norm_epsilon: 1e-6 (flax) or 1e-5 (PyTorch, the official models).
    mlp_size: the MLP's hidden size; None: output_size (SAVi's MOVi models:
      64 hidden, 32 out).
  """

  features: Sequence[int] = (64, 64, 64, 64)
  kernel_size: int = 5
  strides: Sequence[int] = (1, 1, 1, 1)
  output_size: int = 128
  padding: str = SAME
  layer_norm_epsilon: float = 1e-6
  mlp_size: int | None = None

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    """images [B, H, W, 3] -> features [B, H' * W', output_size]."""
    x = conv_layers(images, self.features, self.kernel_size, self.strides,
                    self.padding)
    return position_mlp(x, mlp_size=self.mlp_size or self.output_size,
                        output_size=self.output_size,
                        layer_norm_epsilon=self.layer_norm_epsilon)


class ConvStack(nn.Module):
  """`CNNEncoder`'s conv layers alone, as a `FrameEncoder` backbone:
  images [B, H, W, C] -> [B, h', w', features[-1]] (`feature_grid`)."""

  features: Sequence[int] = (64, 64, 64, 64)
  kernel_size: int = 5
  strides: Sequence[int] = (1, 1, 1, 1)
  padding: str = SAME

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    return conv_layers(images, self.features, self.kernel_size, self.strides,
                       self.padding)


class FrameEncoder(nn.Module):
  """backbone -> position embedding -> flatten -> LayerNorm + MLP ->
  [ReLU(Dense(qkv_size)) -> Transformer]: SAVi++'s encoder with
  `backbone=resnet.ResNet()` and a 4-layer Pre-LN Transformer.

  Attributes:
    backbone: images [B, H, W, C] -> feature map [B, h, w, C'].
    output_size: of the position MLP.
    mlp_size: its hidden size; None: output_size.
    transformer: over the h * w positions (`TransformerEncoder`, its width
      qkv_size), or None: the MLP's output is the encoder's.
    qkv_size: the width the MLP's output is projected to (Dense + ReLU)
      before the Transformer.
    layer_norm_epsilon: of the position MLP's LayerNorm.
  """

  backbone: nn.Module
  output_size: int
  mlp_size: int | None = None
  transformer: TransformerEncoder | None = None
  qkv_size: int = 64
  layer_norm_epsilon: float = 1e-6

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    """images [B, H, W, C] -> features [B, h * w, qkv_size] with a
    Transformer, else [B, h * w, output_size]."""
    x = self.backbone(images)
    x = position_mlp(x, mlp_size=self.mlp_size or self.output_size,
                     output_size=self.output_size,
                     layer_norm_epsilon=self.layer_norm_epsilon)
    if self.transformer is None:
      return x
    x = nn.relu(nn.Dense(self.qkv_size, name='transformer_in')(x))
    return self.transformer(x)
