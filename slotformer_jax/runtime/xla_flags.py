"""XLA:CPU flags for this project's programs: one for speed, one crash fence.

XLA reads ``$XLA_FLAGS`` once, when jax initialises its backends, and aborts
the whole process on a flag it does not know. So ``import slotformer_jax``
(and the entry points that own the process: ``main``, ``benchmarks/``, the
tests' conftest) calls ``apply_fast_cpu_flags()`` before the first jax
computation, and it:

* leaves every flag the user already put in ``$XLA_FLAGS`` alone (a flag of
  the same name there wins, whatever its value);
* adds a flag only after a throw-away subprocess started jax with it and
  ran a computation (the result is cached per jaxlib version, so the probe costs
  ~1 s once per install, not per run);
* does nothing when the backends are already initialised (too late: the
  flags would be ignored for this process; on CPU it says so).

The flags, both YNNPACK fusion types of jaxlib 0.10's XLA:CPU turned off:
``individual_convolution`` for speed (its kernel-gradient path is ~6x slower
than the classic emitter on the SAVi decoder; ``$SLOTFORMER_XLA_CPU_FLAGS=0``
keeps it on), and ``reduce`` as a crash fence, kept whatever that switch says:
jaxlib 0.10.2's YNN reduce fusion segfaults on AVX2-only CPUs for some
rank-7 reductions (the SAVi decoder's vmapped gradient reaches one).
docs/performance.md has the reproduction, the machines and the cost.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
import subprocess
import sys

# Light: files.py imports only the standard library (and errors.py), so this
# module stays importable before jax.
from slotformer_jax.files import write_json_atomic

logger = logging.getLogger(__name__)

# The flags, each a complete `--name=value` string. Several values of a
# list flag (XLA's '+'/'-' form) are joined into one flag: see `_merged`.
# For speed only: `SWITCH_ENV` turns these off.
FAST_CPU_FLAGS: tuple[str, ...] = (
    '--xla_cpu_experimental_ynn_fusion_type=-individual_convolution',
)
# Crash fences, applied whatever `SWITCH_ENV` says (the user's own flag of
# the same name still wins). Remove one when a jaxlib that fixes it is
# pinned: tests/reliability/test_xla_crash_fence.py runs the reproduction.
CRASH_FENCE_FLAGS: tuple[str, ...] = (
    '--xla_cpu_experimental_ynn_fusion_type=-reduce',
)
# '0' / 'false' / 'no' / 'off' disables adding the speed flags.
SWITCH_ENV = 'SLOTFORMER_XLA_CPU_FLAGS'
# Where probe results are kept: $XDG_CACHE_HOME/slotformer_jax (default
# ~/.cache/slotformer_jax). A fact of the install, not of a run's data
# folder: `import slotformer_jax` probes before any command is checked, and a
# command refused for a mistake writes nothing into its folders.
CACHE_ENV = 'XDG_CACHE_HOME'

_PROBE_PROGRAM = (
    'import jax, jax.numpy as jnp\n'
    'x = jnp.ones((1, 4, 4, 2))\n'
    'k = jnp.ones((3, 3, 2, 2))\n'
    'f = lambda k: jax.lax.conv_general_dilated(\n'
    '    x, k, (1, 1), "SAME",\n'
    '    dimension_numbers=("NHWC", "HWIO", "NHWC")).sum()\n'
    'print(float(jax.jit(jax.grad(f))(k).sum()))\n')


def flag_name(flag: str) -> str:
  """'--xla_foo=1' -> 'xla_foo'."""
  return flag.lstrip('-').split('=', 1)[0]


def _names_in(xla_flags: str) -> set[str]:
  return {flag_name(f) for f in xla_flags.split() if f.startswith('-')}


def _disabled(environ) -> bool:
  return environ.get(SWITCH_ENV, '1').strip().lower() in (
      '0', 'false', 'no', 'off')


def _jaxlib_version() -> str:
  try:
    from importlib import metadata  # pylint: disable=g-import-not-at-top
    return metadata.version('jaxlib')
  except Exception:  # pylint: disable=broad-except
    return 'unknown'


def _cache_path(environ) -> Path:
  root = environ.get(CACHE_ENV) or '~/.cache'
  return Path(root).expanduser() / 'slotformer_jax' / 'xla_flag_probes.json'


def _read_cache(path: Path) -> dict[str, bool]:
  try:
    with open(path) as f:
      cached = json.load(f)
    return cached if isinstance(cached, dict) else {}
  except (OSError, ValueError):
    return {}


def _write_cache(path: Path, cached: dict[str, bool]) -> None:
  """Atomic (write + rename): concurrent runs never read half a file."""
  try:
    write_json_atomic(path, cached)
  except OSError as error:  # read-only home: probe again next time
    logger.debug('could not cache XLA flag probes: %s', error)


def probe_flag(flag: str, *, timeout: float = 120.0) -> bool:
  """Whether a fresh jax process accepts `flag` and computes with it.

  Runs a convolution's kernel gradient on CPU in a subprocess and checks its
  value (400), so an unknown flag (XLA aborts) or a rejected value never
  reaches this process.
  """
  env = dict(os.environ, XLA_FLAGS=flag, JAX_PLATFORMS='cpu')
  env.pop(SWITCH_ENV, None)
  try:
    result = subprocess.run([sys.executable, '-c', _PROBE_PROGRAM], env=env,
                            capture_output=True, timeout=timeout, check=False)
  except (OSError, subprocess.TimeoutExpired):
    return False
  return result.returncode == 0 and result.stdout.strip() == b'400.0'


def supported(flag: str, environ=None) -> bool:
  """probe_flag, cached per (jaxlib version, flag) on disk."""
  environ = os.environ if environ is None else environ
  key = f'jaxlib {_jaxlib_version()} {flag}'
  path = _cache_path(environ)
  cached = _read_cache(path)
  if key not in cached:
    cached[key] = probe_flag(flag)
    _write_cache(path, cached)
  return bool(cached[key])


def _backends_initialised() -> bool:
  if 'jax' not in sys.modules:
    return False
  try:
    from jax._src import xla_bridge  # pylint: disable=g-import-not-at-top
    return bool(xla_bridge.backends_are_initialized())
  except (ImportError, AttributeError):
    return False


def _merged(flags: tuple[str, ...]) -> list[str]:
  """Joins flags of the same name into one, values comma-separated, in order:
  ('--a=-x', '--a=-y') -> ['--a=-x,-y'] (XLA keeps only the last of two)."""
  values: dict[str, list[str]] = {}
  for flag in flags:
    values.setdefault(flag_name(flag), []).append(flag.split('=', 1)[1])
  return [f'--{name}={",".join(parts)}' for name, parts in values.items()]


def _cpu_backend() -> bool:
  try:
    import jax  # pylint: disable=g-import-not-at-top
    return jax.default_backend() == 'cpu'
  except Exception:  # pylint: disable=broad-except
    return False


def apply_fast_cpu_flags(flags: tuple[str, ...] = FAST_CPU_FLAGS,
                         environ=None,
                         fences: tuple[str, ...] = CRASH_FENCE_FLAGS,
                         ) -> list[str]:
  """Appends the supported `fences` + `flags` the user did not set to
  $XLA_FLAGS (`flags` only unless `SWITCH_ENV` disables them).

  Call it before the first jax computation. Returns the flags added (empty
  when too late, already set, or unsupported).
  """
  environ = os.environ if environ is None else environ
  wanted = _merged(tuple(fences) + (() if _disabled(environ) else tuple(flags)))
  current = environ.get('XLA_FLAGS', '')
  user_names = _names_in(current)
  wanted = [f for f in wanted if flag_name(f) not in user_names]
  if not wanted:
    return []
  if _backends_initialised():
    if _cpu_backend():
      logger.warning('XLA:CPU flags not applied (%s): jax had already started '
                     'its backends; import slotformer_jax before running jax.',
                     ' '.join(wanted))
    return []
  added = [f for f in wanted if supported(f, environ)]
  if added:
    environ['XLA_FLAGS'] = ' '.join([current, *added]).strip()
  return added
