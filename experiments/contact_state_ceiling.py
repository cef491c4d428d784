"""How much does the future tell, in simulator states? (issue 11, step 1)
Answered (numbers, commands, machine) in docs/experiments/contact.md.

Before blaming SAVi or SlotFormer for a rollout that does not help contact
prediction, check the task itself: train the contact readout on SIMULATOR
STATES instead of slots, once on the observed frames only and once on the
whole video. If the whole video is not far above the observed frames, no
dynamics model can help, whatever its quality.

Per object and frame the "slot" is [x, y, vx, vy, radius] of the agent and
the patient (the readout's pair embedding then sees their relation); the
head is the task's own readout (modules/readouts.PhysionReadout,
'both_orders') and, as a second opinion, a small MLP on the flattened
states. Epoch and threshold are chosen on readout_val, accuracy is reported
on readout_test (mean +- std over seeds). No rendering: every video is the
accepted physics-only pass of datasets/synthetic_contact.generate_states.

  nice -n 19 python experiments/contact_state_ceiling.py \
      --config=configs/synthetic_contact.py:side
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import tempfile
import time

import flax.linen as nn
import numpy as np

from slotformer_jax.datasets import synthetic_contact as contact
from slotformer_jax.datasets import synthetic
from slotformer_jax.modules import readouts
from slotformer_jax.stages import readout_fit
from slotformer_jax.tasks import readout as readout_lib


class StateMLP(nn.Module):
  """states [B, T, N, D] -> logits [B]: flattened, 2 hidden layers."""

  width: int = 64

  @nn.compact
  def __call__(self, states):
    x = states.reshape(states.shape[0], -1)
    x = nn.relu(nn.Dense(self.width)(x))
    x = nn.relu(nn.Dense(self.width)(x))
    return nn.Dense(1)(x)[..., 0]


def fit_head(model, train, select, fit_config, seed):
  """(params, log) of a head fitted as the pipeline fits its readouts
  (`readout_fit.fit_readout`), in a folder thrown away after."""
  with tempfile.TemporaryDirectory() as directory:
    return readout_fit.fit_readout(directory, 'head', model, train, select,
                                   fit_config, seed)


def state_features(example: dict[str, np.ndarray], scale: float,
                   all_objects: bool) -> np.ndarray:
  """float32 [T, K, 5]: [x, y, vx, vy, radius] of agent and patient (K = 2)
  or of every object row (K = O: agent, patient, the others in row order;
  padding rows are zero)."""
  agent, patient = int(example['agent_index']), int(example['patient_index'])
  rows = [agent, patient]
  if all_objects:
    rows += [r for r in range(len(example['sizes']))
             if r not in rows]
  pos = example['positions'][:, rows, :2]
  vel = example['velocities'][:, rows, :2]
  radius = np.array([synthetic.SIZE_RADII[example['sizes'][r]] * scale
                     if example['sizes'][r] >= 0 else 0.0 for r in rows],
                    np.float32)
  radius = np.broadcast_to(radius[None, :, None], pos.shape[:2] + (1,))
  return np.concatenate([pos, vel, radius], -1).astype(np.float32)


def load(config: contact.ContactConfig, split: str, limit: int,
         all_objects: bool):
  n = min(config.num_videos(split), limit)
  feats, labels, onsets = [], [], []
  for i in range(n):
    ex = contact.generate_states(config, split, i)
    feats.append(state_features(ex, config.object_scale, all_objects))
    labels.append(float(ex['contact']))
    onsets.append(int(ex['contact_frame']))
  return np.stack(feats), np.array(labels, np.float32), np.array(onsets)


def evaluate(model, train, val, test, seeds, epochs):
  """(test mean, test std, per-seed test, per-seed val) accuracies [%]."""
  accs, val_accs = [], []
  for seed in seeds:
    def select(params):
      p = readout_lib.predict(model, params, val[0])
      return readout_lib.best_threshold(p, val[1])[1]
    params, _ = fit_head(
        model, train, select,
        readout_lib.FitConfig(epochs=epochs, batch_size=64,
                              learning_rate=1e-3), seed)
    threshold, val_acc = readout_lib.best_threshold(
        readout_lib.predict(model, params, val[0]), val[1])
    val_accs.append(100 * val_acc)
    accs.append(readout_lib.accuracy_at(
        readout_lib.predict(model, params, test[0]), test[1], threshold))
  return (100 * np.mean(accs), 100 * np.std(accs), [100 * a for a in accs],
          val_accs)


def main():
  parser = argparse.ArgumentParser()
  parser.add_argument('--config', default='configs/synthetic_contact.py:side')
  parser.add_argument('--limit', type=int, default=10**9,
                      help='at most this many videos per readout split')
  parser.add_argument('--train_limit', type=int, default=10**9,
                      help='at most this many readout_train videos (labels)')
  parser.add_argument('--epochs', type=int, default=100)
  parser.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
  parser.add_argument('--all_objects', action='store_true',
                      help='every object row, not only agent and patient')
  parser.add_argument('--override', nargs='*', default=[],
                      help='data.<field>=<python literal> overrides')
  args = parser.parse_args()
  path, _, variant = args.config.partition(':')
  spec = importlib.util.spec_from_file_location('cfg', path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  run_config = module.get_config(variant)
  for item in args.override:
    key, value = item.split('=', 1)
    run_config.data[key.removeprefix('data.')] = eval(value)  # pylint: disable=eval-used
  config = contact.config_from_data_config(run_config.data)
  start = time.time()
  limits = {'readout_train': min(args.limit, args.train_limit),
            'readout_val': args.limit, 'readout_test': args.limit}
  splits = {s: load(config, s, n, args.all_objects)
            for s, n in limits.items()}
  sim_s = time.time() - start
  observed = config.observed_frames
  onsets = splits['readout_test'][2]
  results = {'config': args.config, 'overrides': args.override,
             'all_objects': args.all_objects,
             'simulation_s': round(sim_s, 1),
             'test_onsets': np.bincount(onsets[onsets >= 0]).tolist()}
  for window, t in (('observed', observed), ('full', config.num_frames)):
    data = {s: (v[0][:, :t], v[1]) for s, v in splits.items()}
    for name, model in (('readout', readouts.PhysionReadout(
        features=64, pairs='both_orders')), ('mlp', StateMLP())):
      mean, std, per, val = evaluate(model, data['readout_train'],
                                data['readout_val'], data['readout_test'],
                                args.seeds, args.epochs)
      results[f'{window}/{name}'] = f'{mean:.1f} +- {std:.1f}'
      results[f'{window}/{name}/val'] = f'{np.mean(val):.1f}'
      print(f'{window:9s} {name:8s} test {mean:5.1f} +- {std:4.1f} {per}  '
            f'val {np.mean(val):.1f}', flush=True)
  results['total_s'] = round(time.time() - start, 1)
  print(json.dumps(results))


if __name__ == '__main__':
  main()
