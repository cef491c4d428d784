"""Slot extraction: the slot model over every video of every split.

Videos are processed in chunks of `extraction.chunk_length` frames that carry
the slot model's state, so memory does not grow with the video length. A
split whose slots came from the current slot-model checkpoint (and the same
extraction settings) is skipped; stale slots are re-extracted.

Chain after chain (`Run.chains`): a seed view of a K-seed run extracts
with its share of stage 1 into `seed_<s>/slots/<split>/`, drawing with its
seed (stochastic SAVi's samples) as a one-seed run draws with config.seed.
"""

from __future__ import annotations

import logging
from typing import Any

import jax

from slotformer_jax import inference
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.data.slots import read_meta
from slotformer_jax.errors import UserError
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.stages.stage1 import uses_foreign_stage1
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import command

logger = logging.getLogger(__name__)


def extract_slots(run: Run) -> None:
  """Writes slots/<split>/ of every `extraction.splits` split, each
  chain's in its folders."""
  for chain in run.chains():
    _extract(chain)


def _extract(run: Run) -> None:
  """The slots of every `extraction.splits` split of `run` (one seed, or a
  seed view) in `run.paths.slots(split)`."""
  if uses_foreign_stage1(run, 'slots'):
    return
  slot_model, extraction = run.slot_model, run.config.extraction
  loaded = run.stage1
  parent, slot_fields = loaded.slots_parent, run.slots_fields
  batched = sharding.batch_sharding(run.mesh)
  replicated = sharding.replicated_sharding(run.mesh)
  encode = jax.jit(slot_model.encode,
                   in_shardings=(replicated, batched, replicated, batched),
                   out_shardings=(batched, batched))
  seed = jax.random.key(run.seed)

  def encode_chunk(batch_index, chunk, frames, carry):
    # Stochastic SAVi samples: a key per (batch, chunk), the same on rerun.
    rng = jax.random.fold_in(seed, batch_index * 10_000 + chunk)
    return encode(loaded.params, frames, rng, carry)

  local_batch_size = sharding.per_host_batch_size(extraction.batch_size,
                                                  run.mesh)
  num_slots, slot_size = slot_model.slot_shape
  for split in extraction.splits:
    directory = run.paths.slots(split)
    meta = read_meta(directory)
    if (meta and meta.get('complete') and meta.get('parent') == parent
        and meta.get('fields') == slot_fields):
      logger.info('slots of %s already extracted (%s %s)%s', split,
                  slot_model.label, parent, _of_seed(run))
      continue
    if meta and meta.get('complete'):
      _refuse_lost_steps(run, directory, meta.get('parent'), parent,
                         slot_model.label)
      logger.info('slots of %s are stale (from %s, now %s %s): '
                  're-extracting', split, meta.get('parent'),
                  slot_model.label, parent)
    source = run.videos(split)
    inference.encode_videos_into(
        lambda: SlotWriter(directory, len(source), num_slots, slot_size,
                           loaded.step, parent=parent, fields=slot_fields),
        source, encode_chunk, chunk_length=extraction.chunk_length,
        batch_size=local_batch_size, mesh=run.mesh,
        desc=f'extract {split}{_of_seed(run)}',
        conditioning_fields=slot_model.conditioning_fields)
    logger.info('extracted %s slots of %d %s videos%s', slot_model.label,
                len(source), split, _of_seed(run))


def _of_seed(run: Run) -> str:
  """' (seed s)' for a seed view, '' for a one-seed run (its messages)."""
  return '' if run.seed_index is None else f' (seed {run.seed})'


def _refuse_lost_steps(run: Run, directory: str, made_from: Any,
                       parent: dict[str, Any], label: str) -> None:
  """Slots made by a newer step of the same slot-model run than the one
  restored now are good (its newer checkpoints were lost): they are not
  overwritten from the older step; the line names the retraining.

  Raises:
    UserError: `identity.lost_steps` found such a step.
  """
  lost = identity_lib.lost_steps(made_from, parent)
  if lost is not None:
    raise UserError(
        identity_lib.lost_steps_advice(
            label, f'the slots in {directory}', lost,
            command(run.paths.stage1, f'train_{lost[0]}'))
        + f' (delete {directory} to extract from step {lost[1]} instead).')
