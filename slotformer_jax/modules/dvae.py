"""dVAE: the discrete image tokenizer of STEVE / SLATE.

An image is cut into 4x4 patches, each patch gets a categorical over a
vocabulary of `vocab_size` codes (4096 in the paper); the decoder maps a
relaxed one-hot (Gumbel-softmax) code map back to pixels through two
pixel-shuffle x2 steps. After training, the argmax code of every patch is the
token STEVE's Transformer decoder learns to predict.

Shapes: images [batch, height, width, 3] in [-1, 1];
logits / codes [batch, height / 4, width / 4, vocab_size].
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

# PyTorch's kaiming_uniform_(nonlinearity='relu') and xavier_uniform_, the
# initialisers of the official blocks.
_KAIMING = nn.initializers.he_uniform()
_XAVIER = nn.initializers.glorot_uniform()

# Frame pixels per token side: the k4 s4 patch embedding.
DOWNSAMPLING = 4


def pixel_shuffle(x: jax.Array, factor: int) -> jax.Array:
  """[B, H, W, C * f * f] -> [B, H * f, W * f, C].

  Channel c * f * f + i * f + j goes to output pixel (h * f + i, w * f + j),
  PyTorch's `nn.PixelShuffle` order, so converted weights keep their meaning.
  """
  batch, height, width, channels = x.shape
  out_channels = channels // (factor * factor)
  x = x.reshape(batch, height, width, out_channels, factor, factor)
  x = x.transpose(0, 1, 4, 2, 5, 3)
  return x.reshape(batch, height * factor, width * factor, out_channels)


class ConvBlock(nn.Module):
  """Conv (no bias) -> GroupNorm with one group -> ReLU.

  Attributes:
    features: output channels.
    kernel_size: square kernel; 3x3 blocks pad by 1 (size kept), 1x1 and
      the k4 s4 patch embedding use no padding.
    stride: square stride.
  """

  features: int
  kernel_size: int = 1
  stride: int = 1

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    padding = 'SAME' if self.kernel_size == 3 else 'VALID'
    x = nn.Conv(self.features, (self.kernel_size, self.kernel_size),
                strides=(self.stride, self.stride), padding=padding,
                use_bias=False, kernel_init=_KAIMING, name='conv')(x)
    # GroupNorm(1) normalises over all of H, W, C (unlike LayerNorm over C).
    x = nn.GroupNorm(num_groups=1, epsilon=1e-5, name='norm')(x)
    return nn.relu(x)


def gumbel_softmax(rng: jax.Array, log_probs: jax.Array,
                   temperature: jax.Array | float) -> jax.Array:
  """Relaxed one-hot samples over the last axis (soft, no straight-through)."""
  gumbels = jax.random.gumbel(rng, log_probs.shape, log_probs.dtype)
  return jax.nn.softmax((log_probs + gumbels) / temperature, axis=-1)


class DVAE(nn.Module):
  """The official Physion dVAE (64 hidden channels, downsampling x4).

  Attributes:
    vocab_size: number of codes (4096).
    hidden_size: channels of every hidden block (64).
  """

  vocab_size: int = 4096
  hidden_size: int = 64

  def setup(self):
    hidden = self.hidden_size
    self.encoder = nn.Sequential(
        [ConvBlock(hidden, DOWNSAMPLING, DOWNSAMPLING)] + [ConvBlock(hidden) for _ in range(6)] +
        [nn.Conv(self.vocab_size, (1, 1), kernel_init=_XAVIER)])
    # Two stages of (3x3, 1x1, 1x1, expand x4) -> pixel shuffle x2.
    self.decoder_stages = [
        nn.Sequential([ConvBlock(hidden), ConvBlock(hidden, 3),
                       ConvBlock(hidden), ConvBlock(hidden),
                       ConvBlock(hidden * 4)]),
        nn.Sequential([ConvBlock(hidden, 3), ConvBlock(hidden),
                       ConvBlock(hidden), ConvBlock(hidden * 4)]),
    ]
    self.decoder_out = nn.Conv(3, (1, 1), kernel_init=_XAVIER)

  def logits(self, images: jax.Array) -> jax.Array:
    """images [B, H, W, 3] -> code logits [B, H/4, W/4, vocab_size]."""
    return self.encoder(images)

  def tokenize(self, images: jax.Array) -> jax.Array:
    """images [B, H, W, 3] -> int32 tokens [B, H/4, W/4] (argmax codes)."""
    return jnp.argmax(self.logits(images), axis=-1).astype(jnp.int32)

  def decode(self, codes: jax.Array) -> jax.Array:
    """(relaxed) one-hot codes [B, h, w, vocab_size] -> images [B, 4h, 4w, 3]."""
    x = codes
    for stage in self.decoder_stages:
      x = pixel_shuffle(stage(x), 2)
    return self.decoder_out(x)

  def decode_tokens(self, tokens: jax.Array) -> jax.Array:
    """int tokens [B, h, w] -> images [B, 4h, 4w, 3]."""
    return self.decode(jax.nn.one_hot(tokens, self.vocab_size))

  def __call__(self, images: jax.Array, temperature: jax.Array | float
               ) -> tuple[jax.Array, jax.Array]:
    """images [B, H, W, 3] -> (recon [B, H, W, 3], log_probs [B, h, w, V]).

    Draws the Gumbel noise from the 'gumbel' RNG stream.
    """
    log_probs = jax.nn.log_softmax(self.logits(images), axis=-1)
    codes = gumbel_softmax(self.make_rng('gumbel'), log_probs, temperature)
    return self.decode(codes), log_probs
