"""Choosing a kernel form per platform: one for XLA:CPU, one for accelerators.

Some layers here are evaluated in a form that works around XLA:CPU (the
decoder's phase-split transposed convolutions, `convolution.conv2d`'s kernel
gradient, the explicit softmax(QK^T)V attention); GPU and TPU have their own
kernels for the plain form (cuDNN / XLA:TPU convolutions, flash attention).
Each such layer takes a `kernels` field:

* 'auto' (the default): `jax.lax.platform_dependent`, so the choice is made
  when the computation is *lowered*, for the platform it is lowered for.
  An ahead-of-time compile for a TPU from a CPU host (compile-only devices of
  `jax.experimental.topologies`) gets the accelerator form, a CPU run the CPU
  form. On CPU the results are bit for bit those of the layers before the
  choice existed (tests/modules/test_kernel_forms.py; the switch is resolved at
  lowering, XLA never sees it).
* 'cpu' / 'accelerator': that form on every platform (tests, comparisons).

`forms(kernels)` makes the 'auto' layers traced inside it take one form: the
several-seed training step (train/trainer.py) takes the accelerator forms,
since the CPU form of the transposed convolution, vmapped over the seeds,
is slower there than the accelerator form and computes otherwise when the
seeds are split over devices.

Both forms compute the same function; they differ in rounding only.
Parameters are declared outside the choice, so the parameter tree is the
same whatever the form.
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


@contextlib.contextmanager
def forms(kernels: str) -> Iterator[None]:
  """Layers with kernels='auto' traced in this block (this thread) take the
  form `kernels` ('cpu' or 'accelerator') on every platform."""
  check_kernels(kernels)
  stack = _CHOSEN.__dict__.setdefault('stack', [])
  stack.append(kernels)
  try:
    yield
  finally:
    stack.pop()


def check_kernels(kernels: str) -> None:
  if kernels not in KERNEL_FORMS:
    raise ValueError(f'kernels must be one of {KERNEL_FORMS}, got {kernels!r}')


def by_platform(kernels: str, cpu: Callable[..., _T],
                accelerator: Callable[..., _T], *args: Any) -> _T:
  """`cpu(*args)` or `accelerator(*args)`, as `kernels` says (see above).

  `args` are the arrays (pytrees) both forms read; anything static belongs
  in the callables' closures.
  """
  check_kernels(kernels)
  chosen = getattr(_CHOSEN, 'stack', None)
  if kernels == AUTO and chosen and chosen[-1] != AUTO:
    kernels = chosen[-1]
  if kernels == CPU:
    return cpu(*args)
  if kernels == ACCELERATOR:
    return accelerator(*args)
  return jax.lax.platform_dependent(*args, cpu=cpu, default=accelerator)
