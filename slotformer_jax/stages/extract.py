"""Slot extraction: the slot model over every video of every split.

Videos are processed in chunks of `extraction.chunk_length` frames that carry
the slot model's state, so memory does not grow with the video length. A
split whose slots came from the current slot-model checkpoint (and the same
extraction settings) is skipped; stale slots are re-extracted.
"""

from __future__ import annotations

import logging

import jax
from jax.sharding import Mesh
import ml_collections

from slotformer_jax import inference
from slotformer_jax import slot_models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.data.slots import read_meta
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.slot_models.base import uses_foreign_stage1
from slotformer_jax.runtime import sharding

logger = logging.getLogger(__name__)


def extract_slots(config: ml_collections.ConfigDict, workdir: str,
                  mesh: Mesh) -> None:
  """Writes slots/<split>/ of every `extraction.splits` split."""
  slot_model = slot_models.get(config)
  if uses_foreign_stage1(slot_model, workdir, mesh, 'slots'):
    return
  loaded = slot_model.load(workdir, mesh)
  parent = loaded.slots_parent
  slot_fields = workdir_lib.slots_identity_fields(config)
  batched = sharding.batch_sharding(mesh)
  replicated = sharding.replicated_sharding(mesh)
  encode = jax.jit(slot_model.encode,
                   in_shardings=(replicated, batched, replicated, batched),
                   out_shardings=(batched, batched))
  seed = jax.random.key(config.seed)

  def encode_chunk(batch_index, chunk, frames, carry):
    # Stochastic SAVi samples: a key per (batch, chunk), the same on rerun.
    rng = jax.random.fold_in(seed, batch_index * 10_000 + chunk)
    return encode(loaded.params, frames, rng, carry)

  local_batch_size = sharding.per_host_batch_size(
      config.extraction.batch_size, mesh)
  num_slots, slot_size = slot_model.slot_shape
  for split in config.extraction.splits:
    directory = workdir_lib.slots_dir(
        workdir_lib.stage1_workdir(config, workdir), split)
    meta = read_meta(directory)
    if (meta and meta.get('complete') and meta.get('parent') == parent
        and meta.get('fields') == slot_fields):
      logger.info('slots of %s already extracted (%s %s)', split,
                  slot_model.label, parent)
      continue
    if meta and meta.get('complete'):
      logger.info('slots of %s are stale (from %s, now %s %s): '
                  're-extracting', split, meta.get('parent'),
                  slot_model.label, parent)
    source = get_video_source(config.data, split)
    inference.encode_videos_into(
        lambda: SlotWriter(directory, len(source), num_slots, slot_size,
                           loaded.step, parent=parent, fields=slot_fields),
        source, encode_chunk, chunk_length=config.extraction.chunk_length,
        batch_size=local_batch_size, mesh=mesh, desc=f'extract {split}',
        conditioning_fields=slot_model.conditioning_fields)
    logger.info('extracted %s slots of %d %s videos', slot_model.label,
                len(source), split)
