"""Choosing a kernel form per platform: one for XLA:CPU, one for accelerators.

Some layers are evaluated in a form that works around XLA:CPU (the decoder's
phase-split transposed convolutions, `convolution.conv2d`'s kernel gradient,
the explicit softmax(QK^T)V attention); GPU and TPU have their own kernels
for the plain form. Each such layer takes a `kernels` field: 'auto' (the
default: `jax.lax.platform_dependent`, chosen when the computation is
lowered, so an ahead-of-time TPU compile from a CPU host gets the
accelerator form), or 'cpu' / 'accelerator' everywhere. `forms(kernels,
layers)` fixes the form of the 'auto' layers traced inside it: the K-seed
step takes the accelerator form of the transposed convolution, whose CPU
form, vmapped over stacked models, computes otherwise when they are split
over devices. Both forms compute the same function up to rounding, with one
parameter tree. Why and measured: docs/performance.md, "Kernels per
platform".
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import contextlib
import threading
from typing import Any, TypeVar

import jax

AUTO = 'auto'
CPU = 'cpu'
ACCELERATOR = 'accelerator'
KERNEL_FORMS = (AUTO, CPU, ACCELERATOR)

_T = TypeVar('_T')


_CHOSEN = threading.local()  # .stack: forms() blocks, innermost last

CONV_TRANSPOSE = 'conv_transpose'


@contextlib.contextmanager
def forms(kernels: str, layers: tuple[str, ...]) -> Iterator[None]:
  """Layers of the kinds `layers` (e.g. CONV_TRANSPOSE) with kernels='auto'
  traced in this block (this thread) take the form `kernels` ('cpu' or
  'accelerator') on every platform."""
  check_kernels(kernels)
  stack = _CHOSEN.__dict__.setdefault('stack', [])
  stack.append((kernels, tuple(layers)))
  try:
    yield
  finally:
    stack.pop()


def check_kernels(kernels: str) -> None:
  if kernels not in KERNEL_FORMS:
    raise ValueError(f'kernels must be one of {KERNEL_FORMS}, got {kernels!r}')


def by_platform(kernels: str, cpu: Callable[..., _T],
                accelerator: Callable[..., _T], *args: Any,
                layer: str | None = None) -> _T:
  """`cpu(*args)` or `accelerator(*args)`, as `kernels` says (see above).

  `args` are the arrays (pytrees) both forms read; anything static belongs
  in the callables' closures.
  """
  check_kernels(kernels)
  chosen = getattr(_CHOSEN, 'stack', None)
  if kernels == AUTO and chosen and layer in chosen[-1][1]:
    kernels = chosen[-1][0]
  if kernels == CPU:
    return cpu(*args)
  if kernels == ACCELERATOR:
    return accelerator(*args)
  return jax.lax.platform_dependent(*args, cpu=cpu, default=accelerator)
