"""VQA stages: slots (+ SlotFormer rollout) per video -> train Aloe -> evaluate.

Run after the video pipeline (SAVi, extraction, SlotFormer):

  python -m slotformer_jax.main --config=configs/synthetic_vqa.py \
      --workdir=runs/vqa --mode=all     # everything, VQA included
  ... --mode=train_vqa --config.vqa.inputs=observed --config.vqa.seed=1

Workdir layout (next to the video pipeline's)::

    vqa/slots/<split>.npy         float32 [V, video_length + rollout, N, D]
    vqa/slots/meta.json           SAVi / SlotFormer steps they came from
    vqa/<inputs>_s<seed>/         checkpoints/, train_log.jsonl,
                                  metrics_<split>.json, predictions_test.json
    vqa/answer_prior_<split>.json

Questions and vocabulary: the embedded family ('clevrer_like') keeps them in
its dataset folder; for CLEVRER set `vqa.questions_root` (the folder with
questions/) and optionally `vqa.vocab_file` (default: built from the
training questions and CLEVRER's answers).
"""

from __future__ import annotations

import functools
import json
import logging
import os
from typing import Any

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import tqdm

from slotformer_jax import inference
from slotformer_jax import models
from slotformer_jax import slot_models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.data import vqa_questions
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.files import read_json
from slotformer_jax.files import write_json_atomic
from slotformer_jax.tasks import vqa as task
from slotformer_jax.runtime import sharding
from slotformer_jax.train import steps
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import abstract_train_state
from slotformer_jax.train.trainer import checkpointer_for
from slotformer_jax.train.trainer import fit

logger = logging.getLogger(__name__)

# 'future': the ground-truth future, i.e. SAVi's slots of the real frames
# after the video (the extraction must cover them): the ceiling of what any
# rollout can give predictive questions (embedded data only).
INPUTS = ('observed', 'rollout', 'blind', 'future')


def vqa_dir(workdir: str) -> str:
  return os.path.join(workdir, 'vqa')


def variant_dir(config: ml_collections.ConfigDict, workdir: str) -> str:
  return os.path.join(vqa_dir(workdir),
                      f'{config.vqa.inputs}_s{config.vqa.seed}')


def _check_inputs(config: ml_collections.ConfigDict) -> None:
  if config.vqa.inputs not in INPUTS:
    raise ConfigError(f'vqa.inputs must be one of {INPUTS}, got '
                     f'{config.vqa.inputs!r}')


# ----------------------------------------------------------------------------
# Slots per video: observed, then SlotFormer's rollout
# ----------------------------------------------------------------------------


def _slots_path(workdir: str, split: str) -> str:
  return os.path.join(vqa_dir(workdir), 'slots', f'{split}.npy')


def vqa_slots(config: ml_collections.ConfigDict, workdir: str,
              mesh: Mesh) -> None:
  """Writes each split's observed slots followed by SlotFormer's rollout."""
  vqa = config.vqa
  dynamics = config.slotformer
  params, step = inference.load_dynamics_params(
      config, workdir, mesh, models.SLOTFORMER,
      slot_models.get(config).slot_shape)
  model = models.build_slotformer(config)
  meta_path = os.path.join(vqa_dir(workdir), 'slots', 'meta.json')
  meta = {'slotformer_step': step, 'video_length': vqa.video_length,
          'rollout_frames': vqa.rollout_frames}
  if os.path.exists(meta_path) and read_json(meta_path) == meta and all(
      os.path.exists(_slots_path(workdir, s))
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
    source = SlotSource(workdir_lib.slots_dir(
        workdir_lib.stage1_workdir(config, workdir), split))
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
            _slots_path(workdir, split) + '.tmp.npy', mode='w+',
            dtype=np.float32, shape=(len(source),) + both.shape[1:])
      out[first:first + len(both)] = both
    out.flush()
    del out
    os.replace(_slots_path(workdir, split) + '.tmp.npy',
               _slots_path(workdir, split))
  write_json_atomic(meta_path, meta)


def _true_future_slots(config: ml_collections.ConfigDict, workdir: str,
                       split: str, length: int) -> np.ndarray:
  """SAVi's slots of the video and of the real frames after it, float32
  [V, length, N, D] (length = video_length + rollout_frames): the input of
  the ground-truth-future ceiling (`vqa.inputs='future'`)."""
  source = SlotSource(workdir_lib.slots_dir(
      workdir_lib.stage1_workdir(config, workdir), split))
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


def question_batches(config: ml_collections.ConfigDict, workdir: str,
                     split: str, questions: list[vqa_data.EncodedQuestion]
                     ) -> task.QuestionBatches:
  _check_inputs(config)
  vqa = config.vqa
  path = _slots_path(workdir, split)
  if not os.path.exists(path):
    raise MissingInputError(f'{path} is missing: run --mode=vqa_slots first')
  slots = np.load(path, mmap_mode='r')
  if vqa.inputs == 'future':
    slots = _true_future_slots(config, workdir, split, slots.shape[1])
  elif vqa.inputs != 'rollout':
    slots = slots[:, :vqa.video_length]  # no rollout: predictive questions
    # read the end of the video like the others
  index = vqa_questions.filename_to_index(config, split)
  return task.QuestionBatches(
      questions, lambda name: slots[index[name]],
      video_length=vqa.video_length, num_frames=vqa.num_frames,
      stride=vqa.frame_stride, max_choices=vqa.max_choices,
      blind=vqa.inputs == 'blind',
      choice_weights=(dict(vqa.choice_type_weights)
                      if vqa.get('choice_type_weights') else None))


# ----------------------------------------------------------------------------
# Training and evaluation
# ----------------------------------------------------------------------------


def _model_and_init(config: ml_collections.ConfigDict,
                    vocab: vqa_data.Vocabulary):
  vqa = config.vqa
  slot_shape = slot_models.get(config).slot_shape
  model = models.build_aloe(config, len(vocab.questions), len(vocab.answers),
                            num_slots=slot_shape[0])
  length = vqa.max_question_len + vqa.max_choice_len
  slots = jnp.zeros((1, vqa.num_frames, *slot_shape))

  def init(rng: jax.Array) -> Any:
    return steps.init_params(
        model, rng, slots, jnp.zeros((1, length), jnp.int32),
        jnp.zeros((1, length), bool), slots,
        jnp.zeros((1, 1, length), jnp.int32), jnp.zeros((1, 1, length), bool))
  return model, init


def aloe_stage(config: ml_collections.ConfigDict, workdir: str,
               vocab: vqa_data.Vocabulary, batches) -> Stage:
  """Aloe's training stage for `vocab`; `batches` (start step -> this
  host's question batches, `task.QuestionBatches.train_batches`) is only
  read by `fit`."""
  vqa = config.vqa
  model, init = _model_and_init(config, vocab)
  return Stage(
      name=f'vqa_{vqa.inputs}', directory=variant_dir(config, workdir),
      config=vqa, loss_fn=functools.partial(task.vqa_loss, model=model),
      init_params=lambda rng: {'params': init(rng)}, batches=batches,
      logging=config.get('logging'))


def train_vqa(config: ml_collections.ConfigDict, workdir: str,
              mesh: Mesh) -> None:
  """Trains Aloe on the training questions (resumable)."""
  vqa = config.vqa
  vocab = vqa_questions.vocabulary(config)
  batches = question_batches(config, workdir, 'train',
                             vqa_questions.encoded_questions(config, 'train',
                                                             vocab))
  open_size = sharding.per_host_batch_size(vqa.open_batch_size, mesh)
  choice_size = sharding.per_host_batch_size(vqa.choice_batch_size, mesh)
  seed = config.seed * 1000 + vqa.seed
  stage = aloe_stage(
      config, workdir, vocab,
      lambda start_step: batches.train_batches(
          open_size, choice_size, seed=seed, start_step=start_step,
          process_index=jax.process_index(),
          process_count=jax.process_count()))
  fit(stage, mesh=mesh, seed=seed)


def _load_aloe(config: ml_collections.ConfigDict, workdir: str, mesh: Mesh,
               vocab: vqa_data.Vocabulary):
  model, init = _model_and_init(config, vocab)
  directory = variant_dir(config, workdir)
  checkpointer = checkpointer_for(directory, read_only=True)
  if checkpointer.latest_step() is None:
    raise MissingInputError(f'no Aloe checkpoint under {directory}; run '
                            '--mode=train_vqa first')
  state = checkpointer.restore(abstract_train_state(
      lambda rng: {'params': init(rng)}, config.vqa, mesh))
  return model, state.params


def evaluate_vqa(config: ml_collections.ConfigDict, workdir: str,
                 mesh: Mesh) -> dict[str, Any]:
  """Metrics per question type on `vqa.eval_split` (+ the answer prior);
  on a split without answers (CLEVRER's test), the prediction file."""
  vqa = config.vqa
  split = vqa.eval_split
  vocab = vqa_questions.vocabulary(config)
  questions = vqa_questions.encoded_questions(config, split, vocab)
  batches = question_batches(config, workdir, split, questions)
  model, params = _load_aloe(config, workdir, mesh, vocab)
  replicated = sharding.replicated_sharding(mesh)
  run = jax.jit(functools.partial(task.predict, model=model),
                in_shardings=(replicated, sharding.batch_sharding(mesh)))
  size = sharding.per_host_batch_size(vqa.eval_batch_size, mesh)
  metrics = task.VqaMetrics()
  open_answers, choice_correct = {}, {}
  open_index = [k for k, q in enumerate(questions) if q.is_descriptive]
  choice_index = [k for k, q in enumerate(questions) if not q.is_descriptive]
  for batch, open_ids, choice_ids in batches.eval_batches(size, size):
    answers, logits = sharding.gather_to_host(
        run(params, sharding.to_global_batch(batch, mesh)))
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
  directory = variant_dir(config, workdir)
  has_answers = all(q.answer >= 0 for q in questions if q.is_descriptive)
  results = metrics.results() if has_answers else {}
  if has_answers:
    results['descriptive_per_template'] = task.open_accuracy_per_template(
        questions, open_answers)
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
          os.path.join(vqa_dir(workdir), f'answer_prior_{split}.json'),
          prior, sort_keys=False)
  logger.info('VQA %s on %s: %s', vqa.inputs, split, json.dumps(results))
  return results
