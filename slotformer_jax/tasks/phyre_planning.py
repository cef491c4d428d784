"""PHYRE-style planning with a task-success classifier on SlotFormer rollouts:
the pure parts (the stages are in stages/planning/embedded.py).

For a (task, action) pair of the embedded tasks (tasks/phyre_world.py) the
red ball is drawn into the first frame, SAVi encodes it and SlotFormer rolls
the slots out; the classifier (modules/readouts.PhyreReadout) sees the
first-frame slots and the rollout at ``readout.selected_steps`` ('rollout'),
or the first-frame slots alone ('first_frame', the paper's SAVi baseline).
``train_readout`` chooses the epoch by AUCCESS on dev training tasks, never
on test tasks; ``plan`` ranks every candidate of every test task (AUCCESS:
tasks/planning.py). The real PHYRE layout has no simulator:
tasks/phyre_rendered.py. Protocol and workdir files: docs/downstream.md,
"PHYRE-style planning".
"""

from __future__ import annotations

from typing import Any

import ml_collections
import numpy as np
from PIL import Image
from PIL import ImageDraw

from slotformer_jax.modules import readouts
from slotformer_jax.tasks import planning
from slotformer_jax.tasks import readout as readout_lib
from slotformer_jax.tasks import phyre_world

FIRST_FRAME, ROLLOUT = 'first_frame', 'rollout'
CONDITIONS = (FIRST_FRAME, ROLLOUT)


def build_classifier(r: ml_collections.ConfigDict, condition: str
                     ) -> readouts.PhyreReadout:
  """The success classifier of `condition` (readout section `r`)."""
  selected = (0,) if condition == FIRST_FRAME else tuple(r.selected_steps)
  return readouts.PhyreReadout(
      selected_steps=selected, embed_dim=r.embed_dim,
      num_layers=r.num_layers, num_heads=r.num_heads,
      mlp_size=r.mlp_ratio * r.embed_dim,
      dropout_rate=r.dropout_rate, layer_norm_epsilon=r.layer_norm_epsilon)


def task_splits(data: ml_collections.ConfigDict,
                readout: ml_collections.ConfigDict
                ) -> dict[str, list[phyre_world.Task]]:
  """'train', 'dev' (`readout.dev_share` of the training tasks) and 'test'
  tasks of the embedded tasks of the `data` section."""
  generation = phyre_world.config_from_data_config(data)
  splits = phyre_world.split_tasks(generation)
  rng = np.random.default_rng([generation.seed, 19, generation.fold])
  train = list(splits['train'])
  order = rng.permutation(len(train))
  num_dev = int(round(readout.dev_share * len(train)))
  return {'train': [train[i] for i in sorted(order[num_dev:])],
          'dev': [train[i] for i in sorted(order[:num_dev])],
          'test': list(splits['test'])}


def first_frames(task: phyre_world.Task, actions: np.ndarray,
                 resolution: tuple[int, int]) -> np.ndarray:
  """uint8 [A, H, W, 3]: the first frame with each action's red ball."""
  frames = []
  for action in actions:
    bodies = list(task.bodies) + [phyre_world.action_ball(action)]
    poses = [(b.position, b.angle) for b in bodies]
    frames.append(phyre_world.render_state(bodies, poses, resolution)[0])
  return np.stack(frames)


def candidate_scores(model, params, task_features, num_candidates):
  """Per task: float [num_candidates]; invalid candidates score -inf
  (they are never counted as attempts, so their rank does not matter)."""
  scores = []
  for valid, feats in task_features:
    task_scores = np.full(num_candidates, -np.inf)
    task_scores[valid] = readout_lib.predict(model, params, feats)
    scores.append(task_scores)
  return scores


def write_ranking_picture(path: str, task: phyre_world.Task,
                          scores: np.ndarray, outcomes: np.ndarray,
                          generation: phyre_world.PhyreLikeConfig,
                          top: int = 5) -> None:
  """The ``top`` best-scored valid candidates of a task, one row each: the
  simulated rollout (every other frame) with its score and outcome."""
  actions = phyre_world.candidate_actions(generation)
  order = [i for i in planning.rank_actions(scores)
           if outcomes[i] != planning.INVALID][:top]
  scale, label_h = 2, 12
  rows = []
  for rank, index in enumerate(order, start=1):
    video = phyre_world.render_video(task, actions[index], generation)['video']
    strip = np.concatenate([np.pad(
        np.repeat(np.repeat(frame, scale, 0), scale, 1),
        ((1, 1), (1, 1), (0, 0))) for frame in video[::2]], axis=1)
    canvas = Image.new('RGB', (strip.shape[1], strip.shape[0] + label_h),
                       (255, 255, 255))
    canvas.paste(Image.fromarray(strip), (0, label_h))
    outcome = 'SOLVED' if outcomes[index] == planning.SOLVED else 'not solved'
    ImageDraw.Draw(canvas).text(
        (2, 0), f'{task.template}:{task.index} rank {rank}: candidate '
        f'{index}, p(success) = {scores[index]:.2f}, {outcome}',
        fill=(0, 0, 0))
    rows.append(np.asarray(canvas))
  Image.fromarray(np.concatenate(rows, axis=0)).save(path)


_ROW_NAMES = {
    'random': 'random ranking',
    FIRST_FRAME: 'classifier on first-frame slots',
    ROLLOUT: 'classifier on first frame + SlotFormer rollout',
    'oracle': 'oracle (simulated labels)',
}


def format_table(summary: dict[str, Any], fold: int) -> str:
  lines = [f'| ranking | AUCCESS x 100 (fold {fold}) |', '|---|---|']
  for name in ('random', FIRST_FRAME, ROLLOUT, 'oracle'):
    if name in summary:
      row = summary[name]
      lines.append(f'| {_ROW_NAMES[name]} | {100 * row["mean"]:.1f} +- '
                   f'{100 * row["std"]:.1f} |')
  return '\n'.join(lines)
