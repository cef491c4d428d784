"""A stride-1 2-D convolution whose kernel gradient, on CPU, reads a
materialised input.

XLA:CPU computes a convolution's kernel gradient as another convolution over
the input transposed to [C_in, H, W, N]. When the input is the output of
bias + ReLU (every decoder layer), XLA fuses that elementwise work into the
transpose and emits an element loop that walks the input with a stride of
H*W*C floats, several times slower than a transpose of a materialised array
(docs/experiments/performance.md, "Kernel gradients from a materialised
transpose"). `conv2d`
computes the same gradient from `x @ I` (an exact identity product, which
XLA cannot see through and so materialises) transposed.

That form is for XLA:CPU only: on GPU / TPU it would replace the compiler's
own weight-gradient convolution by a correlation whose "kernel" is the whole
output-gradient map. `conv2d` and `SameConv` pick it on CPU and the plain
`lax.conv_general_dilated` (autodiff's own gradient) elsewhere, when the
computation is lowered (`slotformer_jax.modules.platform`).
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotformer_jax.modules import platform

Padding = tuple[tuple[int, int], tuple[int, int]]
_DIMENSIONS = ('NHWC', 'HWIO', 'NHWC')


def _convolve(x: jax.Array, kernel: jax.Array, padding: Padding) -> jax.Array:
  return jax.lax.conv_general_dilated(
      x, kernel, window_strides=(1, 1), padding=padding,
      dimension_numbers=_DIMENSIONS)


def conv2d(x: jax.Array, kernel: jax.Array, padding: Padding,
           kernels: str = platform.AUTO) -> jax.Array:
  """Stride-1 cross-correlation, `lax.conv_general_dilated`; on CPU with the
  kernel gradient of `conv2d_cpu` (`kernels`: see `modules.platform`).

  x [N, H, W, C_in], kernel [KH, KW, C_in, C_out]; padding and the output
  shape as in `conv2d_cpu`.
  """
  return platform.by_platform(
      kernels, lambda x, k: conv2d_cpu(x, k, padding),
      lambda x, k: _convolve(x, k, padding), x, kernel)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv2d_cpu(x: jax.Array, kernel: jax.Array, padding: Padding) -> jax.Array:
  """Stride-1 cross-correlation, as `lax.conv_general_dilated`, whose kernel
  gradient is computed from a materialised `x @ I` (the XLA:CPU form, see
  the module docstring).

  Args:
    x: [N, H, W, C_in].
    kernel: [KH, KW, C_in, C_out].
    padding: ((low_y, high_y), (low_x, high_x)); negative values crop.

  Returns:
    [N, H + low_y + high_y - KH + 1, W + low_x + high_x - KW + 1, C_out].
  """
  return _convolve(x, kernel, padding)


def _conv2d_forward(x, kernel, padding):
  return _convolve(x, kernel, padding), (x, kernel)


def _conv2d_backward(padding, residuals, grad_out):
  x, kernel = residuals
  _, input_vjp = jax.vjp(lambda x: _convolve(x, kernel, padding), x)
  (grad_x,) = input_vjp(grad_out)
  # grad_kernel[ky, kx, i, o] = sum_{n,y,x} x_pad[n, y+ky, x+kx, i]
  #                                         * grad_out[n, y, x, o]:
  # a correlation of x read as [C_in, H, W, N] ("batch" C_in, "features" N)
  # with grad_out read as a [H_out, W_out, N, C_out] kernel.
  kernel_h, kernel_w, c_in, _ = kernel.shape
  (low_y, _), (low_x, _) = padding
  out_h, out_w = grad_out.shape[1:3]
  grad_padding = (
      (low_y, kernel_h - 1 + out_h - x.shape[1] - low_y),
      (low_x, kernel_w - 1 + out_w - x.shape[2] - low_x))
  identity = jnp.eye(c_in, dtype=x.dtype)
  x_t = jnp.einsum('nhwc,cd->dhwn', x, identity)
  grad_out_t = jnp.transpose(grad_out, (1, 2, 0, 3))
  grad_kernel = _convolve(x_t, grad_out_t, grad_padding)  # [C_in, KH, KW, C_out]
  return grad_x, jnp.transpose(grad_kernel, (1, 2, 0, 3))


conv2d_cpu.defvjp(_conv2d_forward, _conv2d_backward)


def odd_kernel_params(module: nn.Module, kernel_size: int, c_in: int,
                      features: int) -> tuple[jax.Array, jax.Array]:
  """Declares `nn.Conv`'s 'kernel' [K, K, C_in, C_out] and 'bias' [C_out]
  (same initialisers) on `module`, for layers that evaluate the convolution
  themselves; K must be odd ('same' padding K // 2)."""
  if kernel_size % 2 != 1:
    raise ValueError(f'kernel_size must be odd, got {kernel_size}')
  kernel = module.param('kernel', nn.initializers.lecun_normal(),
                        (kernel_size, kernel_size, c_in, features))
  bias = module.param('bias', nn.initializers.zeros_init(), (features,))
  return kernel, bias


class SameConv(nn.Module):
  """`nn.Conv(features, (K, K), padding='SAME')` at stride 1 and odd K, through
  `conv2d`. Same parameter tree and initialisers as `nn.Conv`, so checkpoints
  are interchangeable.

  Attributes:
    features: C_out.
    kernel_size: K.
    kernels: 'auto' (the CPU form on CPU, the plain one elsewhere), 'cpu' or
      'accelerator' (`slotformer_jax.modules.platform`).
  """

  features: int
  kernel_size: int
  kernels: str = platform.AUTO

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """x [N, H, W, C_in] -> [N, H, W, features]."""
    kernel, bias = odd_kernel_params(self, self.kernel_size, x.shape[-1],
                                     self.features)
    pad = self.kernel_size // 2
    return conv2d(x, kernel, ((pad, pad), (pad, pad)), self.kernels) + bias
