"""A third dynamics model from this one file, without editing the package.

`PairMLP` predicts each slot of the next frame from that slot in the last
two frames (an MLP of their concatenation, added to the last one: it starts
as copy-last), autoregressively. It is registered below with its label,
colour, the fields that shape it and its section's defaults; it inherits
SlotFormer's training setup as Slot-LSTM does. Trained next to SlotFormer
through the shared trainer (checkpoints, resume, several seeds in one
program), it is rolled out and scored by `evaluate`, drawn by `render` and
shown by the explorer, as a row and a curve of its own.
"""

from __future__ import annotations

import csv
import json
import pathlib
import re

import flax.linen as nn
import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np

from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from slotformer_jax import dynamics
from slotformer_jax import stages

NAME = 'pair_mlp'
LABEL = 'Pair-MLP'


class PairMLP(nn.Module):
  """slots [B, burn_in, N, D], num_steps -> [B, num_steps, N, D]."""

  burn_in: int
  hidden: int

  @nn.compact
  def __call__(self, burn_in_slots: jax.Array, num_steps: int,
               teacher_slots: jax.Array | None = None, *,
               deterministic: bool = True) -> jax.Array:
    del deterministic  # no dropout
    hidden = nn.Dense(self.hidden, name='hidden')
    out = nn.Dense(burn_in_slots.shape[-1], kernel_init=nn.initializers.zeros,
                   name='out')
    previous, current = burn_in_slots[:, -2], burn_in_slots[:, -1]
    predicted = []
    for step in range(num_steps):
      pair = jnp.concatenate([previous, current], axis=-1)
      following = current + out(nn.relu(hidden(pair)))
      predicted.append(following)
      fed = following if teacher_slots is None else teacher_slots[:, step]
      previous, current = current, fed
    return jnp.stack(predicted, axis=1)


@dynamics.register
class PairMLPModel(dynamics.DynamicsModel):
  name = NAME
  label = LABEL
  colour = '#8c564b'
  inherits = 'slotformer'  # its batch, schedule and losses, unless set here
  shaping_fields = ('burn_in', 'hidden')

  def build(self, section: ml_collections.ConfigDict) -> nn.Module:
    return PairMLP(burn_in=section.burn_in, hidden=section.hidden)

  def defaults(self) -> ml_collections.ConfigDict:
    return ml_collections.ConfigDict({'train': True, 'hidden': 16,
                                      'num_train_steps': 3})


def pair_config(data_dir) -> ml_collections.ConfigDict:
  config = micro_config('savi', str(data_dir))
  config.slot_lstm.train = False
  config[NAME] = dynamics.get(NAME).defaults()
  return config


def _mesh(devices):
  return Mesh(np.asarray(jax.devices()[:devices]), ('data',))


def _log_steps(directory) -> list[int]:
  lines = (directory / 'train_log.jsonl').read_text().splitlines()
  return [json.loads(line)['step'] for line in lines]


def test_the_package_does_not_know_it():
  package = pathlib.Path(stages.__file__).parent.parent
  for path in package.rglob('*.py'):
    text = path.read_text()
    assert NAME not in text and LABEL not in text, path
  assert dynamics.get(NAME).label == LABEL


def test_a_dynamics_model_from_one_test_file_runs_the_pipeline(tmp_path):
  config = pair_config(tmp_path / 'data')
  workdir = tmp_path / 'run'
  mesh = _mesh(1)
  run = stages.Run.create(config, str(workdir), mesh)
  selected = stages.selected_stages(run, 'all')
  assert selected.index(f'train_{NAME}') == selected.index(
      'train_slotformer') + 1
  assert 'train_slot_lstm' not in selected  # not trained: not run
  results = run_stages(config, workdir, mesh)
  steps = _log_steps(workdir / NAME)
  assert steps[-1] == config[NAME].num_train_steps  # its own, not SlotFormer's
  assert (json.loads((workdir / NAME / 'model_config.json').read_text())
          == {'burn_in': 2, 'hidden': 16})

  # Scored next to SlotFormer: metrics.json, per_step.csv, the table.
  rollout = results['evaluate']['rollout']
  assert list(rollout)[:3] == ['slotformer', NAME, 'copy_last']
  assert set(rollout[NAME]) == set(rollout['slotformer'])
  assert all(np.isfinite(value['mean']) for value in rollout[NAME].values())
  with open(workdir / 'eval' / 'per_step.csv', newline='') as f:
    methods = {row['method'] for row in csv.DictReader(f)}
  assert {'slotformer', NAME, 'copy_last'} <= methods
  assert (results['evaluate']['checkpoints'][f'{NAME}_step']
          == config[NAME].num_train_steps)

  # Drawn by render (a row of the strips, a curve of per_step.png) ...
  drawn = results['render']
  assert any(path.endswith('per_step.png') for path in drawn)
  assert any(path.endswith('rollout_000.png') for path in drawn)
  # ... and shown by the explorer: a row, a curve, its colour.
  page = (workdir / 'explore' / 'index.html').read_text()
  data = json.loads(re.search(
      r'<script[^>]*id="explorer-data"[^>]*>(.*?)</script>', page,
      re.S).group(1))
  assert NAME in [row['key'] for row in data['videos'][0]['rows']]
  assert LABEL in next(iter(data['run_curves'].values()))
  assert data['method_colours'][LABEL] == '#8c564b'
  assert data['primary']['key'] == 'slotformer'  # the intervened model

  # Trained, it resumes as every stage: nothing is redone.
  again = run_stages(config, workdir, mesh, [f'train_{NAME}', 'evaluate'])
  assert _log_steps(workdir / NAME) == steps
  assert again['evaluate']['rollout'][NAME] == rollout[NAME]


def test_several_seeds_train_it_in_one_program(tmp_path):
  config = pair_config(tmp_path / 'data')
  config.seeds = (0, 1)
  workdir = tmp_path / 'run'
  mesh = _mesh(2)
  run_stages(config, workdir, mesh,
             ['train_savi', 'extract_slots', f'train_{NAME}'])
  # One stacked checkpoint of both seeds; each seed view loads its share.
  assert _log_steps(workdir / NAME)[-1] == config[NAME].num_train_steps
  run = stages.Run.create(config, str(workdir), mesh)
  trained = [run.for_seed(i).dynamics(NAME) for i in range(2)]
  assert [model.step for model in trained] == [3, 3]
  kernels = [np.asarray(model.params['hidden']['kernel'])
             for model in trained]
  assert not np.allclose(*kernels)  # seed s initialised with seed s + 1
