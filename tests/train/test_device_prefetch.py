"""Batches put on the devices ahead of their step
(`sharding.prefetch_to_device`), and the trainer fed by reader worker
processes through it: order, errors, SIGTERM and a bit-exact resume."""

from __future__ import annotations

import dataclasses
import itertools
import multiprocessing
import os
import signal

import chex
import jax
from jax.sharding import Mesh
import numpy as np
import pytest

from linear_stage import linear_stage
from slotformer_jax.data import pipeline
from slotformer_jax.runtime import checkpoint as checkpoint_lib
from slotformer_jax.runtime import sharding
from slotformer_jax.runtime.preemption import Preempted
from slotformer_jax.train import trainer


class StepSource:
  """Picklable: video i holds the frames 10 i, 10 i + 1, ... (float32)."""

  def __len__(self):
    return 6

  def __getitem__(self, index):
    return {'x': (10 * index + np.arange(8, dtype=np.float32))}


def _host_stream(count, fail_at=None, closed=None):
  try:
    for step in range(count):
      if step == fail_at:
        raise KeyError(f'bad batch {step}')
      yield {'x': np.full((4, 3), float(step), np.float32)}
  finally:
    if closed is not None:
      closed.append(True)


@pytest.mark.parametrize('size', [1, 2, 3])
def test_order_and_pairs_are_kept(size):
  mesh = sharding.make_mesh()
  got = list(sharding.prefetch_to_device(_host_stream(7), mesh, size=size))
  assert len(got) == 7
  for step, (host, device) in enumerate(got):
    np.testing.assert_array_equal(host['x'], np.full((4, 3), float(step)))
    np.testing.assert_array_equal(np.asarray(device['x']), host['x'])
    assert device['x'].sharding == sharding.batch_sharding(mesh)


def test_error_surfaces_at_its_own_step_and_closes_the_reader():
  closed = []
  feed = sharding.prefetch_to_device(
      _host_stream(9, fail_at=3, closed=closed), sharding.make_mesh(), size=2)
  assert [float(next(feed)[0]['x'][0, 0]) for _ in range(3)] == [0, 1, 2]
  with pytest.raises(KeyError, match='bad batch 3'):
    next(feed)
  assert closed
  closed.clear()
  feed = sharding.prefetch_to_device(_host_stream(9, closed=closed),
                                     sharding.make_mesh(), size=2)
  next(feed)
  feed.close()
  assert closed


def _worker_stage(directory, signal_at=None, **changes):
  stage = linear_stage(directory, **changes)

  def batches(start_step):
    stream = pipeline.train_batches(
        StepSource(), batch_size=4, clip_length=3, seed=0,
        start_step=start_step, fields=('x',), num_workers=2)
    for step, batch in zip(itertools.count(start_step), stream):
      if step == signal_at:
        # As a scheduler does: the whole group, the workers too.
        for child in multiprocessing.active_children():
          os.kill(child.pid, signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)
      yield {'x': batch['x']}
  return dataclasses.replace(stage, batches=batches)


def test_sigterm_with_reader_workers_saves_and_resumes_bit_exact(tmp_path):
  mesh = Mesh(np.asarray(jax.devices()[:2]), ('data',))
  settings = dict(num_train_steps=8, checkpoint_every=1000, log_every=1000)
  uninterrupted = trainer.fit(_worker_stage(tmp_path / 'a', **settings),
                              mesh=mesh, seed=0)
  assert not multiprocessing.active_children()
  # The batch of step k is taken while update k - DEVICE_PREFETCH + 1 runs.
  signal_at = 3 + trainer.DEVICE_PREFETCH - 1
  previous = signal.getsignal(signal.SIGTERM)
  with pytest.raises(Preempted, match='stopped by SIGTERM after '
                     'step 4;'):
    trainer.fit(_worker_stage(tmp_path / 'b', signal_at=signal_at,
                              **settings), mesh=mesh, seed=0)
  assert signal.getsignal(signal.SIGTERM) is previous
  assert not multiprocessing.active_children()  # the workers are joined
  assert checkpoint_lib.Checkpointer(
      str(tmp_path / 'b' / 'checkpoints'), read_only=True).all_steps() == [4]
  resumed = trainer.fit(_worker_stage(tmp_path / 'b', **settings), mesh=mesh,
                        seed=0)
  assert int(resumed.step) == 8
  chex.assert_trees_all_close(resumed.params, uninterrupted.params, atol=0,
                              rtol=0)
  chex.assert_trees_all_close(resumed.opt_state, uninterrupted.opt_state,
                              atol=0, rtol=0)
  assert not multiprocessing.active_children()


def test_a_reader_error_stops_training_and_the_workers(tmp_path):
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  stage = linear_stage(tmp_path / 'linear', num_train_steps=6)

  def batches(start_step):
    stream = pipeline.train_batches(
        BrokenSource(), batch_size=4, clip_length=3, seed=0,
        start_step=start_step, fields=('x',), num_workers=2)
    for batch in stream:
      yield {'x': batch['x']}
  with pytest.raises(ValueError, match=r'training reader worker \d \(pid '
                     r'\d+\), step \d: video 5 is unreadable'):
    trainer.fit(dataclasses.replace(stage, batches=batches), mesh=mesh,
                seed=0)
  assert not multiprocessing.active_children()


class BrokenSource(StepSource):

  def __getitem__(self, index):
    if index == 5:
      raise ValueError('video 5 is unreadable')
    return super().__getitem__(index)
