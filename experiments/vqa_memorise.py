r"""Can Aloe memorise a fixed batch of multiple-choice questions?
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_memorise.py --workdir=runs/vqa [--inputs=future]
      [--question_type=predictive] [--num_questions=32] [--steps=400]

A wiring check for the multiple-choice path (tokens, question/choice flags,
per-choice [CLS] head, loss): trains the workdir's Aloe config from scratch,
with Adam, on ONE fixed batch of the first `num_questions` training
questions of a type (window start 0, the slots `--inputs` selects) and prints
the choice loss and per-option accuracy on that batch every 50 steps. If
the loss cannot fall well below ln 2 = 0.693 here, the model cannot fit
choices at all; if it can, a failure on held-out questions is one of
learning a rule from the data, not of the plumbing. Needs the workdir's
`vqa_slots` stage (and the real-future slots for `--inputs=future`).
"""

from __future__ import annotations

import argparse
import time

from slotformer_jax.runtime import xla_flags

xla_flags.apply_fast_cpu_flags()

# pylint: disable=g-import-not-at-top,wrong-import-position
import jax
import jax.numpy as jnp
import numpy as np
import optax

from slotformer_jax.data import vqa_questions
from slotformer_jax.run import Run
from slotformer_jax.stages import vqa as vqa_stages
from slotformer_jax.data.vqa import QUESTION_TYPES
from slotformer_jax.tasks import vqa as task


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--workdir', required=True)
  parser.add_argument('--inputs', default='future',
                      choices=('rollout', 'observed', 'blind', 'future'))
  parser.add_argument('--question_type', default='predictive',
                      choices=QUESTION_TYPES[1:])
  parser.add_argument('--num_questions', type=int, default=32)
  parser.add_argument('--steps', type=int, default=400)
  parser.add_argument('--learning_rate', type=float, default=1e-3)
  args = parser.parse_args()

  run = Run.open(args.workdir)
  config = run.config
  config.vqa.inputs = args.inputs
  vocab = vqa_questions.vocabulary(config)
  batches = vqa_stages.question_batches(
      run, 'train', vqa_stages.questions_with_videos(run, 'train', vocab))
  chosen = [i for i, q in enumerate(batches.choice)
            if QUESTION_TYPES[q.question_type] == args.question_type
            ][:args.num_questions]
  if not chosen:
    raise SystemExit(f'no {args.question_type} training questions')
  batch = jax.tree.map(jnp.asarray, batches.batch(
      [], chosen, np.zeros(len(chosen), np.int64), 1, len(chosen)))
  model, init = vqa_stages.model_and_init(config.vqa, vocab,
                                          (config.savi.num_slots,
                                           config.savi.slot_size))
  params = {'params': init(jax.random.key(0))}
  optimizer = optax.adam(args.learning_rate)
  opt_state = optimizer.init(params)

  @jax.jit
  def step(params, opt_state, rng):
    grads, aux = jax.grad(task.vqa_loss, has_aux=True)(
        params, batch, None, rng, model=model)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, aux

  num_options = int(np.asarray(batch['choice_valid']).sum())
  print(f'{len(chosen)} {args.question_type} questions ({num_options} '
        f'options), inputs={args.inputs}')
  start = time.time()
  for i in range(args.steps):
    params, opt_state, aux = step(params, opt_state, jax.random.key(i))
    if i % 50 == 0 or i == args.steps - 1:
      print(f'step {i:4d}  choice loss {float(aux["choice_loss"]):.3f}  '
            f'option accuracy {float(aux["option_accuracy"]):.3f}  '
            f'({time.time() - start:.0f} s)', flush=True)


if __name__ == '__main__':
  main()
