"""Test-session setup: 4 fake CPU devices, so sharded code paths run too.

XLA reads the flag when jax initialises its backends, so it is set here,
before any test module imports jax.
"""

import os

_FLAG = '--xla_force_host_platform_device_count=4'
if _FLAG not in os.environ.get('XLA_FLAGS', ''):
  os.environ['XLA_FLAGS'] = (os.environ.get('XLA_FLAGS', '') + ' ' + _FLAG).strip()
os.environ.setdefault('JAX_PLATFORMS', 'cpu')

# The faster XLA:CPU convolution path, as main.py uses it (imports no jax).
from slotformer_jax.runtime import xla_flags  # noqa: E402
xla_flags.apply_fast_cpu_flags()

import tempfile  # noqa: E402

import jax  # noqa: E402

# Several tests compile the same small programs (e.g. a training run and its
# resumed copy); XLA's persistent cache turns the repeats into lookups.
jax.config.update('jax_compilation_cache_dir',
                  os.path.join(tempfile.gettempdir(), 'slotformer_jax_test_xla_cache'))
jax.config.update('jax_persistent_cache_min_compile_time_secs', 0.5)
jax.config.update('jax_persistent_cache_min_entry_size_bytes', 0)
