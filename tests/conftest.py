"""Test-session setup: 4 fake CPU devices, so sharded code paths run too.

XLA reads the flag when jax initialises its backends, so it is set here,
before any test module imports jax.
"""

import os

_FLAG = '--xla_force_host_platform_device_count=4'
if _FLAG not in os.environ.get('XLA_FLAGS', ''):
  os.environ['XLA_FLAGS'] = (os.environ.get('XLA_FLAGS', '') + ' ' + _FLAG).strip()
os.environ.setdefault('JAX_PLATFORMS', 'cpu')
