"""Long units of a progress bar say where they are (issue 61): the frames
the explorer decodes in one video, the chunks of a batch of videos being
encoded, the steps of a jitted loop; at most one line every
`progress.STEP_LINE_SECONDS`, and a 'compiling' line before the first
call of a program (the trainer's: test_reliability.py)."""

import logging

import jax
import jax.numpy as jnp
from jax.sharding import Mesh
import numpy as np

from explore_helpers import micro_explorer
from slotformer_jax import inference
from slotformer_jax.runtime import progress
from slotformer_jax.runtime import sharding


def _lines(caplog, start):
  return [r.getMessage() for r in caplog.records
          if r.getMessage().startswith(start)]


def test_sub_steps_say_nothing_before_the_line_interval(caplog,
                                                        monkeypatch):
  caplog.set_level(logging.INFO, logger=progress.__name__)
  steps = progress.Steps('unit', 3, 'chunks')
  for _ in range(3):
    steps.advance()
  assert not _lines(caplog, 'unit')  # quick work: no lines
  monkeypatch.setattr(progress, 'STEP_LINE_SECONDS', 0.0)
  steps = progress.Steps('unit', 3, 'chunks')
  steps.advance()
  steps.reached(1)  # the same step again (another device): no line
  steps.reached(3)
  lines = _lines(caplog, 'unit')
  assert len(lines) == 2, lines
  assert lines[0].startswith('unit: 1/3 chunks (')
  assert lines[1].startswith('unit: 3/3 chunks (') and '~0 s left' in lines[1]


def _ticking_loop(mesh, decode_steps):
  """A jitted lax.map whose body ticks, as a decoder of `decode_steps`
  sequential passes per frame would."""
  def body(inputs):
    index, row = inputs
    progress.tick(index, decode_steps)
    return row * 2.0
  return jax.jit(lambda x: jax.lax.map(body, (jnp.arange(x.shape[0]), x)),
                 in_shardings=sharding.batch_sharding(mesh))


def _has_host_callback(lowered) -> bool:
  return '_callback' in lowered.as_text()


def test_a_jitted_sharded_loop_ticks_each_step_once(caplog, monkeypatch):
  """`tick` in a lax.map body on 4 devices: one line per step, in order."""
  caplog.set_level(logging.INFO, logger=progress.__name__)
  monkeypatch.setattr(progress, 'STEP_LINE_SECONDS', 0.0)
  mesh = Mesh(np.asarray(jax.devices()[:4]), ('data',))
  loop = _ticking_loop(mesh, decode_steps=16)
  x = np.ones((4, 8), np.float32)
  with progress.ticking(progress.Steps('loop', 4, 'steps')):
    jax.block_until_ready(loop(x))
  lines = _lines(caplog, 'loop')
  # Step i starts once i steps are done: 1..3 (the last is the bar's).
  assert [line.split()[1] for line in lines] == ['1/4', '2/4', '3/4'], lines
  caplog.clear()
  loop(x).block_until_ready()  # outside `ticking`: nothing counted
  assert not _lines(caplog, 'loop')


def test_a_one_pass_decoder_leaves_the_program_without_callback():
  """Only a decoder of several passes per frame (STEVE) ticks: a program
  with a host callback never comes from jax's persistent compile cache, so
  SAVi's evaluation on a CPU would compile again on every rerun."""
  mesh = Mesh(np.asarray(jax.devices()[:4]), ('data',))
  x = np.ones((4, 8), np.float32)
  assert _has_host_callback(_ticking_loop(mesh, 16).lower(x))
  assert not _has_host_callback(_ticking_loop(mesh, 1).lower(x))


def test_the_explorer_says_the_frames_of_a_video(tmp_path, caplog,
                                                 monkeypatch):
  """--mode=explore sat at 'explore 0/1' for 21 minutes with STEVE: a slot
  model that decodes each frame in several passes ticks per frame (the
  micro SAVi, told it decodes so); the SAVi as it is does not."""
  caplog.set_level(logging.INFO, logger=progress.__name__)
  monkeypatch.setattr(progress, 'STEP_LINE_SECONDS', 0.0)
  config, slot_model, explorer, args = micro_explorer(tmp_path)
  assert not _has_host_callback(explorer._jitted.lower(*args))  # pylint: disable=protected-access
  monkeypatch.setattr(type(slot_model), 'decode_steps', 16)
  explorer = micro_explorer(tmp_path)[2]  # traced anew, told so
  frames = config.slotformer.burn_in + config.evaluation.rollout_steps
  with progress.ticking(progress.Steps('explore video 1/1', frames,
                                       'frames')):
    jax.device_get(explorer(*args))
  lines = _lines(caplog, 'explore video 1/1')
  assert lines and lines[-1].startswith(
      f'explore video 1/1: {frames - 1}/{frames} frames'), lines


def test_encoding_says_it_compiles_and_the_chunks_of_a_batch(caplog,
                                                             monkeypatch):
  """Extraction of one long video: its chunks are lines of their own."""
  caplog.set_level(logging.INFO, logger=progress.__name__)
  monkeypatch.setattr(progress, 'STEP_LINE_SECONDS', 0.0)
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  source = [{'video': np.zeros((10, 2, 2, 3), np.uint8)}]

  def encode_chunk(batch_index, chunk, frames, carry):
    del batch_index, chunk
    return jnp.mean(frames, axis=(2, 3, 4)), carry
  out = list(inference.encode_videos(source, encode_chunk, chunk_length=3,
                                     batch_size=1, mesh=mesh,
                                     desc='extract test'))
  assert [index for index, _ in out] == [0] and out[0][1].shape == (10,)
  messages = [r.getMessage() for r in caplog.records]
  assert messages[0] == ('extract test: compiling (the first chunk takes '
                         'longer)'), messages
  chunks = _lines(caplog, 'extract test batch 1/1')
  assert [line.split()[4] for line in chunks] == ['1/4', '2/4', '3/4'], chunks
