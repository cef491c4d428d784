"""Host-side batching of video sources (numpy only; no jax arrays here).

A *source* is anything with ``__len__`` and ``__getitem__(i) -> dict`` of
numpy arrays whose first axis is time (e.g. a :class:`sources.VideoSource`,
or extracted slots ``{'slots': float32 [T, N, D], ...}``); 0-d entries
(per-video scalars such as ``num_objects``) are passed through unsliced.
Videos may have different lengths.

* :func:`train_batches`: random clips; step ``s``'s global batch is a pure
  function of ``(seed, s, global batch size)`` and the data (a resumed run
  sees the same batches), built in a thread or in worker processes
  (``data.reader_workers``; data/workers.py) that yield the same stream;
* :func:`eval_batches`: every video of the host's shard once, in padded
  fixed-shape batches marked by a ``mask``; :func:`host_batches`: that
  plan as indices only.

Multi-host (batch sizes are per host, ``B``; the global batch is ``P * B``):

* training: every host computes the same plan of the global batch (videos
  drawn from all videos, start frames for every row) and reads only its own
  rows ``[p * B, (p + 1) * B)``, the rows `runtime.sharding.to_global_batch`
  places on its devices (the trainer checks this). So 2 hosts x 1 device
  train on the batches of 1 host x 2 devices, and any host may read any
  video: all hosts need the whole dataset (a shared data dir, as the launch
  scripts assume).
* evaluation and extraction: host ``p`` of ``P`` owns videos
  ``p, p + P, p + 2P, ...``.

Dtypes are kept as stored (videos stay uint8); convert on device.
"""

from __future__ import annotations

import functools
import math
import queue
import threading
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from slotformer_jax.data import workers

# Seed-sequence tags that keep the random streams of a run independent.
_TAG_ORDER = 0    # which videos, per epoch
_TAG_START = 1    # which start frames, per step
_TAG_TRANSFORM = 2  # a clip's augmentation, per step and global row
_JOIN_TIMEOUT_S = 30.0


class Source(Protocol):
  """Random access to items (dicts of arrays, time first).

  A source may also read clips without the whole item (e.g. a chunked TFDS
  folder, ``data/chunked.py``): it then has ``supports_clips`` (true),
  ``time_fields`` (the fields ``clip`` cuts along time), ``num_frames(i)``
  (the item's T, without decoding it) and ``clip(i, start, length, stride,
  fields)``, which returns exactly what :func:`_slice_item` cuts from
  ``source[i]``. :func:`make_train_batch` uses them when the first requested
  field is one of ``time_fields`` (so T is the same number as with the
  whole item); other sources are read whole and sliced.
  """

  def __len__(self) -> int:
    ...

  def __getitem__(self, index: int) -> Mapping[str, Any]:
    ...


def _reads_clips(source: Source, fields: Sequence[str]) -> bool:
  """Whether make_train_batch may read ``source``'s clips directly."""
  return (bool(getattr(source, 'supports_clips', False)) and bool(fields)
          and fields[0] in tuple(getattr(source, 'time_fields', ())))


def _check_host(process_index: int, process_count: int) -> None:
  if process_count < 1 or not 0 <= process_index < process_count:
    raise ValueError(f'need 0 <= process_index < process_count, got '
                     f'{process_index} / {process_count}')


def shard_indices(num_items: int, process_index: int,
                  process_count: int) -> np.ndarray:
  """int64 [ceil((num_items - p) / P)]: the items of host ``p``: p, p+P, ...
  (evaluation and extraction; training reads rows of a global plan)."""
  _check_host(process_index, process_count)
  return np.arange(process_index, num_items, process_count, dtype=np.int64)


def _num_frames(item: Mapping[str, Any], fields: Sequence[str],
                index: int) -> int:
  """T of an item: the leading axis of its first non-scalar requested field."""
  for field in fields:
    value = _get(item, field, index)
    if np.ndim(value) > 0:
      return int(np.shape(value)[0])
  raise ValueError(f'fields {tuple(fields)} of item {index} are all scalars; '
                   'need at least one array with a time axis')


def _get(item: Mapping[str, Any], field: str, index: int) -> Any:
  try:
    return item[field]
  except KeyError:
    raise KeyError(f'item {index} has no field {field!r}; it has '
                   f'{sorted(item)}') from None


def _slice_item(item: Mapping[str, Any], fields: Sequence[str], index: int,
                start: int, length: int, stride: int
                ) -> dict[str, np.ndarray]:
  """Frames ``start, start + stride, ...`` (``length`` of them) of each field.

  Raises ValueError if a field's time axis disagrees with the first field's,
  since slicing it would silently pair frames that do not belong together.
  """
  num_frames = _num_frames(item, fields, index)
  out = {}
  for field in fields:
    value = np.asarray(_get(item, field, index))
    if value.ndim == 0:
      out[field] = value
      continue
    if value.shape[0] != num_frames:
      raise ValueError(
          f'item {index}: field {field!r} has {value.shape[0]} steps on its '
          f'first axis but {fields[0]!r} has {num_frames}; every requested '
          'non-scalar field must have time first')
    out[field] = value[start:start + (length - 1) * stride + 1:stride]
  return out


def _stack(parts: Sequence[Mapping[str, np.ndarray]], fields: Sequence[str]
           ) -> dict[str, np.ndarray]:
  return {field: np.stack([p[field] for p in parts]) for field in fields}


def _epoch_order(seed: int, epoch: int, size: int) -> np.ndarray:
  """int64 [size]: the order of all videos in ``epoch``."""
  # The 0 stands where the process index was when each host drew its own
  # batches: with it, single-process streams stay what they were.
  rng = np.random.default_rng([seed, _TAG_ORDER, 0, epoch])
  return rng.permutation(size)


def _train_plan(seed: int, step: int, global_batch_size: int,
                num_videos: int) -> tuple[np.ndarray, np.ndarray]:
  """Video indices int64 [G] and start-frame fractions float64 [G] of the
  global batch of a step (G: ``global_batch_size``); the same on every host.

  Videos are drawn without replacement within an epoch (a fresh permutation
  of all videos per epoch), so every video is seen once per epoch; position
  ``q`` of the stream lies in epoch ``q // num_videos``, which makes step
  ``s`` computable without replaying steps ``< s``.
  """
  positions = np.arange(step * global_batch_size,
                        (step + 1) * global_batch_size, dtype=np.int64)
  epochs, offsets = np.divmod(positions, num_videos)
  videos = np.empty(global_batch_size, np.int64)
  for epoch in np.unique(epochs):
    selected = epochs == epoch
    videos[selected] = _epoch_order(seed, int(epoch), num_videos)[
        offsets[selected]]
  # Fractions, not frame numbers: each video maps them to its own length.
  rng = np.random.default_rng([seed, _TAG_START, 0, step])
  return videos, rng.random(global_batch_size)


def host_rows(batch_size: int, process_index: int) -> slice:
  """Host ``p``'s rows of a global batch of per-host size ``batch_size``:
  ``[p * B, (p + 1) * B)``."""
  return slice(process_index * batch_size, (process_index + 1) * batch_size)


# A clip's augmentation: (clip, its generator) -> the clip delivered.
Transform = Callable[[dict[str, np.ndarray], np.random.Generator],
                     dict[str, np.ndarray]]


def transform_rng(seed: int, step: int, row: int) -> np.random.Generator:
  """The generator of the augmentation of row ``row`` of the global batch
  of step ``step``: the same whichever host builds the row."""
  return np.random.default_rng([seed, _TAG_TRANSFORM, 0, step, row])


def make_train_batch(source: Source, step: int, *, batch_size: int,
                     clip_length: int, seed: int,
                     fields: Sequence[str] = ('video',), frame_stride: int = 1,
                     process_index: int = 0, process_count: int = 1,
                     transform: Transform | None = None
                     ) -> dict[str, np.ndarray]:
  """This host's rows of the global batch of step ``step`` (see
  :func:`train_batches`); ``batch_size`` is per host."""
  _check_host(process_index, process_count)
  if len(source) == 0:
    raise ValueError('the source has no videos to train on')
  videos, fractions = _train_plan(seed, step, batch_size * process_count,
                                  len(source))
  rows = host_rows(batch_size, process_index)
  span = (clip_length - 1) * frame_stride + 1
  fields = tuple(fields)
  clips = _reads_clips(source, fields)
  parts = []
  for video, fraction in zip(videos[rows], fractions[rows]):
    if clips:  # T from the source's index; only the clip's frames are read
      num_frames = int(source.num_frames(int(video)))
    else:
      item = source[int(video)]
      num_frames = _num_frames(item, fields, int(video))
    if num_frames < span:
      raise ValueError(
          f'video {video} has {num_frames} frames, shorter than a clip of '
          f'{clip_length} frames with stride {frame_stride} ({span} frames)')
    start = int(fraction * (num_frames - span + 1))
    if clips:
      parts.append(source.clip(int(video), start, clip_length, frame_stride,
                               fields))
    else:
      parts.append(_slice_item(item, fields, int(video), start, clip_length,
                               frame_stride))
  if transform is None:
    return _stack(parts, fields)
  first_row = rows.start
  parts = [transform(part, transform_rng(seed, step, first_row + i))
           for i, part in enumerate(parts)]
  return _stack(parts, tuple(parts[0]))


def train_batches(source: Source, *, batch_size: int, clip_length: int,
                  seed: int, start_step: int = 0,
                  fields: Sequence[str] = ('video',), frame_stride: int = 1,
                  process_index: int = 0, process_count: int = 1,
                  prefetch: int = 2, num_workers: int = 0,
                  transform: Transform | None = None
                  ) -> Iterator[dict[str, np.ndarray]]:
  """Infinite random training clips, one batch per global step.

  Args:
    source: the videos (see the module docstring).
    batch_size: B, clips per batch on this host (the global batch is
      ``process_count * B``).
    clip_length: L, frames per clip.
    seed: seed of the whole stream.
    start_step: global step of the first batch (for resuming).
    fields: item keys to return; non-scalar ones must have time first.
    frame_stride: take every ``frame_stride``-th frame.
    process_index, process_count: this host and the number of hosts; host
      ``p`` gets rows ``[p * B, (p + 1) * B)`` of the global batch.
    prefetch: batches built ahead in a background thread (0: no thread), or
      with `num_workers`, by each worker process.
    num_workers: 0: build the batches in this process (the thread above);
      N >= 1: in N worker processes (`data.reader_workers`), worker w building
      the steps s with (s - start_step) % N == w. The stream is the same
      either way. A source that does not pickle falls back to the thread,
      with a warning.
    transform: applied to every clip with its own generator
      (`transform_rng`: per seed, step and global row), e.g. SAVi's random
      resized crop (data/augment.py); the batch holds the fields it
      returns. None: the clips as read.

  Yields:
    ``{field: [B, L, ...]}`` (scalar fields: ``[B]``), dtypes as stored. The
    global batch of step ``s`` depends only on ``(seed, s, P * B)`` and the
    data, not on ``P``; with one host it is the batch itself.

  Raises:
    ValueError: bad arguments, or a video shorter than a clip.
  """
  if batch_size < 1 or clip_length < 1 or frame_stride < 1:
    raise ValueError('batch_size, clip_length and frame_stride must be >= 1, '
                     f'got {batch_size}, {clip_length}, {frame_stride}')
  if start_step < 0:
    raise ValueError(f'start_step must be >= 0, got {start_step}')
  fields = tuple(fields)
  _check_host(process_index, process_count)  # validate early
  if not isinstance(num_workers, int) or num_workers < 0:
    raise ValueError(f'num_workers must be an integer >= 0, got {num_workers!r}')

  # A partial of a module-level function, so that worker processes can
  # unpickle it (with its source).
  make = functools.partial(
      make_train_batch, source, batch_size=batch_size,
      clip_length=clip_length, seed=seed, fields=fields,
      frame_stride=frame_stride, process_index=process_index,
      process_count=process_count, transform=transform)
  if num_workers > 0:
    make_bytes, why = workers.picklable(make)
    if make_bytes is not None:
      return workers.worker_batches(make_bytes, start_step, num_workers,
                                    depth=max(1, prefetch))
    warnings.warn(f'training reader: {type(source).__name__} does not '
                  f'pickle ({why}); building batches in a thread instead of '
                  f'{num_workers} worker processes')
  return _prefetched(make, start_step, prefetch)


def _prefetched(make: Callable[[int], dict[str, np.ndarray]], start_step: int,
                prefetch: int) -> Iterator[dict[str, np.ndarray]]:
  """Yields make(start_step), make(start_step + 1), ... built ahead.

  The producer thread starts on the first ``next`` and is stopped and joined
  when the generator is closed or garbage collected, so abandoning the
  iterator does not leak a thread. Errors in ``make`` re-raise in the
  consumer.
  """
  if prefetch <= 0:
    step = start_step
    while True:
      yield make(step)
      step += 1
  buffer: queue.Queue[tuple[bool, Any]] = queue.Queue(maxsize=prefetch)
  stop = threading.Event()

  def put(entry: tuple[bool, Any]) -> bool:
    # Timed puts so the producer notices `stop` even when the buffer is full.
    while not stop.is_set():
      try:
        buffer.put(entry, timeout=0.05)
        return True
      except queue.Full:
        continue
    return False

  def produce() -> None:
    step = start_step
    try:
      while not stop.is_set():
        if not put((True, make(step))):
          return
        step += 1
    except BaseException as error:  # pylint: disable=broad-except
      put((False, error))

  thread = threading.Thread(target=produce, name='slotformer-data-prefetch',
                            daemon=True)
  thread.start()
  try:
    while True:
      ok, value = buffer.get()
      if not ok:
        raise value
      yield value
  finally:
    stop.set()
    # The producer finishes at most the batch it is building; the timeout
    # only guards against a read that never returns (the thread is a daemon).
    thread.join(timeout=_JOIN_TIMEOUT_S)
    if thread.is_alive():
      warnings.warn('data prefetch thread did not stop within '
                    f'{_JOIN_TIMEOUT_S} s; leaving it behind (daemon)')


def eval_batches(source: Source, *, batch_size: int,
                 fields: Sequence[str] = ('video',),
                 num_frames: int | None = None, process_index: int = 0,
                 process_count: int = 1, max_videos: int | None = None,
                 multiple_of: int = 1) -> Iterator[dict[str, np.ndarray]]:
  """Every video of this host's shard once, in order, in fixed-shape batches.

  Args:
    source: the videos (see the module docstring).
    batch_size: B, videos per batch on this host.
    fields: item keys to return; non-scalar ones must have time first.
    num_frames: keep the first ``num_frames`` frames (None: all frames; then
      all videos must have the same length).
    process_index, process_count: this host and the number of hosts.
    max_videos: only use the first ``max_videos`` videos of the source
      (before sharding, so the evaluated set does not depend on the number of
      hosts).
    multiple_of: the batch size stays a multiple of it (the host's devices).

  Yields:
    ``{field: [b, num_frames, ...], 'index': int32 [b], 'mask': bool [b]}``,
    b <= B as `host_batch_plan` sizes it (a 2-video split is one batch of
    2, not of B). Batches are padded by repeating the last video, with
    ``mask`` False on the padding. Every host yields the same number of
    batches, ``ceil(ceil(N / P) / B)`` for N videos, of the same size, so
    collective eval steps stay in lockstep; a host with fewer videos gets
    extra padded entries.
  """
  if num_frames is not None and num_frames < 1:
    raise ValueError(f'num_frames must be >= 1, got {num_frames}')
  fields = tuple(fields)
  for indices, mask in host_batches(_num_eval_videos(source, max_videos),
                                    batch_size, process_index,
                                    process_count, multiple_of):
    parts = []
    cache: dict[int, dict[str, np.ndarray]] = {}  # padding repeats one video
    for index in indices:
      index = int(index)
      if index not in cache:
        cache[index] = _eval_item(source, index, fields, num_frames)
      parts.append(cache[index])
    lengths = {len(p[f]) for p in parts for f in fields if p[f].ndim}
    if len(lengths) > 1:
      raise ValueError(f'videos {indices.tolist()} have different lengths '
                       f'{sorted(lengths)}; pass num_frames to cut them')
    batch = _stack(parts, fields)
    batch['index'] = indices.astype(np.int32)
    batch['mask'] = mask
    yield batch


def _num_eval_videos(source: Source, max_videos: int | None) -> int:
  return len(source) if max_videos is None else min(len(source), max_videos)


def num_eval_batches(source: Source, *, batch_size: int,
                     process_count: int = 1, max_videos: int | None = None,
                     multiple_of: int = 1, **unused: Any) -> int:
  """How many batches :func:`eval_batches` yields given the same keyword
  arguments (those that do not change the count are accepted and ignored)."""
  del unused
  return host_batch_plan(_num_eval_videos(source, max_videos), batch_size,
                         process_count, multiple_of)[0]


def host_batch_plan(num_items: int, batch_size: int, process_count: int = 1,
                    multiple_of: int = 1) -> tuple[int, int]:
  """(number of batches, batch size) every host uses for `num_items` items.

  The number is that of full batches of at most `batch_size`,
  ``ceil(ceil(N / P) / batch_size)``; the size is the smallest multiple of
  `multiple_of` (the host's devices) that holds the host's share in that
  many batches. So a split smaller than a batch costs its own size rounded
  up to the devices, not a whole batch, and a larger one pads fewer than
  ``num_batches * multiple_of`` entries in all instead of up to a batch.
  """
  if batch_size < 1:
    raise ValueError(f'batch_size must be >= 1, got {batch_size}')
  if batch_size % multiple_of:
    raise ValueError(f'batch_size {batch_size} is not a multiple of '
                     f'{multiple_of}')
  per_host = math.ceil(num_items / process_count)
  num_batches = math.ceil(per_host / batch_size)
  if not num_batches:
    return 0, batch_size
  size = math.ceil(math.ceil(per_host / num_batches) / multiple_of)
  return num_batches, min(batch_size, size * multiple_of)


def host_batches(num_items: int, batch_size: int, process_index: int = 0,
                 process_count: int = 1, multiple_of: int = 1
                 ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
  """This host's items in batches of one size: (indices int64 [b], valid
  bool [b]) each, b and their number from `host_batch_plan` (b <=
  `batch_size`, a multiple of `multiple_of`).

  Host ``p`` of ``P`` gets items p, p + P, ... in order; a batch is padded
  by repeating the host's last item (``valid`` False there). Every host
  yields the same number of batches of the same size, so collective steps
  stay in lockstep; a host with no item at all (N < P) pads with item 0,
  all entries invalid.
  """
  shard = shard_indices(num_items, process_index, process_count)
  num_batches, size = host_batch_plan(num_items, batch_size, process_count,
                                      multiple_of)
  pad_item = int(shard[-1]) if len(shard) else 0
  for b in range(num_batches):
    real = shard[b * size:(b + 1) * size]
    indices = np.full(size, pad_item, np.int64)
    indices[:len(real)] = real
    yield indices, np.arange(size) < len(real)


def _eval_item(source: Source, index: int, fields: Sequence[str],
               num_frames: int | None) -> dict[str, np.ndarray]:
  item = source[index]
  length = _num_frames(item, fields, index)
  if num_frames is not None and length < num_frames:
    raise ValueError(f'video {index} has {length} frames, fewer than '
                     f'num_frames={num_frames}')
  return _slice_item(item, fields, index, 0,
                     length if num_frames is None else num_frames, 1)


class ClipSource:
  """Clips of a source's videos, each served as an item of its own.

  ``clips[i] = (video, start)``: item ``i`` is ``source[video]`` with the
  ``time_fields`` cut to begin at frame ``start`` (other entries unchanged).
  Used for evaluation protocols that pick specific clips per video (e.g.
  CLEVRER's clips without entering objects).
  """

  def __init__(self, source: Source, clips: Sequence[tuple[int, int]],
               time_fields: Sequence[str]):
    self._source = source
    self._clips = [(int(video), int(start)) for video, start in clips]
    self._time_fields = tuple(time_fields)

  def __len__(self) -> int:
    return len(self._clips)

  def __getitem__(self, index: int) -> dict[str, Any]:
    video, start = self._clips[index]
    item = dict(self._source[video])
    for field in self._time_fields:
      item[field] = item[field][start:]
    return item

  @property
  def clips(self) -> list[tuple[int, int]]:
    return list(self._clips)
