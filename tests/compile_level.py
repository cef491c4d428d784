"""The suite's compile level, and the way back to a user's.

The suite compiles far more than it runs, so it compiles cheaper than a
user's run does (docs/performance.md, "The test suite's wall time"):
* `JAX_DISABLE_MOST_OPTIMIZATIONS=1`, jax's own switch: LLVM at -O0
  without its expensive passes;
* XLA:CPU's older elementwise emitters instead of its MLIR fusion emitters
  (`SUITE_XLA_FLAGS`): the same HLO passes and fusions, YNNPACK's included,
  emitted with less compile work (tests/modules/test_targets.py, cold cache:
  68 s -> 41-48 s on the 2-core AMD EPYC);
* one source line per op in the lowered module instead of the test's whole
  Python stack (`JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS=0`): the same
  program, less to lower and compile (docs/performance.md).
Both follow the one switch: `JAX_DISABLE_MOST_OPTIMIZATIONS=0 python -m
pytest -q tests` runs the whole suite compiled as users compile.
"""

import os

SWITCH_ENV = 'JAX_DISABLE_MOST_OPTIMIZATIONS'
SUITE_XLA_FLAGS = ('--xla_cpu_use_fusion_emitters=false',)
LOCATIONS_ENV = 'JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS'


def _name(flag: str) -> str:
  return flag.split('=', 1)[0]


def apply(environ=os.environ) -> None:
  """Sets the suite's compile level in `environ` (values already set win)."""
  environ.setdefault(SWITCH_ENV, '1')
  if environ[SWITCH_ENV] == '0':
    return
  environ.setdefault(LOCATIONS_ENV, '0')
  flags = environ.get('XLA_FLAGS', '').split()
  names = {_name(f) for f in flags}
  added = [f for f in SUITE_XLA_FLAGS if _name(f) not in names]
  environ['XLA_FLAGS'] = ' '.join(flags + added)


def as_users_compile(environ) -> dict:
  """A copy of `environ` that compiles as a user's run compiles."""
  suite = {_name(f) for f in SUITE_XLA_FLAGS}
  flags = environ.get('XLA_FLAGS', '').split()
  return dict(environ, **{
      SWITCH_ENV: '0', LOCATIONS_ENV: '1',
      'XLA_FLAGS': ' '.join(f for f in flags if _name(f) not in suite)})
