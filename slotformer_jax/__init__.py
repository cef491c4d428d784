"""SlotFormer in JAX/Flax."""

# Before anything in the package can start jax's backends: the XLA:CPU
# flags, a crash fence among them (runtime/xla_flags.py; imports no jax).
from slotformer_jax.runtime import xla_flags as _xla_flags

_xla_flags.apply_fast_cpu_flags()
