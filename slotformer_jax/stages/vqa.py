"""VQA stages: slots (+ SlotFormer rollout) per video -> train Aloe -> evaluate.

Run after the video pipeline (SAVi, extraction, SlotFormer): ``vqa_slots``
writes every video's slots, and SlotFormer's rollout after them, to
``vqa/slots/<split>.npy`` (float32 [V, video_length + rollout, N, D]);
``train_vqa`` trains Aloe into ``vqa/<inputs>_s<seed>/``; ``evaluate_vqa``
writes its metrics (and the answer prior) there. Questions and vocabulary
come with the embedded family's dataset; for CLEVRER from
``vqa.questions_root`` (and optionally ``vqa.vocab_file``). With several
seeds each chain gets its own slots and Aloe (docs/seeds.md). The workdir
files and the commands: docs/vqa.md, "Workdir".
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import os
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import tqdm

from slotformer_jax import inference
from slotformer_jax.config import defaults
from slotformer_jax.config.sections import primary_dynamics
from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.data import vqa_questions
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.errors import UserError
from slotformer_jax.evaluation import seeds as seeds_lib
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding
from slotformer_jax.stages import fit as fit_lib
from slotformer_jax.stages.task import Task
from slotformer_jax.stages.task import register
from slotformer_jax.tasks import vqa as task
from slotformer_jax.train import steps
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import abstract_train_state
from slotformer_jax.train.trainer import checkpointer_for
from slotformer_jax.workdir.paths import command

logger = logging.getLogger(__name__)

# 'future': the ground-truth future, i.e. SAVi's slots of the real frames
# after the video (the extraction must cover them): the ceiling of what any
# rollout can give predictive questions (embedded data only).
INPUTS = ('observed', 'rollout', 'blind', 'future')


def _check_inputs(vqa: ml_collections.ConfigDict) -> None:
  if vqa.inputs not in INPUTS:
    raise ConfigError(f'vqa.inputs must be one of {INPUTS}, got '
                      f'{vqa.inputs!r}')


# ----------------------------------------------------------------------------
# Slots per video: observed, then SlotFormer's rollout
# ----------------------------------------------------------------------------


def _slots_path(run: Run, split: str) -> str:
  return os.path.join(run.paths.vqa_slots, f'{split}.npy')


def vqa_slots(run: Run) -> None:
  """Writes each split's observed slots followed by SlotFormer's rollout
  (several seeds: each chain's, SlotFormer seed s on slot model seed s's
  slots)."""
  for chain in run.chains():
    _vqa_slots(chain)


def _vqa_slots(run: Run) -> None:
  """`vqa_slots` of one chain."""
  config = run.config
  vqa = config.vqa
  dynamics = run.dynamics_section(primary_dynamics(run.config))
  trained = run.dynamics(primary_dynamics(run.config))
  params, step, model = trained.params, trained.step, trained.module
  meta_path = os.path.join(run.paths.vqa_slots, 'meta.json')
  meta = {'slotformer_step': step, 'video_length': vqa.video_length,
          'rollout_frames': vqa.rollout_frames}
  if os.path.exists(meta_path) and read_json(meta_path) == meta and all(
      os.path.exists(_slots_path(run, s))
      for s in config.extraction.splits):
    logger.info('VQA slots already rolled out (SlotFormer step %d)', step)
    return
  params = sharding.gather_to_host(params)
  roll = jax.jit(functools.partial(inference.rollout_slots, model=model),
                 static_argnames='num_steps')

  def rollout(history: np.ndarray, num_steps: int) -> np.ndarray:
    return np.asarray(roll(params, jnp.asarray(history), num_steps=num_steps))

  os.makedirs(os.path.dirname(meta_path), exist_ok=True)
  batch_size = config.extraction.batch_size
  for split in config.extraction.splits:
    source = SlotSource(run.paths.slots(split))
    out = None
    for first in tqdm.trange(0, len(source), batch_size,
                             desc=f'vqa rollout {split}'):
      ids = range(first, min(len(source), first + batch_size))
      observed = np.stack([source[i]['slots'][:vqa.video_length]
                           for i in ids])
      if observed.shape[1] != vqa.video_length:
        raise ConfigError(f'{split} videos have {observed.shape[1]} frames '
                          f'of slots, vqa.video_length is {vqa.video_length}')
      future = task.rollout_after_video(
          rollout, observed, burn_in=dynamics.burn_in,
          stride=dynamics.frame_stride, num_frames=vqa.rollout_frames)
      both = np.concatenate([observed, future], axis=1).astype(np.float32)
      if out is None:
        out = np.lib.format.open_memmap(
            _slots_path(run, split) + '.tmp.npy', mode='w+',
            dtype=np.float32, shape=(len(source),) + both.shape[1:])
      out[first:first + len(both)] = both
    out.flush()
    del out
    os.replace(_slots_path(run, split) + '.tmp.npy',
               _slots_path(run, split))
  write_json_atomic(meta_path, meta)


def _true_future_slots(run: Run, split: str, length: int) -> np.ndarray:
  """SAVi's slots of the video and of the real frames after it, float32
  [V, length, N, D] (length = video_length + rollout_frames): the input of
  the ground-truth-future ceiling (`vqa.inputs='future'`)."""
  source = SlotSource(run.paths.slots(split))
  out = []
  for i in range(len(source)):
    slots = source[i]['slots']
    if len(slots) < length:
      raise ConfigError(
          f"vqa.inputs='future' needs slots of {length} frames per video "
          f'(the video and the frames after it), {split} video {i} has '
          f'{len(slots)}: extract slots over the whole simulated clip')
    out.append(slots[:length])
  return np.stack(out).astype(np.float32)


def questions_with_videos(run: Run, split: str, vocab: vqa_data.Vocabulary,
                          *, scoring: bool = False) -> vqa_questions.Joined:
  """The split's questions joined to its videos by name; the ones whose
  video is not in the converted split are reported (counts, examples) and
  left out.

  Raises:
    UserError: the split has no question, or no question has its video;
      or, when `scoring`, more than `vqa.max_missing_video_fraction` of them
      have none (a score over the rest would not be the split's).
  """
  vqa = run.config.vqa
  joined = vqa_questions.joined_questions(run.config, split, vocab)
  if not joined.total:
    raise UserError(
        f'VQA: the {split} question file under '
        f'{vqa_questions.questions_root(run.config)}/questions holds no '
        'question')
  if joined.num_missing:
    logger.warning('VQA %s', joined.report(split))
  problem = joined.problem(split, vqa.max_missing_video_fraction, scoring)
  if problem:
    raise UserError(problem)
  return joined


def missing_video_problems(run: Run, stages: Sequence[str]) -> list[str]:
  """Before any work (`stages.check`): the question-to-video check of the
  splits `stages` read, where the converted data is there already (the
  converter knew which videos it skipped): the same line the VQA stage
  would stop with after stage 1 and the dynamics model are trained. Data or
  questions not there yet: nothing here (the stage that reads them says)."""
  vqa = run.config.vqa
  splits = ([('train', False)] if 'train_vqa' in stages else []) + (
      [(vqa.eval_split, True)] if 'evaluate_vqa' in stages else [])
  problems = []
  for split, scoring in splits:
    try:
      joined = vqa_questions.coverage(run.config, split)
    except (UserError, OSError):
      continue
    problem = joined.problem(split, vqa.max_missing_video_fraction, scoring)
    if problem:
      problems.append(problem)
  return problems


def question_batches(run: Run, split: str, joined: vqa_questions.Joined
                     ) -> task.QuestionBatches:
  """Batches of the `joined` questions (`questions_with_videos`), each
  reading the slots of the video it names."""
  config = run.config
  vqa = config.vqa
  _check_inputs(vqa)
  path = _slots_path(run, split)
  if not os.path.exists(path):
    raise MissingInputError(f'{path} is missing: run --mode=vqa_slots first')
  slots = np.load(path, mmap_mode='r')
  if len(slots) != len(joined.rows):
    raise UserError(
        f'{path} holds the slots of {len(slots)} videos, the converted '
        f'{split} split has {len(joined.rows)}: the slots are from another '
        f'conversion; delete {run.paths.slots(split)} and {path}, and re-run '
        '--mode=extract_slots, then --mode=vqa_slots')
  if vqa.inputs == 'future':
    slots = _true_future_slots(run, split, slots.shape[1])
  elif vqa.inputs != 'rollout':
    slots = slots[:, :vqa.video_length]  # no rollout: predictive questions
    # read the end of the video like the others
  return task.QuestionBatches(
      joined.questions, lambda name: slots[joined.row(name)],
      video_length=vqa.video_length, num_frames=vqa.num_frames,
      stride=vqa.frame_stride, max_choices=vqa.max_choices,
      blind=vqa.inputs == 'blind',
      choice_weights=(dict(vqa.choice_type_weights)
                      if vqa.choice_type_weights else None))


# ----------------------------------------------------------------------------
# Training and evaluation
# ----------------------------------------------------------------------------


def model_and_init(vqa: ml_collections.ConfigDict,
                   vocab: vqa_data.Vocabulary, slot_shape: tuple[int, int]):
  """(Aloe, rng -> its initial parameters) for `vocab` over slots of
  `slot_shape` (N, D)."""
  model = task.build_aloe(vqa, len(vocab.questions), len(vocab.answers),
                          num_slots=slot_shape[0])
  length = vqa.max_question_len + vqa.max_choice_len
  slots = jnp.zeros((1, vqa.num_frames, *slot_shape))

  def init(rng: jax.Array) -> Any:
    return steps.init_params(
        model, rng, slots, jnp.zeros((1, length), jnp.int32),
        jnp.zeros((1, length), bool), slots,
        jnp.zeros((1, 1, length), jnp.int32), jnp.zeros((1, 1, length), bool))
  return model, init


def aloe_stage(vqa: ml_collections.ConfigDict, directory: str,
               vocab: vqa_data.Vocabulary, slot_shape: tuple[int, int],
               batches, logging_config: ml_collections.ConfigDict | None = None
               ) -> Stage:
  """Aloe's training stage (the `vqa` section) for `vocab` in `directory`;
  `batches` (start step -> this host's question batches,
  `task.QuestionBatches.train_batches`) is only read by `fit`."""
  model, init = model_and_init(vqa, vocab, slot_shape)
  return Stage(
      name=f'vqa_{vqa.inputs}', directory=directory,
      config=vqa, loss_fn=functools.partial(task.vqa_loss, model=model),
      init_params=lambda rng: {'params': init(rng)}, batches=batches,
      logging=logging_config)


def drawn_batch_sizes(vqa: ml_collections.ConfigDict,
                      batches: task.QuestionBatches) -> tuple[int, int]:
  """(descriptive, multiple-choice) questions per training step, global:
  `vqa.open_batch_size` / `vqa.choice_batch_size`, or 0 for a kind the
  training questions have none of (an open-only or choice-only set: that
  kind is not drawn).

  Raises:
    UserError: neither kind is drawn (no question of a kind with a batch
      size > 0).
  """
  sizes = []
  for kind, questions, field in (
      ('descriptive', batches.open, 'open_batch_size'),
      ('multiple-choice', batches.choice, 'choice_batch_size')):
    size = vqa[field]
    if size and not questions:
      logger.info('VQA train: no %s questions; only the other kind is '
                  'drawn (vqa.%s=%d unused)', kind, field, size)
      size = 0
    sizes.append(size)
  if not any(sizes):
    raise UserError(
        f'VQA train: nothing to draw: {len(batches.open)} descriptive '
        f'questions with vqa.open_batch_size={vqa.open_batch_size}, '
        f'{len(batches.choice)} multiple-choice ones with '
        f'vqa.choice_batch_size={vqa.choice_batch_size}; give a kind the '
        'training questions have a batch size > 0')
  return sizes[0], sizes[1]


def aloe_seed(run_seed: int, vqa: ml_collections.ConfigDict) -> int:
  """What Aloe draws with (initialisation, dropout, question order) in a
  run of seed `run_seed`: run_seed * 1000 + vqa.seed."""
  return run_seed * 1000 + vqa.seed


def _train_stage(run: Run, directory: str, vocab: vqa_data.Vocabulary,
                 stream_seed: int) -> Stage:
  """Aloe's stage on `run`'s (a chain's) training slots, its questions
  drawn with `stream_seed`."""
  config, mesh = run.config, run.mesh
  vqa = config.vqa
  batches = question_batches(run, 'train', questions_with_videos(
      run, 'train', vocab))
  open_total, choice_total = drawn_batch_sizes(vqa, batches)
  open_size = sharding.per_host_batch_size(open_total, mesh)
  choice_size = sharding.per_host_batch_size(choice_total, mesh)
  return aloe_stage(
      vqa, directory, vocab, run.slot_model.slot_shape,
      lambda start_step: batches.train_batches(
          open_size, choice_size, seed=stream_seed, start_step=start_step,
          process_index=jax.process_index(),
          process_count=jax.process_count()), config.logging)


def train_vqa(run: Run) -> None:
  """Trains Aloe on the training questions (resumable); a question set of
  one kind (open-only, choice-only) trains on that kind. Each chain's Aloe
  (`Run.chains`) on its slots, all in one program, drawing with `aloe_seed`
  of its chain's seed (initialisation, step RNG; questions in the shared or
  per-seed order, config.seed_data_order)."""
  config = run.config
  vqa = config.vqa
  vocab = vqa_questions.vocabulary(config)
  directory = run.paths.aloe(vqa.inputs, vqa.seed)
  fit_lib.fit_chains(run, fit_lib.Training(
      what='VQA', identity_fields=None,
      chain_stage=lambda chain, stream: (
          _train_stage(chain, directory, vocab, stream), None),
      seed_of=functools.partial(aloe_seed, vqa=vqa)))


@dataclasses.dataclass(frozen=True)
class Aloe:
  """A trained Aloe of a run.

  Attributes:
    module: Aloe (`tasks.vqa.build_aloe`).
    params: its newest parameters ({'params': ...}, replicated).
    step: their step.
    vocab: the vocabulary its word and answer ids index.
    diverged_at: a seed of a several-seed run: the update in which it
      diverged (its parameters are then its last finite ones), 0: it did
      not.
  """

  module: Any
  params: Any
  step: int
  vocab: vqa_data.Vocabulary
  diverged_at: int = 0


def load_aloe(run: Run, inputs: str | None = None,
              seed: int | None = None) -> Aloe:
  """The Aloe trained on `inputs` with `seed` (default: the config's
  `vqa.inputs` and `vqa.seed`).

  Raises:
    MissingInputError: not trained (the message names the stage).
  """
  vqa = run.config.vqa
  inputs = vqa.inputs if inputs is None else inputs
  seed = vqa.seed if seed is None else seed
  vocab = vqa_questions.vocabulary(run.config)
  model, init = model_and_init(vqa, vocab, run.slot_model.slot_shape)
  directory = run.paths.aloe(inputs, seed)
  if run.stacked is not None:  # a seed view: its share of the stacked Aloe
    params, step, diverged_at = inference.restore_seed(
        directory, jax.eval_shape(lambda: {'params': init(
            jax.random.key(0))}), run.mesh, run.stacked, what='Aloe',
        train_command=command(run.paths.root, 'train_vqa'),
        num_train_steps=vqa.num_train_steps)
    return Aloe(module=model, params=params, step=step, vocab=vocab,
                diverged_at=diverged_at)
  checkpointer = checkpointer_for(directory, read_only=True)
  if checkpointer.latest_step() is None:
    raise MissingInputError(f'no Aloe checkpoint under {directory}; run '
                            '--mode=train_vqa first')
  state = checkpointer.restore(abstract_train_state(
      lambda rng: {'params': init(rng)}, vqa, run.mesh))
  return Aloe(module=model, params=state.params, step=int(state.step),
              vocab=vocab)


def evaluate_vqa(run: Run) -> dict[str, Any]:
  """Metrics per question type on `vqa.eval_split` (+ the answer prior);
  on a split without answers (CLEVRER's test), the prediction file.
  Several seeds: each chain's Aloe on its own slots, then every metric's
  mean, std and per-seed values (a diverged seed named and left out)."""
  if run.seeds is None:
    return _evaluate(run, load_aloe(run))
  vqa = run.config.vqa
  per_seed, excluded = {}, {}
  for view in run.seed_views():
    aloe = load_aloe(view)
    if aloe.diverged_at:
      excluded[view.seed] = f'Aloe diverged in update {aloe.diverged_at}'
      logger.warning('VQA: seed %d not evaluated (%s)', view.seed,
                     excluded[view.seed])
      continue
    per_seed[view.seed] = _evaluate(view, aloe)
  summary = {'seeds': list(run.seeds), 'excluded': {
      str(seed): reason for seed, reason in excluded.items()},
             'std': seeds_lib.STD,
             'metrics': seeds_lib.fold(per_seed)}
  if jax.process_index() == 0:
    write_json_atomic(os.path.join(
        run.paths.aloe_results(vqa.inputs, vqa.seed),
        f'metrics_{vqa.eval_split}.json'), summary, sort_keys=False)
  logger.info('VQA %s on %s, %d seeds: %s', vqa.inputs, vqa.eval_split,
              len(per_seed), json.dumps(summary['metrics']))
  return summary


def _evaluate(run: Run, aloe: Aloe) -> dict[str, Any]:
  """`evaluate_vqa` of one chain with its `aloe`."""
  config, mesh = run.config, run.mesh
  vqa = config.vqa
  split = vqa.eval_split
  vocab = aloe.vocab
  joined = questions_with_videos(run, split, vocab, scoring=True)
  questions = joined.questions
  batches = question_batches(run, split, joined)
  model, params = aloe.module, aloe.params
  replicated = sharding.replicated_sharding(mesh)
  predict = jax.jit(functools.partial(task.predict, model=model),
                    in_shardings=(replicated, sharding.batch_sharding(mesh)))
  size = sharding.per_host_batch_size(vqa.eval_batch_size, mesh)
  metrics = task.VqaMetrics()
  open_answers, choice_correct = {}, {}
  open_index = [k for k, q in enumerate(questions) if q.is_descriptive]
  choice_index = [k for k, q in enumerate(questions) if not q.is_descriptive]
  for batch, open_ids, choice_ids in batches.eval_batches(size, size):
    answers, logits = sharding.gather_to_host(
        predict(params, sharding.to_global_batch(batch, mesh)))
    n_open, n_choice = len(open_ids), len(choice_ids)
    valid = batch['choice_valid'][:n_choice]
    metrics.add_open(answers[:n_open], batch['open_label'][:n_open])
    metrics.add_choices(logits[:n_choice] > 0, batch['choice_label'][:n_choice],
                        valid, batch['choice_type'][:n_choice])
    for k, i in enumerate(open_ids):
      open_answers[open_index[i]] = int(answers[k])
    for k, i in enumerate(choice_ids):
      n = int(valid[k].sum())
      choice_correct[choice_index[i]] = (logits[k, :n] > 0).tolist()
  directory = run.paths.aloe_results(vqa.inputs, vqa.seed)
  has_answers = all(q.answer >= 0 for q in questions if q.is_descriptive)
  results = metrics.results() if has_answers else {}
  if has_answers:
    results['descriptive_per_template'] = task.open_accuracy_per_template(
        questions, open_answers)
  if joined.num_missing:  # scored without them (within the threshold)
    results['left_out'] = {'questions': joined.num_missing,
                           'of': joined.total,
                           'videos_not_converted': list(joined.missing_videos)}
  if jax.process_index() == 0:
    write_json_atomic(os.path.join(directory, f'metrics_{split}.json'),
                      results, sort_keys=False)
    if not has_answers:
      write_json_atomic(
          os.path.join(directory, f'predictions_{split}.json'),
          task.prediction_file(questions, open_answers, choice_correct,
                               vocab.answer_names), indent=None,
          sort_keys=False)
    if has_answers:
      prior = task.evaluate_answer_prior(task.fit_answer_prior(
          vqa_questions.encoded_questions(config, 'train', vocab)),
          questions)
      write_json_atomic(
          os.path.join(run.paths.vqa, f'answer_prior_{split}.json'),
          prior, sort_keys=False)
  logger.info('VQA %s on %s: %s', vqa.inputs, split, json.dumps(results))
  return results


TASK = register(Task(
    name='vqa', config='configs/synthetic_vqa.py',
    stages={'vqa_slots': vqa_slots, 'train_vqa': train_vqa,
            'evaluate_vqa': evaluate_vqa},
    seeded=('vqa_slots', 'train_vqa', 'evaluate_vqa'),
    section='vqa', defaults=defaults.vqa_config,
    reads=lambda config: (('vqa.eval_split', config.vqa.eval_split),),
    input_problems=missing_video_problems))
