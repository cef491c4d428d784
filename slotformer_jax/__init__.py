"""SlotFormer in JAX/Flax."""
