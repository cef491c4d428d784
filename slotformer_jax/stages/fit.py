"""Training a stage of the pipeline: one trainer stage per chain of the run
(stacked with several seeds), its identity stamped, its architecture
checked, then the trainer's loop (train/trainer.py), which knows nothing of
workdirs.

A stage says what it trains in a `Training` and hands it to `fit_chains`:

    fit_chains(run, Training(what='slotformer', chain_stage=..., offset=1,
                             identity_fields=..., model_fields=...))
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections

from slotformer_jax.config.sections import several_seeds
from slotformer_jax.run import Run
from slotformer_jax.train.state import TrainState
from slotformer_jax.train.trainer import Seeds
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit
from slotformer_jax.workdir import identity as identity_lib


def seeds_of(config: ml_collections.ConfigDict, offset: int = 0
             ) -> Seeds | None:
  """The run's several seeds (config.seeds, each + `offset`: a stage's own
  stream), or None for one seed (config.seed, as before)."""
  values = several_seeds(config)
  if values is None:
    return None
  return Seeds(tuple(v + offset for v in values),
               data_order=config.seed_data_order,
               on_divergence=config.on_seed_divergence,
               seed_axis=config.seed_axis,
               loop=config.seed_loop)


def stream_seeds(seeds: Seeds | None, seed: int) -> tuple[int, ...]:
  """Each chain's data-order seed, for a stage whose stream is `seed`
  (config.seed + its offset) and whose `seeds` are `seeds_of` it: one seed,
  (seed,); several, `seed` for every seed (the shared order) or each its
  own ('per_seed')."""
  return (seed,) if seeds is None else seeds.stream_seeds(seed)


def stacked_stage(stages: list[Stage]) -> Stage:
  """One stage of K seeds from their one-seed stages, each on that seed's
  own data: seed k's batches from `stages[k]` (drawn in the order it was
  built for, `stream_seeds`), its frozen parameters (SlotFormer's L_I
  decoder; None: none) `stages[k]`'s, stacked [K, ...]; the loss, schedule,
  pictures (the first seed's) and directory are the first stage's (the
  same for every seed)."""
  frozen = [stage.frozen_params for stage in stages]
  stacked_frozen = (None if frozen[0] is None else
                    jax.tree.map(lambda *xs: jnp.stack(xs), *frozen))
  return dataclasses.replace(
      stages[0],
      seed_batches=lambda index, start_step: stages[index].batches(
          start_step),
      frozen_params=stacked_frozen, seed_frozen_params=True,
      batches_for_seed=None)


def stamped_fields(identity_fields: dict[str, Any], seeds: Seeds | None
                   ) -> dict[str, Any]:
  """The identity fields a stage trained with `seeds` records: with
  several, its `identity_fields` and the seeds with their data order."""
  if seeds is None or not seeds.several:
    return identity_fields
  return dict(identity_fields, seeds=identity_lib.seeds_entry(
      seeds.values, seeds.data_order))


@dataclasses.dataclass(frozen=True)
class Training:
  """What a training stage of the pipeline trains (`fit_chains`).

  Attributes:
    what: its name in messages ('SAVi', 'slotformer').
    chain_stage: (chain, stream seed) -> (the one-seed trainer `Stage` on
      that chain's data (`Run.chains`: the run, or a seed view), its batches
      drawn with the stream seed; the parent its identity records, e.g. the
      stage 1 its slots descend from, or None).
    identity_fields: what shapes the trained model (besides its parent).
    model_fields: its architecture, checked against its checkpoints.
    offset: its own stream of batches and RNG: config.seed + offset (with
      several seeds: each seed + offset), apart from other stages' (the
      dynamics: 1, stage 1: 0).
    shared_data: every seed trains on the same data (SAVi, the dVAE: the
      training videos): with several seeds, one stage on the run whose
      `batches_for_seed` draws each seed's batches in its data order;
      otherwise (the dynamics, STEVE) one stage per chain, stacked
      (`stacked_stage`).
  """

  what: str
  chain_stage: Callable[[Run, int], tuple[Stage, dict[str, Any] | None]]
  identity_fields: dict[str, Any]
  model_fields: dict[str, Any]
  offset: int = 0
  shared_data: bool = False


def fit_chains(run: Run, training: Training) -> TrainState:
  """Trains `training` for the run's one seed or all its seeds in one
  program, resumably.

  Each chain's stage (`training.chain_stage`; with `shared_data` one stage
  on the run), stacked with several seeds. Its identity records its fields,
  the seeds with their data order, and the first chain's parent (every
  chain's was checked by its `chain_stage`): a stage made with other
  settings, seeds or from another parent is set aside and retrained
  (`identity.start_stage`); its checkpoints must have the architecture of
  `model_fields`. Then the trainer's loop (`train.trainer.fit`).
  """
  seed = run.config.seed + training.offset
  seeds = seeds_of(run.config, training.offset)
  identity_fields = stamped_fields(training.identity_fields, seeds)
  if training.shared_data or seeds is None:
    built = [training.chain_stage(run, seed)]
  else:
    built = [training.chain_stage(chain, stream) for chain, stream
             in zip(run.chains(), seeds.stream_seeds(seed))]
  stages = [stage for stage, _ in built]
  stage = stages[0] if len(stages) == 1 else stacked_stage(stages)
  identity_lib.start_stage(stage.directory, identity_fields, built[0][1],
                           training.what)
  identity_lib.check_model_config(stage.directory, training.model_fields,
                                  training.what)
  identity_lib.write_model_config(stage.directory, training.model_fields)
  return fit(stage, mesh=run.mesh, seed=seed, seeds=seeds)
