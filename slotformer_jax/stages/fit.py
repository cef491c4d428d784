"""Training a stage of the pipeline: the one-seed trainer stage of each chain
of the run (`Run.chains`), its identity stamped, its architecture checked,
then the trainer (`train.seeds.fit`: one seed, or the run's seeds in one
program), which knows nothing of workdirs.

A stage says what it trains in a `Training` and hands it to `fit_chains`:

    fit_chains(run, Training(what='slotformer', chain_stage=..., offset=1,
                             identity_fields=..., model_fields=...))
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from slotformer_jax.run import Run
from slotformer_jax.train import seeds as seeds_lib
from slotformer_jax.train.seeds import Seeds
from slotformer_jax.train.trainer import Stage
from slotformer_jax.workdir import identity as identity_lib


def stamped_fields(identity_fields: dict[str, Any], seeds: Seeds
                   ) -> dict[str, Any]:
  """The identity fields a stage trained with `seeds` records: with
  several, its `identity_fields` and the seeds with their data order."""
  if not seeds.several:
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
    identity_fields: what shapes the trained model (besides its parent);
      None: it keeps no identity (VQA's Aloe).
    model_fields: its architecture, checked against its checkpoints (with
      `identity_fields`).
    seed_of: what it draws with (batches, initialisation, step RNG) in a
      chain of a seed: its own stream, apart from other stages' (the
      dynamics: seed + 1; stage 1: the seed).
    shared_data: every chain trains on the run's data (SAVi, the dVAE: the
      training videos): one stage on the run (the shared data order), or
      one per chain drawing its own order; otherwise (the dynamics, STEVE)
      one stage per chain, on its own data.
  """

  what: str
  chain_stage: Callable[[Run, int], tuple[Stage, dict[str, Any] | None]]
  identity_fields: dict[str, Any] | None
  model_fields: dict[str, Any] | None = None
  seed_of: Callable[[int], int] = lambda seed: seed
  shared_data: bool = False


def fit_chains(run: Run, training: Training) -> Any:
  """Trains `training` for every chain of the run (`Run.chains`) in one
  program, resumably (`train.seeds.fit`).

  Each chain's stage (`training.chain_stage`; with `shared_data` the run's),
  its batches drawn with its stream seed (`Seeds.stream_seeds`). Its
  identity records its fields, the seeds with their data order, and the
  first chain's parent (every chain's was checked by its `chain_stage`): a
  stage made with other settings, seeds or from another parent is set
  aside and retrained (`identity.start_stage`); its checkpoints must have
  the architecture of `model_fields`.
  """
  seeds = Seeds.of_config(run.config).map(training.seed_of)
  streams = seeds.stream_seeds(training.seed_of(run.config.seed))
  chains = run.chains()
  if training.shared_data:  # one order every seed reads, or each its own
    chains = [run] * (len(streams) if seeds.data_order == 'per_seed' else 1)
  built = [training.chain_stage(chain, stream)
           for chain, stream in zip(chains, streams)]
  stages = [stage for stage, _ in built]
  directory = stages[0].directory
  if training.identity_fields is not None:
    identity_lib.start_stage(
        directory, stamped_fields(training.identity_fields, seeds),
        built[0][1], training.what)
    identity_lib.check_model_config(directory, training.model_fields,
                                    training.what)
    identity_lib.write_model_config(directory, training.model_fields)
  return seeds_lib.fit(stages, mesh=run.mesh, seeds=seeds)
