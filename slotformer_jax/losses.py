"""The paper's losses, as pure functions of (params, batch, frozen, rng).

* SAVi: frame reconstruction MSE (+ kl_weight * KL for stochastic SAVi);
  with other targets (`config.savi.targets`: SAVi's flow, depth) one MSE
  per target (`reconstruction_loss`).
* the dynamics models (SlotFormer, Slot-LSTM, ...): a sum of registered
  terms (`register_loss`), each weighted by its config entry
  `<term>_weight`: L = L_S + lambda * L_I (slot MSE + image MSE of the
  frames -- or the slot model's other targets -- decoded by the frozen SAVi
  decoder) with `image_loss_weight` = lambda.
* STEVE's dVAE: pixel MSE of the relaxed-code reconstruction; STEVE: the
  cross-entropy of its token decoder against the frozen dVAE's tokens.

Pixels are in the [-1, 1] range of `frames.frames_to_model`. Every loss
plugs into `train.trainer.fit` as `loss_fn(params, batch, frozen_params,
rng) -> (loss, metrics)`.
"""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
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


@dataclasses.dataclass(frozen=True)
class Rollout:
  """What a loss term of a dynamics model reads (`LossTerm.fn`).

  predicted / target_slots: [B, rollout, N, D], the model's own rollout and
  the extracted slots of those frames; batch: the training batch ('slots'
  [B, burn_in + rollout, N, D], and the slot model's `image_loss_fields`
  when a term that needs the decoder is on); decoder, decoder_params: the
  slot model's frozen pixel decoder (None without such a term); to_model:
  uint8 frames -> the decoder's pixel range.
  """

  predicted: jax.Array
  target_slots: jax.Array
  batch: Batch
  rollout: int
  decoder: Any = None
  decoder_params: Any = None
  to_model: Callable[[jax.Array], jax.Array] = frames_to_model


@dataclasses.dataclass(frozen=True)
class LossTerm:
  """One term of a dynamics model's loss, registered by name.

  Attributes:
    name: its metric in the training log and, when `weighted`, its config
      entry: the dynamics section's `<name>_weight` (a section without the
      field does not train with it; 0 turns it off).
    fn: (Rollout) -> (value, metrics) (metrics include {name: value}).
    label: how messages name it ('L_I').
    weighted: False: always in the loss, at weight 1 (L_S, the objective).
    needs_decoder: it decodes the predicted slots with the slot model's
      frozen pixel decoder and reads the batch's video fields (L_I).
  """

  name: str
  fn: Callable[[Rollout], tuple[jax.Array, Metrics]]
  label: str
  weighted: bool = True
  needs_decoder: bool = False


# {name: term}, in registration order (the order they are summed in).
LOSS_TERMS: dict[str, LossTerm] = {}
# The suffix of every term's name: its weight field ends in `_loss_weight`
# (workdir/identity.py reads an absent one as 0: the term was not there).
LOSS_SUFFIX = '_loss'


TermFn = Callable[[Rollout], tuple[jax.Array, Metrics]]


def register_loss(name: str, label: str, *, weighted: bool = True,
                  needs_decoder: bool = False
                  ) -> Callable[[TermFn], TermFn]:
  """Registers a dynamics loss term `name` (a decorator of its function)."""
  if not name.endswith(LOSS_SUFFIX):
    raise ValueError(f'a loss term\'s name ends in {LOSS_SUFFIX!r}: {name!r}')

  def decorate(fn):
    LOSS_TERMS[name] = LossTerm(name, fn, label, weighted=weighted,
                                needs_decoder=needs_decoder)
    return fn

  return decorate


def weight_field(name: str) -> str:
  """The config entry of loss term `name`'s weight."""
  return f'{name}_weight'


def loss_weights(section: Any) -> dict[str, float]:
  """{term: weight} of a dynamics section: every unweighted term at 1 and
  every weighted term whose `<term>_weight` the section sets (0 included:
  the term is off), in registration order."""
  return {name: (float(section[weight_field(name)]) if term.weighted
                 else 1.0)
          for name, term in LOSS_TERMS.items()
          if not term.weighted or weight_field(name) in section}


@register_loss('slot_loss', 'L_S', weighted=False)
def slot_loss(rollout: Rollout) -> tuple[jax.Array, Metrics]:
  """L_S: the MSE between predicted and extracted slots."""
  value = jnp.mean(jnp.square(rollout.predicted - rollout.target_slots))
  return value, {'slot_loss': value}


@register_loss('image_loss', 'L_I', needs_decoder=True)
def image_loss(rollout: Rollout) -> tuple[jax.Array, Metrics]:
  """L_I: the MSE between the frames decoded from the predicted slots by
  the *frozen* decoder and the real frames, in the slot model's pixel
  range (`to_model`); a decoder of other targets (SAVi's flow, depth) is
  compared with their batch fields, as `savi_loss` does (metrics
  'image_loss_<target>' too)."""
  batch, steps = rollout.batch, rollout.rollout
  frames = (rollout.to_model(batch['video'][:, -steps:]) if 'video' in batch
            else None)
  decoded = rollout.decoder.apply(
      {'params': jax.lax.stop_gradient(rollout.decoder_params)},
      rollout.predicted)
  reconstructions = reconstructions_of(decoded)
  return reconstruction_loss(
      reconstructions, _truths(batch, reconstructions, frames, steps),
      'image_loss')


def slotformer_loss(params: Any, batch: Batch, decoder_params: Any,
                    rng: jax.Array, *, model: nn.Module,
                    decoder: SpatialBroadcastDecoder | None, rollout: int,
                    weights: dict[str, float], teacher_forcing: bool,
                    to_model: Callable[[jax.Array], jax.Array] = (
                        frames_to_model)) -> tuple[jax.Array, Metrics]:
  """A dynamics model's loss on its own rollout: the registered terms of
  `weights` ({term: weight}, `loss_weights`; SlotFormer's L_S + lambda *
  L_I), a term at weight 0 left out.

  batch['slots']: float32 [B, burn_in + rollout, N, D];
  batch['video']: uint8 [B, T, H, W, 3] whose last `rollout` frames are the
  rollout's (T = rollout: the training stream reads only those; T =
  burn_in + rollout also works; needed by L_I). Both MSEs are averaged over
  every element, as the official implementation.
  """
  burn_in = model.burn_in
  history = batch['slots'][:, :burn_in]
  target_slots = batch['slots'][:, burn_in:burn_in + rollout]
  predicted = model.apply(
      {'params': params}, history, rollout,
      teacher_slots=target_slots if teacher_forcing else None,
      deterministic=False, rngs={'dropout': rng})
  inputs = Rollout(predicted=predicted, target_slots=target_slots,
                   batch=batch, rollout=rollout, decoder=decoder,
                   decoder_params=decoder_params, to_model=to_model)
  loss, metrics = None, {}
  for name, weight in weights.items():
    term = LOSS_TERMS[name]
    if weight <= 0:
      continue
    value, term_metrics = term.fn(inputs)
    metrics.update(term_metrics)
    weighted = value if not term.weighted else weight * value
    loss = weighted if loss is None else loss + weighted
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
