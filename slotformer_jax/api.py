"""A trained world model as one Python object: frames in, slots, rollouts
and frames out, as the pipeline's stages compute them::

    from slotformer_jax.api import WorldModel
    model = WorldModel.load('runs/mine')          # any trained workdir
    frames = model.read_video('clip.mp4')         # uint8 [T, H, W, 3]
    slots = model.encode(frames[:6])              # [6, N, D]
    future = model.rollout(slots, 10)             # [10, N, D]
    out = model.decode(future)                    # .frames [10, H, W, 3] uint8,
                                                  # .masks [10, N, H, W]

What the model expects (``WorldModel.expected``) is read from the workdir's
``config.json``: RGB uint8 frames of ``data.resolution``, a file resampled
to ``data.fps`` and then every ``data.frame_stride``-th frame kept (a
folder-of-videos run), and SlotFormer's burn-in and stride. ``read_video``
reads a file that way; frames given to ``encode`` are taken as they are.
Frames of another size are resized the way the folder dataset stores them
(``data.fit``: crop or pad), with one logged notice, or refused in one line
(``on_mismatch='refuse'``).

Each function is jitted once per input shape, on one device of any backend.
Nothing here imports training code (tests/test_layout.py).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import jax
import jax.numpy as jnp
from jax.sharding import Mesh
import numpy as np

from slotformer_jax import inference
from slotformer_jax.data import media
from slotformer_jax.datasets import videos as video_files
from slotformer_jax.errors import UserError
from slotformer_jax.errors import shown
from slotformer_jax.frames import to_uint8
from slotformer_jax.run import Run
from slotformer_jax.runtime import sharding

logger = logging.getLogger(__name__)

ON_MISMATCH = ('resize', 'refuse')


@dataclasses.dataclass(frozen=True)
class Expected:
  """What a trained model reads (from its workdir's config.json).

  Attributes:
    resolution: (H, W) of its frames.
    channel_order: 'rgb' (or 'bgr': an official CLEVRER model).
    fps: video files were resampled to this rate first (0: their own).
    frame_stride: then every n-th frame was kept (1: all).
    fit: how frames of another aspect ratio are resized ('crop', 'pad').
    burn_in: slots SlotFormer reads before it predicts.
    rollout_stride: frames between two slots SlotFormer reads or predicts.
    value_range: the frames' dtype and range.
  """

  resolution: tuple[int, int]
  channel_order: str
  fps: float
  frame_stride: int
  fit: str
  burn_in: int
  rollout_stride: int
  value_range: str = 'uint8 0..255'


@dataclasses.dataclass(frozen=True)
class Decoded:
  """Frames decoded from slots.

  Attributes:
    frames: uint8 [T, H, W, 3] (None: a model that decodes no pixels).
    masks: float32 [T, N, H, W], each pixel's weights over the N slots.
  """

  frames: np.ndarray | None
  masks: np.ndarray


class WorldModel:
  """A trained slot model and dynamics model of a workdir (see the module
  docstring). ``dynamics``: 'slotformer' or 'slot_lstm'."""

  def __init__(self, run: Run, dynamics: str = 'slotformer', *,
               on_mismatch: str = 'resize'):
    if on_mismatch not in ON_MISMATCH:
      raise ValueError(f'on_mismatch must be one of {ON_MISMATCH}, got '
                       f'{on_mismatch!r}')
    self.run = run
    self.on_mismatch = on_mismatch
    config = run.config
    section = run.dynamics_section(dynamics)
    self.expected = Expected(
        resolution=tuple(config.data.resolution),
        channel_order=config.data.channel_order,
        fps=float(config.data.get('fps') or 0),
        frame_stride=int(config.data.get('frame_stride', 1)),
        fit=config.data.get('fit', 'crop'), burn_in=int(section.burn_in),
        rollout_stride=int(section.frame_stride))
    self._stage1 = run.stage1
    self._dynamics = run.dynamics(dynamics)
    self._chunk_length = int(config.extraction.chunk_length)
    self._seed = jax.random.key(run.seed)
    self._encode = jax.jit(run.slot_model.encode)
    self._decode = jax.jit(run.slot_model.decode)
    module = self._dynamics.module
    self._rollout = jax.jit(
        lambda params, slots, steps: inference.rollout_slots(
            params, slots, model=module, num_steps=steps),
        static_argnums=2)

  @classmethod
  def load(cls, workdir: str | os.PathLike[str], dynamics: str = 'slotformer',
           *, on_mismatch: str = 'resize') -> WorldModel:
    """The trained models of ``workdir`` (a run of the pipeline, or one
    made by ``official.convert``), on the first device.

    Raises:
      UserError: not a trained run (one line naming what is missing).
    """
    mesh = Mesh(np.asarray(jax.devices()[:1]), (sharding.DATA_AXIS,))
    return cls(Run.open(os.fspath(workdir), mesh), dynamics,
               on_mismatch=on_mismatch)

  # ---- input ---------------------------------------------------------------

  def read_video(self, path: str | os.PathLike[str],
                 max_frames: int | None = None) -> np.ndarray:
    """uint8 [T, H, W, 3]: a video file, GIF or folder of frames as the
    model expects it (its resolution, fit, frame rate and frame stride; at
    most ``max_frames``, default 1000).

    Raises:
      UserError: it cannot be decoded, or a folder of frames (no frame
        rate) for a model trained at a set ``fps`` (one line naming it).
    """
    expected = self.expected
    options = video_files.Options(
        resolution=expected.resolution, num_frames=max_frames or 1000,
        fps=expected.fps, frame_stride=expected.frame_stride,
        fit=expected.fit)
    try:
      frames = video_files.read_video(Path(path), options)
    except media.SkipVideo as error:
      raise UserError(error.message) from None
    return frames[..., ::-1] if expected.channel_order == 'bgr' else frames

  def frames_as_expected(self, frames: np.ndarray) -> np.ndarray:
    """uint8 [T, H, W, 3] at the model's resolution: resized (one notice)
    or refused (``on_mismatch``).

    Raises:
      UserError: not uint8 [T, h, w, 3], or another size when refusing.
    """
    frames = np.asarray(frames)
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
      raise UserError(f'frames must be uint8 [T, H, W, 3] (RGB 0..255), got '
                      f'{frames.dtype} {list(frames.shape)}')
    height, width = self.expected.resolution
    if frames.shape[1:3] == (height, width):
      return frames
    size = f'{frames.shape[2]}x{frames.shape[1]}'
    if self.on_mismatch == 'refuse':
      raise UserError(f'frames are {size}, the model reads {width}x{height}: '
                      f'resize them (or load with on_mismatch="resize")')
    logger.warning('frames are %s, the model reads %dx%d: resized (%s)',
                   size, width, height, self.expected.fit)
    return np.stack([video_files.fit_frame(frame, (height, width),
                                           self.expected.fit)
                     for frame in frames])

  # ---- the model -------------------------------------------------------------

  def encode(self, frames: np.ndarray) -> np.ndarray:
    """uint8 [T, H, W, 3] (channels in ``expected.channel_order``, as
    ``read_video`` gives them) -> slots float32 [T, N, D]: the slot model
    over the frames in chunks of ``extraction.chunk_length`` carrying its
    state, as slot extraction does (a stochastic SAVi draws with the keys
    of the extraction's first batch)."""
    frames = self.frames_as_expected(frames)
    length, chunk = len(frames), self._chunk_length
    num_chunks = -(-length // chunk)
    padded = np.concatenate([frames, np.repeat(
        frames[-1:], num_chunks * chunk - length, axis=0)])[None]
    carry, out = None, []
    for index in range(num_chunks):
      rng = jax.random.fold_in(self._seed, index)
      slots, carry = self._encode(
          self._stage1.params, jnp.asarray(padded[:, index * chunk:
                                                  (index + 1) * chunk]),
          rng, carry)
      out.append(np.asarray(slots[0]))
    return np.concatenate(out)[:length]

  def rollout(self, slots: np.ndarray, steps: int) -> np.ndarray:
    """slots [T, N, D] -> the next ``steps`` slots [steps, N, D], from the
    last ``burn_in`` slots at the model's stride.

    Raises:
      UserError: fewer slots than the burn-in needs.
    """
    burn_in, stride = self.expected.burn_in, self.expected.rollout_stride
    needed = (burn_in - 1) * stride + 1
    if len(slots) < needed:
      raise UserError(f'rollout needs {needed} slots (burn-in {burn_in}, '
                      f'stride {stride}), got {len(slots)}')
    history = np.asarray(slots)[len(slots) - needed::stride]
    return np.asarray(self._rollout(self._dynamics.params,
                                    jnp.asarray(history)[None], int(steps))[0])

  def decode(self, slots: np.ndarray) -> Decoded:
    """slots [T, N, D] -> frames and masks (``Decoded``)."""
    out = self._decode(self._stage1.params, jnp.asarray(slots))
    return Decoded(
        frames=None if out.recon is None else to_uint8(out.recon),
        masks=np.asarray(out.alpha_masks[..., 0]))

  def __repr__(self) -> str:
    return (f'WorldModel({shown(self.run.paths.root)}, {self.expected})')
