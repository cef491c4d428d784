"""The paper's losses, as pure functions of (params, batch, frozen, rng).

* SAVi: frame reconstruction MSE (+ kl_weight * KL for stochastic SAVi);
  with other targets (`config.savi.targets`: SAVi's flow, depth) one MSE
  per target (`reconstruction_loss`).
* SlotFormer / Slot-LSTM: L = L_S + lambda * L_I (slot MSE + image MSE of
  the frames -- or the slot model's other targets -- decoded by the frozen
  SAVi decoder).
* STEVE's dVAE: pixel MSE of the relaxed-code reconstruction; STEVE: the
  cross-entropy of its token decoder against the frozen dVAE's tokens.

Pixels are in the [-1, 1] range of `frames.frames_to_model`. Every loss
plugs into `train.trainer.fit` as `loss_fn(params, batch, frozen_params,
rng) -> (loss, metrics)`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from slotformer_jax import targets as targets_lib
from slotformer_jax.frames import frames_to_model
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.modules.dvae import DVAE
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.modules.steve import STEVE

Batch = dict[str, jax.Array]
Metrics = dict[str, jax.Array]


def reconstruction_loss(reconstructions: dict[str, jax.Array],
                        truths: dict[str, jax.Array], name: str
                        ) -> tuple[jax.Array, Metrics]:
  """The reconstruction loss of one or several targets, and its metrics.

  reconstructions / truths: {target: [..., C]} in the same range. Each
  target's term is its MSE; the loss is the MSE over every target channel
  together, i.e. the terms weighted by their share of the channels (SAVi
  sums the squared errors over every channel of every target, so that is
  its relative weighting; a mean keeps the RGB-only loss what it was). One
  target: the loss is its MSE. Metrics: {name: loss}, and `<name>_<target>`
  per target unless RGB is the only one.
  """
  terms = {target: jnp.mean(jnp.square(values - truths[target]))
           for target, values in reconstructions.items()}
  if len(terms) == 1:
    (loss,) = terms.values()
  else:
    widths = {target: values.shape[-1]
              for target, values in reconstructions.items()}
    total = sum(widths.values())
    loss = sum(widths[target] / total * term
               for target, term in terms.items())
  metrics = {name: loss}
  if tuple(terms) != targets_lib.DEFAULT:
    metrics.update({f'{name}_{target}': term
                    for target, term in terms.items()})
  return loss, metrics


def reconstructions_of(decoded: Any) -> dict[str, jax.Array]:
  """{target: [..., H, W, C]} of a decoder's output: its
  `reconstructions()` (`DecodedSlots`), or the frames `recon` alone."""
  if hasattr(decoded, 'reconstructions'):
    return decoded.reconstructions()
  return {targets_lib.RGB.name: decoded.recon}


def _truths(batch: Batch, names: Any, frames: jax.Array | None,
            rollout: int | None = None) -> dict[str, jax.Array]:
  """{target: its batch field} of the targets `names`: 'rgb' is `frames`
  (the video already in the model's range), the others their fields as
  they are (the last `rollout` frames, when given)."""
  out = {}
  for name in names:
    if name == targets_lib.RGB.name:
      if frames is None:
        raise KeyError("the batch has no 'video' to compare the decoded "
                       'frames with')
      out[name] = frames
    else:
      values = batch[targets_lib.TARGETS[name].field]
      out[name] = values if rollout is None else values[:, -rollout:]
  return out


def savi_loss(params: Any, batch: Batch, frozen_params: Any, rng: jax.Array,
              *, model: SAVi, kl_weight: float) -> tuple[jax.Array, Metrics]:
  """Reconstruction loss of its targets (`reconstruction_loss`: the frame
  MSE for RGB) + kl_weight * KL for stochastic SAVi.

  batch['video']: uint8 [B, T, H, W, 3] (+ 'boxes' float32 [B, T, O, 4]
  for conditional SAVi; + the fields of its other targets, e.g. 'flow'
  float32 [B, T, H, W, 3], 'depth' [B, T, H, W, 1]: slotformer_jax/
  targets.py). The KL is summed over the slot dimensions and averaged over
  batch, frames and slots. Metrics: 'recon_loss', 'kl' (and
  'recon_loss_<target>' for each target when RGB is not the only one).
  """
  del frozen_params
  video = frames_to_model(batch['video'])
  sample_rng, dropout_rng = jax.random.split(rng)
  # deterministic=False: the predictor's dropout (0.1 officially) is on.
  # Conditional SAVi starts from the clip's first-frame boxes [B, O, 4].
  boxes = batch['boxes'][:, 0] if 'boxes' in batch else None
  output = model.apply({'params': params}, video, deterministic=False,
                       rngs={'sample': sample_rng, 'dropout': dropout_rng},
                       boxes=boxes)
  reconstructions = reconstructions_of(output.decoded)
  recon_loss, metrics = reconstruction_loss(
      reconstructions, _truths(batch, reconstructions, video), 'recon_loss')
  kl = jnp.mean(output.kl)
  loss = recon_loss + kl_weight * kl
  return loss, {**metrics, 'kl': kl}


def slotformer_loss(params: Any, batch: Batch, decoder_params: Any,
                    rng: jax.Array, *, model: nn.Module,
                    decoder: SpatialBroadcastDecoder | None, rollout: int,
                    image_loss_weight: float, teacher_forcing: bool,
                    to_model: Callable[[jax.Array], jax.Array] = (
                        frames_to_model)) -> tuple[jax.Array, Metrics]:
  """L = L_S + lambda * L_I on the model's own rollout.

  batch['slots']: float32 [B, burn_in + rollout, N, D];
  batch['video']: uint8 [B, T, H, W, 3] whose last `rollout` frames are the
  rollout's (T = rollout: the training stream reads only those; T =
  burn_in + rollout also works; needed when lambda > 0). L_S is the MSE between predicted and extracted slots, L_I
  the MSE between frames decoded from the predicted slots by the *frozen*
  SAVi decoder and the real frames (both averaged over every element, as the
  official implementation), in the pixel range of the slot model
  (`to_model`: uint8 frames -> the decoder's range). A decoder of other
  targets (SAVi's flow, depth) is compared with their batch fields (the
  slot model's `image_loss_fields`, same frames) as `savi_loss` does
  (`reconstruction_loss`; metrics 'image_loss_<target>' too).
  """
  burn_in = model.burn_in
  history = batch['slots'][:, :burn_in]
  target_slots = batch['slots'][:, burn_in:burn_in + rollout]
  predicted = model.apply(
      {'params': params}, history, rollout,
      teacher_slots=target_slots if teacher_forcing else None,
      deterministic=False, rngs={'dropout': rng})
  slot_loss = jnp.mean(jnp.square(predicted - target_slots))
  metrics = {'slot_loss': slot_loss}
  loss = slot_loss
  if image_loss_weight > 0:
    frames = (to_model(batch['video'][:, -rollout:]) if 'video' in batch
              else None)
    decoded = decoder.apply({'params': jax.lax.stop_gradient(decoder_params)},
                            predicted)
    reconstructions = reconstructions_of(decoded)
    image_loss, image_metrics = reconstruction_loss(
        reconstructions, _truths(batch, reconstructions, frames, rollout),
        'image_loss')
    metrics.update(image_metrics)
    loss = loss + image_loss_weight * image_loss
  return loss, metrics


def dvae_loss(params: Any, batch: Batch, frozen_params: Any, rng: jax.Array,
              *, model: DVAE) -> tuple[jax.Array, Metrics]:
  """Pixel MSE of the relaxed-code reconstruction.

  batch['video']: uint8 [B, T, H, W, 3] (single frames: T = 1);
  batch['gumbel_temperature']: float32 [B], every entry the temperature of
  the batch's step (the step is not an argument of a loss; see
  `slot_models.steve.with_gumbel_temperature`).
  """
  del frozen_params
  video = frames_to_model(batch['video'])
  images = video.reshape(-1, *video.shape[2:])
  temperature = jnp.mean(batch['gumbel_temperature'])
  recon, log_probs = model.apply({'params': params}, images, temperature,
                                 rngs={'gumbel': rng})
  loss = jnp.mean(jnp.square(recon - images))
  # How many codes the encoder uses: exp(entropy of the mean code
  # distribution), a quick check for codebook collapse.
  mean_probs = jnp.mean(jnp.exp(log_probs), axis=(0, 1, 2))
  perplexity = jnp.exp(-jnp.sum(mean_probs * jnp.log(mean_probs + 1e-10)))
  return loss, {'recon_loss': loss, 'gumbel_temperature': temperature,
                'code_perplexity': perplexity}


def steve_loss(params: Any, batch: Batch, frozen_params: Any, rng: jax.Array,
               *, model: STEVE) -> tuple[jax.Array, Metrics]:
  """Cross-entropy of the decoder's token logits against the frozen dVAE's
  tokens, averaged over batch, frames and tokens.

  batch['video']: uint8 [B, T, H, W, 3]; batch['tokens']: int [B, T, L]
  (precomputed argmax codes of the same frames).
  """
  del frozen_params
  video = frames_to_model(batch['video'])
  tokens = batch['tokens'].astype(jnp.int32)
  logits, _, _ = model.apply({'params': params}, video, tokens,
                             deterministic=False, rngs={'dropout': rng})
  loss = jnp.mean(optax.softmax_cross_entropy_with_integer_labels(
      logits, tokens))
  accuracy = jnp.mean(jnp.argmax(logits, -1) == tokens)
  return loss, {'token_loss': loss, 'token_accuracy': accuracy}
