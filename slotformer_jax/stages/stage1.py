"""Stage 1 of any slot model: train each part it declares, compute the data
one part derives for the next, in the order the slot model gives.

`stage_functions(slot_model)` returns its modes ({'train_savi': fn} or
{'train_dvae', 'tokenize_frames', 'train_steve'}). A part is trained on the
training videos (plus the derived data it reads); its identity records the
part it descends from, a part trained from other settings or another parent
is set aside and retrained, and a stage 1 read from another workdir
(`config.stage1_workdir`) is only checked, never written.

Each chain of the run (`Run.chains`: the run, or each seed view of a
K-seed run) has its own share of a part and its own derived data (in
`seed_<s>/`, e.g. STEVE's `seed_<s>/tokens/train/`). A part with no parent
(SAVi, the dVAE) trains on the run's training videos, a part trained on
another (STEVE) on each chain's derived data; every chain's in one program
(`stages/fit.py` `fit_chains`), one checkpoint per part.
"""

from __future__ import annotations

import functools
import logging
from typing import Any

import jax
from jax.sharding import Mesh

from slotformer_jax import inference
from slotformer_jax.data import pipeline
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.modules import initializers
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.slot_models import chain
from slotformer_jax.slot_models.base import Derived
from slotformer_jax.slot_models.base import Part
from slotformer_jax.stages.fit import Training
from slotformer_jax.stages.fit import fit_chains
from slotformer_jax.train import steps
from slotformer_jax.train.trainer import Stage
from slotformer_jax.workdir import identity as identity_lib
from slotformer_jax.workdir.paths import command

logger = logging.getLogger(__name__)


def stage_functions(run: Run) -> dict[str, Any]:
  """{mode: (run) -> None} of the run's slot model, in training order."""
  slot_model = run.slot_model
  table = {}
  for part in slot_model.parts:
    table[part.mode] = functools.partial(train_part, name=part.name)
    for derived in slot_model.derived:
      if derived.source == part.name:
        table[derived.mode] = functools.partial(derive, name=derived.name)
  return table


def uses_foreign_stage1(run: Run, what: str) -> bool:
  """True (after checking it) when stage 1 is another workdir's: the stage
  `what` then has nothing to do here. That workdir's stage 1 must hold
  every chain's share, each checked with its slots (a seed view: its
  own)."""
  if not run.paths.foreign_stage1:
    return False
  for view in run.chains():
    chain.check_foreign_stage1(view.slot_model, view.paths, view.mesh,
                               tuple(view.config.extraction.splits),
                               view.slots_fields, view.stacked)
  logger.info('%s: using the read-only stage 1 in %s', what,
              run.paths.stage1)
  return True


def _part(run: Run, name: str) -> Part:
  return {part.name: part for part in run.slot_model.parts}[name]


def _derived(run: Run, name: str) -> Derived:
  return {d.name: d for d in run.slot_model.derived}[name]


def part_stage(part: Part, directory: str, mesh: Mesh, source: Any, *,
               seed: int, logging_config: Any = None,
               reader_workers: int = 0) -> Stage:
  """The trainer's `Stage` of `part` on `source` (the training videos, with
  the data it reads; only its `batches` read it), read by `reader_workers`
  processes (`data.reader_workers`)."""
  local_batch_size = sharding.per_host_batch_size(part.section.batch_size,
                                                  mesh)

  def init_params(rng):
    params = steps.init_params(part.module, rng, *part.example,
                               **part.example_kwargs)
    if part.init is None:
      return params
    return initializers.initialize(params, jax.random.fold_in(rng, 1),
                                   part.init)

  def batches(start_step):
    stream = pipeline.train_batches(
        source, batch_size=local_batch_size, clip_length=part.clip_length,
        seed=seed, start_step=start_step, fields=part.batch_fields,
        process_index=jax.process_index(), process_count=jax.process_count(),
        num_workers=reader_workers, transform=part.transform)
    return (part.with_batches(stream, start_step)
            if part.with_batches is not None else stream)

  return Stage(name=part.name, directory=directory, config=part.section,
               loss_fn=part.loss, init_params=init_params,
               batches=batches,
               logging=logging_config, images=part.images)


def _parent(run: Run, part: Part) -> dict[str, Any] | None:
  """What `part` is trained on: its parent part's run id and newest step
  (a seed view: of the stacked parent every seed shares)."""
  if part.parent is None:
    return None
  parent = _part(run, part.parent)
  _, step = chain.load_part(parent, run.paths, run.mesh, run.stacked)
  return identity_lib.parent_of(
      chain.part_identity(parent, run.paths, run.stacked), step, parent.name)


def check_derived_current(run: Run, derived: Derived, split: str,
                          parent: dict[str, Any]) -> None:
  """The derived data of `split` must come from the part `parent`.

  Raises:
    UserError: missing or stale, with the command that rebuilds it.
  """
  directory = run.paths.derived(derived.name, split)
  meta = derived.read_meta(directory)
  rebuild = command(run.paths.stage1, derived.mode)
  source_label = run.slot_model.stage_labels[derived.source]
  if not (meta and meta.get('complete')):
    raise MissingInputError(
        f'no complete {source_label} {derived.name} in {directory}; compute '
        f'them: {rebuild}')
  lost = identity_lib.lost_steps(meta.get('parent'), parent)
  if lost is not None:
    raise UserError(identity_lib.lost_steps_advice(
        source_label, f'the {derived.name} in {directory}', lost,
        command(run.paths.stage1, f'train_{lost[0]}')) + '.')
  if meta.get('parent') != parent:
    raise UserError(
        f'the {derived.name} in {directory} are stale: made by '
        f'{source_label} {meta.get("parent")}, the current {source_label} '
        f'is {parent}. Recompute them: {rebuild}')


def train_part(run: Run, name: str) -> None:
  """Trains part `name` of the slot model on the training videos (resumable);
  set aside and retrained when its settings or its parent changed. Every
  chain in one program: a part without a parent (SAVi, the dVAE) on the
  training videos they share; a part trained on another (STEVE on the
  dVAE's tokens) on each chain's data, each checked to come from the
  chain's share of the parent part (`_parent`)."""
  part = _part(run, name)
  if uses_foreign_stage1(run, part.label):
    return
  parent = _parent(run.chains()[0], part)
  fit_chains(run, Training(
      what=part.label,
      chain_stage=lambda chain, stream: (
          _view_stage(chain, part, parent, stream), parent),
      identity_fields=dict(part.identity_fields),
      model_fields=dict(part.model_fields),
      shared_data=part.parent is None and not part.reads))


def _view_stage(run: Run, part: Part, parent: dict[str, Any] | None,
                stream_seed: int) -> Stage:
  """The one-seed training stage of `part` on the training videos of `run`
  (a run, or a seed view: that seed's derived data) with the derived data
  it reads, checked to come from `parent`; batches drawn with
  `stream_seed`; its directory the part's (stacked for a seed view).

  Raises:
    UserError: the derived data are missing or stale.
  """
  source = run.videos('train')
  for derived_name in part.reads:
    derived = _derived(run, derived_name)
    for split in derived.splits:
      check_derived_current(run, derived, split, parent)
    source = derived.reader(run.paths.derived(derived.name, 'train'), source)
  run.slot_model.check_data(source, 'train')
  return part_stage(part, run.paths.model(part.name), run.mesh, source,
                    seed=stream_seed, logging_config=run.config.logging,
                    reader_workers=run.config.data.reader_workers)


def derive(run: Run, name: str) -> None:
  """Computes the derived data `name` of every split it is needed for, with
  the frozen part that makes it (skipped when it came from that part's
  current checkpoint), chain after chain (`Run.chains`), each with its
  share of the part, into its folders."""
  derived = _derived(run, name)
  if uses_foreign_stage1(run, derived.name):
    return
  batched = sharding.batch_sharding(run.mesh)
  encode = jax.jit(derived.encode,
                   in_shardings=(sharding.replicated_sharding(run.mesh),
                                 batched),
                   out_shardings=batched)
  for view in run.chains():
    _derive(view, derived, encode)


def _derive(run: Run, derived: Derived, encode: Any) -> None:
  """The derived data of every split of `derived` for `run` (a run, or a
  seed view: its share of the stacked source part, its folders), with
  `encode` (`derived.encode`, jitted)."""
  source_part = _part(run, derived.source)
  params, step = chain.load_part(source_part, run.paths, run.mesh,
                                 run.stacked)
  parent = identity_lib.parent_of(
      chain.part_identity(source_part, run.paths, run.stacked), step,
      source_part.name)
  of_seed = '' if run.seed_index is None else f' (seed {run.seed})'
  local_batch_size = sharding.per_host_batch_size(derived.batch_size,
                                                  run.mesh)
  for split in derived.splits:
    directory = run.paths.derived(derived.name, split)
    meta = derived.read_meta(directory)
    if meta and meta.get('complete') and meta.get('parent') == parent:
      logger.info('%s of %s already computed (%s %s)%s', derived.name, split,
                  source_part.label, parent, of_seed)
      continue
    lost = (identity_lib.lost_steps(meta.get('parent'), parent)
            if meta and meta.get('complete') else None)
    if lost is not None:  # good ones: the model's newer steps were lost
      raise UserError(
          identity_lib.lost_steps_advice(
              source_part.label, f'the {derived.name} in {directory}', lost,
              command(run.paths.stage1, f'train_{lost[0]}'))
          + f' (delete {directory} to compute them from step {lost[1]} '
          'instead).')
    if meta and meta.get('complete'):
      logger.info('%s of %s are stale (from %s %s, now %s): recomputing%s',
                  derived.name, split, source_part.label, meta.get('parent'),
                  parent, of_seed)
    videos = run.videos(split)
    inference.encode_videos_into(
        lambda: derived.writer(directory, len(videos), step, parent),
        videos, lambda b, c, frames, carry: (encode(params, frames), None),
        chunk_length=derived.chunk_length, batch_size=local_batch_size,
        mesh=run.mesh, desc=f'{derived.mode} {split}{of_seed}')
    logger.info('%s: %d %s videos%s', derived.mode, len(videos), split,
                of_seed)
