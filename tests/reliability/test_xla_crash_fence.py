"""The XLA:CPU crash fence (runtime/xla_flags.py: CRASH_FENCE_FLAGS).

jaxlib 0.10.2's YNNPACK reduce fusion segfaults on AVX2-only CPUs (seen on a
2-core AMD EPYC) for the reduction below; the SAVi decoder's vmapped gradient
(tests/modules/test_targets.py's jacobian) reaches one. The reproduction runs
in a subprocess, so a crash is one failed test, not a dead suite, and with the
flags `import slotformer_jax` sets, as every user path gets them. On a CPU
where the fusion does not crash this still checks the value and that the
fence is applied, so the test means the same on every CI machine.
"""

import os
import subprocess
import sys

from slotformer_jax.runtime import xla_flags

import compile_level

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# The smallest program found that crashes (docs/performance.md): a product
# of two inputs summed over axis 3 of a rank-7 array with a trailing 1.
# Smaller spatial sizes (16 x 8), rank 6 or no trailing 1 do not crash.
REPRODUCTION = r'''
import os, sys
import numpy as np
if sys.argv[1] == 'package':
  import slotformer_jax  # noqa: F401  (sets the project's XLA:CPU flags)
import jax
rng = np.random.RandomState(0)
x, y = (rng.rand(2, 2, 2, 3, 16, 16, 1).astype(np.float32) for _ in range(2))
out = jax.jit(lambda x, y: (x * y).sum(axis=3))(x, y)
np.testing.assert_allclose(np.asarray(out), (x * y).sum(axis=3), rtol=1e-5)
print('ok', os.environ.get('XLA_FLAGS', ''))
'''


def _without_ynn_flags(flags: str) -> str:
  name = xla_flags.flag_name(xla_flags.CRASH_FENCE_FLAGS[0])
  return ' '.join(f for f in flags.split() if xla_flags.flag_name(f) != name)


def _users_flags() -> str:
  return compile_level.as_users_compile(os.environ)['XLA_FLAGS']


def _run(mode: str, **env):
  # Compiled as a user's run compiles it (the suite compiles cheaper:
  # tests/compile_level.py).
  env = dict(compile_level.as_users_compile(os.environ), JAX_PLATFORMS='cpu',
             PYTHONPATH=REPO, **env)
  return subprocess.run([sys.executable, '-c', REPRODUCTION, mode], env=env,
                        cwd=REPO, capture_output=True, text=True, timeout=300,
                        check=False)


def test_the_reproduction_runs_with_the_packages_flags():
  result = _run('package',
                XLA_FLAGS=_without_ynn_flags(_users_flags()))
  assert result.returncode == 0, (result.returncode, result.stderr[-2000:])
  assert result.stdout.startswith('ok')
  fence = xla_flags.CRASH_FENCE_FLAGS[0].split('=', 1)[1]
  ynn = [f for f in result.stdout.split() if f.startswith(
      '--' + xla_flags.flag_name(xla_flags.CRASH_FENCE_FLAGS[0]))]
  assert len(ynn) == 1 and fence in ynn[0].split('=', 1)[1].split(','), ynn


def test_the_fence_holds_with_the_speed_flags_switched_off():
  result = _run('package', **{
      'XLA_FLAGS': _without_ynn_flags(_users_flags()),
      xla_flags.SWITCH_ENV: '0'})
  assert result.returncode == 0, (result.returncode, result.stderr[-2000:])
  assert '-reduce' in result.stdout and 'individual_convolution' not in (
      result.stdout)


def test_flags_of_one_name_are_merged_into_one():
  assert xla_flags._merged((  # pylint: disable=protected-access
      '--xla_a=-x', '--xla_b=1', '--xla_a=-y')) == ['--xla_a=-x,-y', '--xla_b=1']
