"""SAVi++'s ResNet backbone: ResNet v1 of basic blocks, group norm, the
small-input stem (google-research/slot-attention-video,
`savi/modules/resnet.py`, as `savi++_conditional.py` builds it:
`ResNet34(norm_type='group', small_inputs=True, num_classes=None)`).

    stem     3x3 conv, stride 1, no bias -> GroupNorm (no ReLU and no max
             pool after it: the small-input stem of SAVi's code)
    stage s  `stage_sizes[s]` basic blocks of width * 2^s channels; the
             first block of stages 2.. has stride 2
    block    3x3 conv (stride) -> GN -> ReLU -> 3x3 conv -> GN (scale
             initialised to 0) + the input (through a strided 1x1 conv + GN
             where the shape changes) -> ReLU

Every GroupNorm has 32 groups (flax's default, SAVi's); no classifier head.
Shapes: images [B, H, W, C] -> features [B, H / 8, W / 8, width * 8]
(128x128 frames: a 16x16 map of 512 channels for ResNet-34).
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax

# Basic blocks per stage of ResNet-34 (He et al., 2015, Table 1).
RESNET34_STAGES = (3, 4, 6, 3)


class BasicBlock(nn.Module):
  """Two 3x3 convolutions with a residual connection (ResNet-18 / 34).

  Attributes:
    features: output channels.
    stride: of the first convolution (and of the projection, when the
      shape changes).
    num_groups: of every GroupNorm.
  """

  features: int
  stride: int = 1
  num_groups: int = 32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x [B, H, W, C] -> [B, H / stride, W / stride, features]."""
    conv = lambda name, size, stride: nn.Conv(
        self.features, (size, size), strides=(stride, stride),
        use_bias=False, name=name)
    norm = lambda name, **kw: nn.GroupNorm(num_groups=self.num_groups,
                                           name=name, **kw)
    residual = x
    y = conv('conv_1', 3, self.stride)(x)
    y = nn.relu(norm('norm_1')(y))
    y = conv('conv_2', 3, 1)(y)
    # Zero-initialised scale: every block starts as the identity (SAVi's,
    # after "Fixup", Zhang et al., 2019).
    y = norm('norm_2', scale_init=nn.initializers.zeros)(y)
    if residual.shape != y.shape:
      residual = norm('projection_norm')(
          conv('projection', 1, self.stride)(residual))
    return nn.relu(residual + y)


class ResNet(nn.Module):
  """ResNet v1 of basic blocks with the small-input stem, no head.

  Attributes:
    stage_sizes: basic blocks per stage (ResNet-34: RESNET34_STAGES).
    width: channels of the stem and the first stage (doubled per stage).
    num_groups: of every GroupNorm.
  """

  stage_sizes: Sequence[int] = RESNET34_STAGES
  width: int = 64
  num_groups: int = 32

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    """images [B, H, W, C] -> feature map [B, H / 2^(S-1), W / 2^(S-1),
    width * 2^(S-1)] for S stages (SAME padding: sizes round up)."""
    x = nn.Conv(self.width, (3, 3), use_bias=False, name='stem_conv')(images)
    x = nn.GroupNorm(num_groups=self.num_groups, name='stem_norm')(x)
    for stage, num_blocks in enumerate(self.stage_sizes):
      for block in range(num_blocks):
        stride = 2 if stage > 0 and block == 0 else 1
        x = BasicBlock(self.width * 2**stage, stride, self.num_groups,
                       name=f'stage_{stage + 1}_block_{block + 1}')(x)
    return x


def output_grid(resolution: Sequence[int], num_stages: int = 4
                ) -> tuple[int, int]:
  """(h', w') of `ResNet`'s feature map for frames of `resolution`: halved
  (rounding up) by every stage after the first."""
  height, width = resolution
  for _ in range(num_stages - 1):
    height, width = -(-height // 2), -(-width // 2)
  return height, width
