"""A third loss term of the dynamics models from this one file, without
editing the package.

`velocity_loss` compares the predicted slots' frame-to-frame change with the
extracted slots' (an MSE). Registered below, it is one function; a config
turns it on with one entry, `<section>.velocity_loss_weight`, and the
dynamics stage trains with it (logged next to L_S and L_I) without a line of
stage code. A workdir from before the term (its section has no such field)
keeps its identity when the weight is 0.
"""

from __future__ import annotations

import json
import pathlib

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from pipeline_helpers import micro_config
from pipeline_helpers import run_stages
from slotformer_jax import losses
from slotformer_jax import stages
from slotformer_jax.modules.slotformer import SlotFormer
from slotformer_jax.train import steps
from slotformer_jax.workdir import identity as identity_lib

NAME = 'velocity_loss'


@losses.register_loss(NAME, 'L_V')
def velocity_loss(rollout: losses.Rollout):
  """MSE of the predicted slots' change over one frame against the
  extracted slots' (the first predicted frame against the last observed
  one is left out: L_S covers it)."""
  change = jnp.diff(rollout.predicted, axis=1)
  target = jnp.diff(rollout.target_slots, axis=1)
  value = jnp.mean(jnp.square(change - target))
  return value, {NAME: value}


def test_the_package_does_not_know_it():
  package = pathlib.Path(stages.__file__).parent.parent
  assert not any(NAME in path.read_text() for path in package.rglob('*.py'))
  assert losses.LOSS_TERMS[NAME].fn is velocity_loss


def test_a_config_entry_turns_it_on():
  section = ml_collections.ConfigDict({'image_loss_weight': 1.0})
  assert losses.loss_weights(section) == {'slot_loss': 1.0,
                                          'image_loss': 1.0}
  section.velocity_loss_weight = 0.25
  assert losses.loss_weights(section) == {
      'slot_loss': 1.0, 'image_loss': 1.0, NAME: 0.25}


def test_the_loss_adds_it_with_its_weight():
  model = SlotFormer(burn_in=2, embed_dim=16, num_layers=1, num_heads=2,
                     mlp_size=32, dropout_rate=0.0)
  params = steps.init_params(model, jax.random.key(0),
                             jnp.zeros((1, 2, 3, 16)), 3)
  batch = {'slots': np.random.default_rng(2).normal(
      size=(2, 5, 3, 16)).astype(np.float32)}
  rng = jax.random.key(4)
  loss, metrics = losses.slotformer_loss(
      params, batch, None, rng, model=model, decoder=None, rollout=3,
      weights={'slot_loss': 1.0, NAME: 0.5}, teacher_forcing=False)
  predicted = model.apply({'params': params}, batch['slots'][:, :2], 3,
                          deterministic=False, rngs={'dropout': rng})
  target = batch['slots'][:, 2:]
  slot_loss = jnp.mean(jnp.square(predicted - target))
  change = jnp.mean(jnp.square(jnp.diff(predicted, axis=1)
                               - jnp.diff(target, axis=1)))
  assert list(metrics) == ['slot_loss', NAME]
  np.testing.assert_allclose(metrics[NAME], change, rtol=1e-6)
  np.testing.assert_allclose(loss, slot_loss + 0.5 * change, rtol=1e-6)
  # Weight 0: as if it were not registered.
  off, off_metrics = losses.slotformer_loss(
      params, batch, None, rng, model=model, decoder=None, rollout=3,
      weights={'slot_loss': 1.0, NAME: 0.0}, teacher_forcing=False)
  assert list(off_metrics) == ['slot_loss']
  np.testing.assert_array_equal(off, metrics['slot_loss'])


def test_an_older_workdir_keeps_its_identity():
  old = {'slotformer': {'burn_in': 2, 'image_loss_weight': 1.0}}
  new = {'slotformer': {**old['slotformer'], 'velocity_loss_weight': 0.0}}
  assert identity_lib.flat_differences(old, new) == []
  new['slotformer']['velocity_loss_weight'] = 0.5
  assert identity_lib.flat_differences(old, new) == [
      'slotformer.velocity_loss_weight: (absent) -> 0.5']


def test_the_dynamics_stage_trains_with_it(tmp_path):
  config = micro_config('savi', tmp_path / 'data')
  config.slot_lstm.train = False
  config.slotformer.velocity_loss_weight = 0.5
  workdir = tmp_path / 'run'
  run_stages(config, workdir, jax.sharding.Mesh(
      np.asarray(jax.devices()[:1]), ('data',)),
             ['train_savi', 'extract_slots', 'train_slotformer'])
  logged = [json.loads(line) for line in
            (workdir / 'slotformer' / 'train_log.jsonl').read_text()
            .splitlines()]
  assert all({'slot_loss', 'image_loss', NAME} <= set(entry)
             for entry in logged if 'loss' in entry)
  last = logged[-1]
  np.testing.assert_allclose(
      last['loss'], last['slot_loss'] + last['image_loss'] + 0.5 * last[NAME],
      rtol=1e-5)
