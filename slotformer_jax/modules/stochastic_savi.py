"""The stochastic slot initialisation of SlotFormer's stochastic SAVi.

Vanilla SAVi initialises the slots of frame t+1 deterministically from the
slots of frame t, so empty slots stay near-identical and all of them grab the
first object that enters the scene. Stochastic SAVi (SlotFormer, Appendix C)
predicts a Gaussian per slot with a two-layer MLP with LayerNorm (the
official CLEVRER model: one linear layer) and samples the initial slots from
it; a KL term pulls every standard deviation toward a fixed prior sigma_hat
(0.1) without constraining the mean.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


def kl_to_fixed_sigma(log_variance: jax.Array, prior_sigma: float) -> jax.Array:
  """KL(N(mu, sigma^2) || N(mu, prior_sigma^2)), summed over the last axis.

  Both Gaussians share the mean, so only the variance is penalised:
  log(prior_sigma / sigma) + sigma^2 / (2 prior_sigma^2) - 1/2 per dimension.

  Args:
    log_variance: [..., D] log sigma^2.
    prior_sigma: sigma_hat.

  Returns:
    [...] the KL of each slot (summed over its D dimensions).
  """
  variance = jnp.exp(log_variance)
  per_dim = (jnp.log(prior_sigma) - 0.5 * log_variance
             + variance / (2.0 * prior_sigma**2) - 0.5)
  return jnp.sum(per_dim, axis=-1)


NO_HEAD = 'none'
LINEAR_HEAD = 'linear'
MLP_HEAD = 'mlp'
POSTERIOR_HEADS = (NO_HEAD, LINEAR_HEAD, MLP_HEAD)


class GaussianSlotSampler(nn.Module):
  """The posterior head: (mu, log sigma^2) = head(slots), then mu or a sample.

  The official SAVi applies this head to the predicted slots before Slot
  Attention in every model; the deterministic ones (OBJ3D, PHYRE) then keep
  the mean half, the stochastic one (CLEVRER) samples.

  Attributes:
    prior_sigma: sigma_hat of the KL term (0.1 in the paper).
    kind: 'mlp' (Linear(D, 2D) -> LayerNorm -> ReLU -> Linear(2D, 2D), the
      paper's description and the official OBJ3D / PHYRE SAVi) or 'linear'
      (one Linear(D, 2D), the official CLEVRER StoSAVi's `kernel_mlp=False`).
    stochastic: sample (and return the KL) or return the mean (KL zeros).
    layer_norm_epsilon: of the 'mlp' head's LayerNorm.
  """

  prior_sigma: float = 0.1
  kind: str = MLP_HEAD
  stochastic: bool = True
  layer_norm_epsilon: float = 1e-6

  @nn.compact
  def __call__(self, slots: jax.Array) -> tuple[jax.Array, jax.Array]:
    """slots [B, N, D] -> (initial slots [B, N, D], KL [B, N]).

    Draws from the 'sample' RNG stream when stochastic.
    """
    slot_size = slots.shape[-1]
    if self.kind == MLP_HEAD:
      hidden = nn.Dense(2 * slot_size, name='hidden')(slots)
      hidden = nn.LayerNorm(epsilon=self.layer_norm_epsilon,
                            name='norm')(hidden)
      slots = nn.relu(hidden)
    elif self.kind != LINEAR_HEAD:
      raise ValueError(f"posterior head must be '{MLP_HEAD}' or "
                       f"'{LINEAR_HEAD}', got {self.kind!r}")
    statistics = nn.Dense(2 * slot_size, name='statistics')(slots)
    mean, log_variance = jnp.split(statistics, 2, axis=-1)
    if not self.stochastic:
      return mean, jnp.zeros(mean.shape[:-1], mean.dtype)
    noise = jax.random.normal(self.make_rng('sample'), mean.shape, mean.dtype)
    sample = mean + jnp.exp(0.5 * log_variance) * noise
    return sample, kl_to_fixed_sigma(log_variance, self.prior_sigma)
