"""Inference shared by every stage: one implementation each.

* rollouts of the dynamics models (SlotFormer, Slot-LSTM) and the copy-last
  baseline: pure functions of the parameters (the caller jits them);
* reading trained parameters from a stage folder without building an
  optimizer;
* `encode_videos`: a jitted function over every video of a source, in
  fixed-shape host batches and chunks of frames that carry a state (slot
  extraction, STEVE's tokenization).

Slot models (SAVi, STEVE) encode and decode through `slot_models/`; this
module knows nothing of them but their slot shape.

Shapes: slots [B, T, N, D]; video uint8 [B, T, H, W, 3].
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import dataclasses
import logging
import math
from typing import Any

import flax.linen as nn
import jax
from jax.experimental import multihost_utils
from jax.sharding import Mesh
import jax.numpy as jnp
import numpy as np

from slotformer_jax.data import pipeline
from slotformer_jax.runtime import progress
from slotformer_jax.runtime import sharding
from slotformer_jax.runtime.checkpoint import restore_fields
from slotformer_jax.runtime.checkpoint import restore_params
from slotformer_jax.workdir import identity as identity_lib

logger = logging.getLogger(__name__)


def rollout_slots(params: Any, burn_in_slots: jax.Array, *,
                  model: nn.Module,
                  num_steps: int, **interventions: jax.Array) -> jax.Array:
  """[B, burn_in, N, D] -> [B, num_steps, N, D] (deterministic).

  `model`: a dynamics model's module (dynamics/base.py);
  `interventions`: `slot_presence` / `frozen` ([B, N] bool, the
  counterfactual rollouts of the explorer) for a model that takes them.
  """
  return model.apply({'params': params}, burn_in_slots, num_steps,
                     **interventions)


def copy_last_rollout(burn_in_slots: jax.Array, num_steps: int) -> jax.Array:
  """The copy-last-slots baseline: the last observed slots, repeated."""
  last = burn_in_slots[:, -1:]
  return jnp.repeat(last, num_steps, axis=1)


def rollouts(dynamics_params: dict[str, Any], dynamics: dict[str, Any],
             burn_in_slots: jax.Array, num_steps: int, *,
             copy_last: bool = True) -> dict[str, jax.Array]:
  """Every method's predicted slots: {name: [B, num_steps, N, D]} for each
  dynamics model in `dynamics` ({name: module}, params in
  `dynamics_params`), plus 'copy_last' (the baseline) when asked."""
  out = {name: rollout_slots(dynamics_params[name], burn_in_slots,
                             model=model, num_steps=num_steps)
         for name, model in dynamics.items()}
  if copy_last:
    out['copy_last'] = copy_last_rollout(burn_in_slots, num_steps)
  return out


# --------------------------------------------------------------------------
# Trained parameters of a workdir (no optimizer is built)
# --------------------------------------------------------------------------


# Shapes already traced, by (module, input shapes): every stage that loads a
# model asks again (extraction, training, evaluation, render, explore), and
# tracing a model's init costs ~0.5 s even at test sizes.
_SHAPES_CACHE: dict[Any, Any] = {}
_SHAPES_CACHE_SIZE = 64


def _shape_key(value: Any) -> Any:
  """Arrays as (shape, dtype); containers item by item; others as they are."""
  if isinstance(value, (np.ndarray, jax.Array, jax.ShapeDtypeStruct)):
    return ('array', tuple(value.shape), str(value.dtype))
  if isinstance(value, (tuple, list)):
    return (type(value).__name__, tuple(_shape_key(v) for v in value))
  if isinstance(value, dict):
    return ('dict', tuple(sorted((k, _shape_key(v)) for k, v in value.items())))
  return value


def param_shapes(module, *args, **kwargs) -> Any:
  """The parameter shapes of `module` for example inputs (no compute;
  remembered per module and input shapes: linen modules compare by their
  fields)."""
  try:
    key = (module, _shape_key(args), _shape_key(kwargs),
           jax.config.jax_enable_x64)
    shapes = _SHAPES_CACHE.get(key)
  except TypeError:  # a field or input that cannot be hashed: not kept
    key, shapes = None, None
  if shapes is None:
    rngs = {name: jax.random.key(0)
            for name in ('params', 'sample', 'dropout', 'gumbel')}
    shapes = jax.eval_shape(
        lambda: module.init(rngs, *args, **kwargs)['params'])
    if key is not None:
      if len(_SHAPES_CACHE) >= _SHAPES_CACHE_SIZE:
        _SHAPES_CACHE.pop(next(iter(_SHAPES_CACHE)))
      _SHAPES_CACHE[key] = shapes
  return shapes


def restore(directory: str, shapes: Any, mesh: Mesh, *, what: str,
            train_command: str, num_train_steps: int) -> tuple[Any, int]:
  """The newest parameters of the stage folder `directory` (replicated) and
  their step; a warning when it was trained for fewer steps than asked.

  Raises:
    UserError: no checkpoint (the message names `train_command`), or none
      fits.
  """
  params, step = restore_params(
      directory, shapes, sharding.replicated_sharding(mesh), what=what,
      train_command=train_command)
  if step < num_train_steps:
    logger.warning('%s was trained for %d of %d steps only', what, step,
                   num_train_steps)
  return params, step


@dataclasses.dataclass(frozen=True)
class StackedSeed:
  """Seed `seeds[index]` of a run that trains `seeds` in one program
  (config.seeds): index `index` of its stages' stacked checkpoints.

  Attributes:
    seeds: every seed of the run, in order (config.seeds).
    index: this seed's position in `seeds` and in the stacked state.
    data_order: config.seed_data_order (the stacked stages record it).
  """

  seeds: tuple[int, ...]
  index: int
  data_order: str

  @property
  def seed(self) -> int:
    return self.seeds[self.index]

  def identity_fields(self) -> dict[str, Any]:
    """What the identity of a stacked stage records besides its own fields:
    its seeds and their data order."""
    return {'seeds': identity_lib.seeds_entry(self.seeds, self.data_order)}


@jax.jit
def _seed_slice(stacked: Any, index: jax.Array) -> Any:
  """[K, ...] leaves -> their [index] (one compile for every index)."""
  return jax.tree.map(lambda x: x[index], stacked)


def restore_seed(directory: str, shapes: Any, mesh: Mesh,
                 stacked: StackedSeed, *, what: str, train_command: str,
                 num_train_steps: int) -> tuple[Any, int, int]:
  """`restore` of one seed of a stage trained with several seeds in one
  program (one checkpoint of the stacked [K, ...] state, train/seeds.py):
  seed `stacked.index`'s parameters of `shapes` (replicated), their step,
  and the update in which that seed diverged (its recorded `diverged_at`;
  0: it trained to the end, its parameters are then its last finite ones).

  Raises:
    UserError: no checkpoint (the message names `train_command`), or none
      fits K seeds of `shapes`.
  """
  count = len(stacked.seeds)
  replicated = sharding.replicated_sharding(mesh)
  fields, step = restore_fields(
      directory, {'params': jax.tree.map(
          lambda x: jax.ShapeDtypeStruct((count, *x.shape), x.dtype),
          shapes),
                  'diverged_at': jax.ShapeDtypeStruct((count,), np.int32)},
      replicated, what=what, train_command=train_command)
  params = jax.device_put(
      _seed_slice(fields['params'], np.int32(stacked.index)), replicated)
  diverged_at = int(np.asarray(
      fields['diverged_at'].addressable_data(0))[stacked.index])
  if step < num_train_steps:
    logger.warning('%s (seed %d) was trained for %d of %d steps only', what,
                   stacked.seed, step, num_train_steps)
  return params, step, diverged_at


# --------------------------------------------------------------------------
# A function over every video of a source
# --------------------------------------------------------------------------

# encode_chunk(batch_index, chunk_index, frames uint8 [B, C, H, W, 3] (global,
# batch-sharded), carry) -> (out [B, C, ...], carry).
ChunkFn = Callable[[int, int, jax.Array, Any], tuple[jax.Array, Any]]


def _padded_clip(video: np.ndarray, num_frames: int) -> np.ndarray:
  """video [T, ...] -> [num_frames, ...], repeating the last frame."""
  if len(video) >= num_frames:
    return video[:num_frames]
  padding = np.repeat(video[-1:], num_frames - len(video), axis=0)
  return np.concatenate([video, padding], axis=0)


def encode_videos(source: pipeline.Source, encode_chunk: ChunkFn, *,
                  chunk_length: int, batch_size: int, mesh: Mesh,
                  desc: str, conditioning_fields: Sequence[str] = ()
                  ) -> Iterator[tuple[int, np.ndarray]]:
  """`encode_chunk` over every video of `source`, chunk after chunk.

  Each host encodes its own videos (`pipeline.host_batches`: p, p + P, ...)
  in batches of at most `batch_size` (per host, `pipeline.host_batch_plan`:
  a 2-video split is one batch of 2); videos are padded to a whole
  number of chunks of `chunk_length` frames by repeating their last frame,
  every host running the same number of batches and chunks (the collectives
  of a multi-host run stay in lockstep, also on a host with no video). The
  carry starts as None for every batch, or with `conditioning_fields` as
  those fields of each video's first frame ({field: [B, ...]}, the fresh
  start of a conditional slot model).

  Yields, on every host, (video index, out [T, ...]) of every video of the
  source (all hosts' results are gathered), T its own number of frames.
  """
  process_index, process_count = jax.process_index(), jax.process_count()
  plan = list(pipeline.host_batches(len(source), batch_size, process_index,
                                    process_count,
                                    multiple_of=len(mesh.local_devices)))
  progress.compiling(desc, 'chunk')
  for batch_index, (indices, valid) in enumerate(progress.bar(
      plan, desc=desc, unit='batch')):
    items = [source[int(i)] for i in indices]
    videos = [item['video'] for item in items]
    lengths = np.array([len(v) for v in videos])
    num_chunks = math.ceil(lengths.max() / chunk_length)
    if process_count > 1:  # all hosts must run the same number of chunks
      num_chunks = int(multihost_utils.process_allgather(
          np.array(num_chunks)).max())
    padded = np.stack([_padded_clip(v, num_chunks * chunk_length)
                       for v in videos])
    carry, chunks = None, []
    if conditioning_fields:
      carry = sharding.to_global_batch(
          {field: np.stack([np.asarray(item[field][0]) for item in items])
           for field in conditioning_fields}, mesh)
    # A long video is one unit of the bar: its chunks say more.
    steps = progress.Steps(f'{desc} batch {batch_index + 1}/{len(plan)}',
                           num_chunks, 'chunks')
    for chunk in range(num_chunks):
      frames = padded[:, chunk * chunk_length:(chunk + 1) * chunk_length]
      out, carry = encode_chunk(
          batch_index, chunk,
          sharding.to_global_batch({'video': frames}, mesh)['video'], carry)
      chunks.append(out)
      if chunk:  # the one before is done (one chunk stays in flight)
        jax.block_until_ready(chunks[-2])
        steps.reached(chunk)
    gathered = sharding.gather_to_host({
        'out': jnp.concatenate(chunks, axis=1),
        **sharding.to_global_batch(
            {'index': indices, 'length': lengths, 'valid': valid}, mesh)})
    for out, index, length, is_valid in zip(
        gathered['out'], gathered['index'], gathered['length'],
        gathered['valid']):
      if is_valid:
        yield int(index), out[:length]


def encode_videos_into(make_writer: Callable[[], Any], source: pipeline.Source,
                       encode_chunk: ChunkFn, *, chunk_length: int,
                       batch_size: int, mesh: Mesh, desc: str,
                       conditioning_fields: Sequence[str] = ()) -> None:
  """`encode_videos`, each video's output added to the writer
  `make_writer()` builds on the lead host (a `SlotWriter`, `TokenWriter`:
  `add(index, out)`, `close()`); every host waits until it is closed."""
  writer = make_writer() if jax.process_index() == 0 else None
  for index, out in encode_videos(source, encode_chunk,
                                  chunk_length=chunk_length,
                                  batch_size=batch_size, mesh=mesh,
                                  desc=desc,
                                  conditioning_fields=conditioning_fields):
    if writer is not None:
      writer.add(index, out)
  if writer is not None:
    writer.close()
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices(f'{desc} written')
