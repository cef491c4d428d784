"""Keeps freed host memory in the process instead of handing it back to the
kernel after every training step (glibc's malloc only).

Why: XLA:CPU allocates each step's scratch buffer afresh and frees it when
the step ends; glibc maps blocks that large with their own ``mmap`` (its
mmap threshold cannot go above 32 MiB) and unmaps them on free, so every
step faulted its pages in again. Before jax allocates,
``keep_freed_memory()`` sets with ``mallopt``:

* ``M_ARENA_MAX = 1``: every thread allocates from the main heap (a
  thread's own arena maps any block above 64 MiB by itself). Must come
  before the threads first allocate;
* ``M_MMAP_MAX = 0``: large blocks come from the heap and can be reused;
* ``M_TRIM_THRESHOLD = -1``: the heap's free top is never given back.

No result changes; the resident size stays near its peak, and one arena
slows XLA's multi-threaded compiler on few cores, so processes that mostly
compile (the tests' conftest) ask for ``no-arena-limit``.
``$SLOTFORMER_MALLOC_TUNING``: unset / ``1`` / ``true`` / ``yes`` / ``on``:
all three; ``no-arena-limit``: the last two; ``0`` / ``false`` / ``no`` /
``off``: none. Nothing is set when ``$GLIBC_TUNABLES`` sets a
``glibc.malloc.`` tunable (the user's choice wins), when the process may
compute on an accelerator (``$JAX_PLATFORMS`` names another platform
first, or, unset, a jax accelerator plugin is installed), or on a C library
other than glibc. An ``LD_PRELOAD``ed allocator makes these settings moot.
Measurements: docs/performance.md, "Host memory churn".
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
# glibc as the largest size_t) never trims; the K-seed SlotFormer program
# frees more than 2 GiB - 1, the largest positive value (docs/performance.md,
# "Three seeds in one program").
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
