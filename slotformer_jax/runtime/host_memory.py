"""Keeps freed host memory in the process instead of handing it back to the
kernel after every training step (glibc's malloc only).

Why: XLA:CPU allocates each execution's scratch ("temp") buffer afresh and
frees it when the step ends (it cannot reuse donated buffers either). On the
quickstart's SAVi step that buffer is 59,555,840 bytes. glibc's malloc
serves every block above its mmap threshold with a fresh ``mmap`` and
returns it with ``munmap``, and that threshold cannot be raised above
32 MiB (``mallopt`` and ``GLIBC_TUNABLES`` refuse larger values). So every
step mapped ~57 MiB of new pages and the kernels faulted each of them in
again: 300 SAVi steps took 4.5 M minor page faults and 16-17 s of system
time (docs/performance.md, "Host memory churn").

What: before jax allocates, ``keep_freed_memory()`` calls glibc's
``mallopt`` three times:

* ``M_ARENA_MAX = 1``: every thread allocates from the main heap. A
  thread's own arena has heaps of at most 64 MiB, and glibc maps (and
  unmaps) any larger block from such a thread by itself, whatever the other
  settings: the quickstart's SlotFormer step (L_I on) allocates 120 MiB and
  452 MiB blocks from XLA's threads (``strace``). It must come before the
  threads first allocate (before jax starts its backend): a thread may
  reuse an arena that already exists;
* ``M_MMAP_MAX = 0``: malloc no longer serves large blocks by their own
  ``mmap``; they come from the heap like small ones, so they can be reused;
* ``M_TRIM_THRESHOLD = -1``: free space at the top of the heap is never
  given back to the kernel ("-1 disables trimming completely", mallopt(3)),
  so the next step's buffer lands on pages that are already mapped. The
  largest positive value (2 GiB - 1, mallopt's int) was the setting before:
  the three-seed SlotFormer program (L_I on) frees more than 2 GiB at the
  top of the heap after each step, which was then returned and faulted in
  again (60 steps: 12.6-12.8 M faults, 25-26 s system time; never trimming:
  2.55 M, 6.4-6.8 s; docs/performance.md, "Host memory churn").

The process then keeps up to its high-water mark of heap memory mapped (the
resident size stays near the peak instead of shrinking between steps); no
result changes, only where the bytes live.

The price of one arena: every thread takes the same malloc lock and
allocates next to the others, so threads that allocate at the same time on
different cores slow each other down. XLA's compiler does that: 20 small
programs compiled in one process took 10.1-11.2 s with the three settings
and 7.2-8.8 s without them on the 2-core box (the same on one core: 11.3-11.7
against 12.0-12.7 s). Steps pay a little too: 200 quickstart SAVi steps,
whose 57 MiB scratch fits a thread's own heap, ran fastest without the
limit (18.2-19.7 s against 20.3-20.8 s wall). But the 3-seed SlotFormer
step with L_I needs it: 60 steps took 17.4 M faults and 42 s of system time
without it, 2.3-2.6 M and 8 s with it (docs/performance.md, "Host memory
churn"). A training run compiles a few programs and then steps thousands
of times, so ``main`` keeps all three; a process that mostly compiles
small programs (the tests' conftest) asks for ``no-arena-limit``: the two
other settings, which cost nothing there.

``$SLOTFORMER_MALLOC_TUNING`` chooses:

* unset, ``1`` / ``true`` / ``yes`` / ``on``: all three settings;
* ``no-arena-limit``: ``M_MMAP_MAX`` and ``M_TRIM_THRESHOLD`` only (blocks a
  thread allocates above 64 MiB are still mapped afresh);
* ``0`` / ``false`` / ``no`` / ``off``: none.

It does nothing (whatever the switch says) when

* ``$GLIBC_TUNABLES`` already sets a ``glibc.malloc.`` tunable (the user's
  choice wins, as for ``$XLA_FLAGS`` in ``xla_flags``);
* the process may compute on an accelerator: ``$JAX_PLATFORMS`` names
  another platform first, or, unset, a jax accelerator plugin (libtpu, a
  ``jax_plugins`` package or entry point: CUDA, ROCm) is installed. There
  the steps' buffers live on the device and these settings were never
  measured; a CPU run on such a host says ``JAX_PLATFORMS=cpu`` to get them;
* the C library is not glibc (musl, macOS: their allocators differ) or
  ``mallopt`` refuses a value.

A preloaded allocator (``LD_PRELOAD`` of tcmalloc or jemalloc) replaces
``malloc`` itself; then glibc's settings are moot but harmless.
"""

from __future__ import annotations

import ctypes
import importlib.metadata
import importlib.util
import logging
import os
import platform

logger = logging.getLogger(__name__)

SWITCH_ENV = 'SLOTFORMER_MALLOC_TUNING'
# glibc's malloc.h.
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8
# Free space kept at the top of the heap before it is trimmed: -1 (read by
# glibc as the largest size_t) never trims. Measured on 60 SlotFormer steps
# (L_I on, one arena, no mmap): 1 GiB still trimmed (1.62 M faults, 5.6 s
# system), 2 GiB - 1: 0.93 M, 3.7 s (one seed); with three seeds in one
# program 2 GiB - 1 trimmed every step (12.8 M, 25.9 s) and -1 did not
# (2.55 M, 6.4 s).
TRIM_THRESHOLD_BYTES = -1

_applied: tuple[tuple[int, int], ...] | None = None

ALL = 'all'
NO_ARENA_LIMIT = 'no-arena-limit'
OFF = 'off'
_OFF_VALUES = ('0', 'false', 'no', 'off')
_ALL_VALUES = ('', '1', 'true', 'yes', 'on', 'all')
# Modules of jax's accelerator plugins that are not `jax_plugins.*`.
_ACCELERATOR_MODULES = ('libtpu',)


def level(environ) -> str:
  """ALL, NO_ARENA_LIMIT or OFF, from $SLOTFORMER_MALLOC_TUNING."""
  value = environ.get(SWITCH_ENV, '').strip().lower()
  if value in _OFF_VALUES:
    return OFF
  if value == NO_ARENA_LIMIT:
    return NO_ARENA_LIMIT
  if value not in _ALL_VALUES:
    logger.warning('$%s=%r is not one of 1, %s, 0: using 1 (all settings)',
                   SWITCH_ENV, value, NO_ARENA_LIMIT)
  return ALL


def _user_tunes_malloc(environ) -> bool:
  return 'glibc.malloc.' in environ.get('GLIBC_TUNABLES', '')


def _is_glibc() -> bool:
  try:
    return platform.libc_ver()[0] == 'glibc'
  except (OSError, ValueError):
    return False


def may_compute_on_accelerator(environ) -> bool:
  """Whether jax may pick a TPU or GPU backend in this process.

  Decided before jax starts (the settings must come first): from
  $JAX_PLATFORMS when set (its first platform), else from the accelerator
  plugins jax would discover. A plugin installed on a machine without its
  chip reads as "may": the process then runs untuned, as before.
  """
  platforms = environ.get('JAX_PLATFORMS', '').strip().lower()
  if platforms:
    return platforms.split(',')[0].strip() != 'cpu'
  if any(importlib.util.find_spec(name) is not None
         for name in _ACCELERATOR_MODULES):
    return True
  if importlib.util.find_spec('jax_plugins') is not None:
    return True
  try:
    return bool(importlib.metadata.entry_points(group='jax_plugins'))
  except Exception:  # a broken distribution's metadata: assume none
    return False


def settings(which: str = ALL) -> tuple[tuple[int, int], ...]:
  """(mallopt parameter, value) pairs `keep_freed_memory` sets for a
  `level` (ALL, NO_ARENA_LIMIT, OFF), in order."""
  heap = ((M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
  if which == ALL:
    return ((M_ARENA_MAX, 1),) + heap
  if which == NO_ARENA_LIMIT:
    return heap
  return ()


def keep_freed_memory(environ=None) -> bool:
  """Applies `settings()` with glibc's mallopt; True when all were accepted.

  Call it once, early (main, the tests' conftest): settings
  apply to every allocation from then on, in every thread. Idempotent.
  """
  global _applied
  environ = os.environ if environ is None else environ
  which = level(environ)
  if (which == OFF or _user_tunes_malloc(environ) or not _is_glibc()
      or may_compute_on_accelerator(environ)):
    return False
  if _applied is not None:
    return True
  try:
    mallopt = ctypes.CDLL(None).mallopt
  except (OSError, AttributeError):
    return False
  mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
  mallopt.restype = ctypes.c_int
  for parameter, value in settings(which):
    if mallopt(parameter, value) != 1:  # glibc returns 1 on success
      logger.debug('mallopt(%d, %d) refused', parameter, value)
      return False
  _applied = settings(which)
  return True
