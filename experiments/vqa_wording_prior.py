r"""What the wording alone tells about multiple-choice labels, per question type.
Answered (numbers, commands, machine) in docs/experiments/vqa.md.

  python experiments/vqa_wording_prior.py --root=<dataset folder with questions/>

A question-only baseline that needs no training: every choice gets a key
from its text only, (template, choice kind, whether the choice names an
object that the question names); the label of a test choice is the more
frequent training label of its key. If choice labels are balanced per kind
and template, this stays near 50% per option; the v1 generator's
explanatory choices gave it away ("the collision between ..." mostly
correct). Also prints questions per video per type and the label balance
per (template, kind).
"""

from __future__ import annotations

import argparse
import collections
import re

from slotformer_jax.data import vqa

_NAME = re.compile(r'the (\w+ (?:cube|sphere|cylinder))')


def _kind(choice: str) -> str:
  if choice.startswith('the presence of'):
    return 'presence'
  if choice.startswith('the collision between'):
    return 'collision_event'
  return 'collides'


def _keys(scenes):
  """(question type, key, label) of every choice."""
  for scene in scenes:
    for q in scene['questions']:
      if 'choices' not in q:
        continue
      named = set(_NAME.findall(q['question']))
      for c in q['choices']:
        shares = bool(named & set(_NAME.findall(c['choice'])))
        key = (q.get('template', q['question_type']), _kind(c['choice']),
               shares)
        yield q['question_type'], key, c['answer'] == 'correct'


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument('--root', required=True)
  args = parser.parse_args()
  train = vqa.read_clevrer_questions(args.root, 'train')
  test = vqa.read_clevrer_questions(args.root, 'test')
  for split, scenes in (('train', train), ('test', test)):
    per_type = collections.Counter(q['question_type'] for s in scenes
                                   for q in s['questions'])
    print(f'{split}: {len(scenes)} videos; questions per video: ' + ', '.join(
        f'{t} {n / len(scenes):.2f} ({n})' for t, n in sorted(
            per_type.items())))
  counts = collections.defaultdict(collections.Counter)
  for _, key, label in _keys(train):
    counts[key][label] += 1
  print('train labels per (template, kind, names a question object): '
        'correct / wrong')
  for key, c in sorted(counts.items()):
    print(f'  {key}: {c[True]} / {c[False]}')
  right, total = collections.Counter(), collections.Counter()
  for q_type, key, label in _keys(test):
    guess = counts[key][True] > counts[key][False]
    right[q_type] += guess == label
    total[q_type] += 1
  print('test per-option accuracy of the wording rule: ' + ', '.join(
      f'{t} {100 * right[t] / total[t]:.1f}% ({total[t]} options)'
      for t in sorted(total)))


if __name__ == '__main__':
  main()
