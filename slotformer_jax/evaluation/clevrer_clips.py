"""CLEVRER's official evaluation (and training) clips: no object entering late.

An object that comes into view during the rollout (or late in the burn-in)
cannot be predicted from the observed frames, so the official SlotFormer
CLEVRER evaluation skips clips where one does: per half-clip block of a
video, the first start without such an entry (:func:`eval_clip_starts`);
training with ``filter_enter=True`` uses every such start
(:func:`train_clip_starts`). Both read the converted dataset's ``in_view``
(bool [T, O], full frame rate; data/convert/clevrer.py stores it). Frame
numbers are full-rate; a clip takes frames ``start + i * frame_stride`` for
``i < burn_in + rollout``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

# Official filter: an object entering during the burn-in must be visible in
# at least this many burn-in frames.
MIN_BURN_IN_FRAMES_VISIBLE = 3


def entering_frames(in_view: np.ndarray) -> np.ndarray:
  """int64 [K]: frames t where some object goes from out of view to in view.

  ``in_view``: bool [T, O] as stored (full frame rate). As in the official
  code, an object visible from frame 0 does not enter, and a frame counts
  once however many objects enter in it.
  """
  in_view = np.asarray(in_view, bool)
  entered = (~in_view[:-1] & in_view[1:]).any(axis=1)
  return np.nonzero(entered)[0].astype(np.int64) + 1


def clip_has_entering_object(
    enter_frames: np.ndarray, start: int, burn_in: int, rollout: int,
    frame_stride: int,
    min_burn_in_visible: int = MIN_BURN_IN_FRAMES_VISIBLE) -> bool:
  """Whether an object enters too late in the clip to be evaluated.

  The clip takes frames ``start + i * frame_stride`` for ``i < burn_in +
  rollout``. Following the official filter, an entry counts when it
  happens after clip frame ``burn_in - min_burn_in_visible`` (so the object
  would be seen in fewer than ``min_burn_in_visible`` burn-in frames) and no
  later than the last clip frame. Frame numbers are full-rate.
  """
  first = start + (burn_in - min_burn_in_visible) * frame_stride
  last = start + (burn_in + rollout - 1) * frame_stride
  enter_frames = np.asarray(enter_frames)
  return bool(((enter_frames > first) & (enter_frames <= last)).any())


def clevrer_eval_filter(item: Mapping[str, Any], burn_in: int, rollout: int,
                        frame_stride: int, start: int = 0) -> bool:
  """True if the clip of ``item`` at ``start`` may be used for evaluation.

  Args:
    item: a stored CLEVRER video (full frame rate, as read from the source),
      with ``in_view`` and ``has_annotations``.
    burn_in, rollout: clip frames observed / predicted.
    frame_stride: temporal subsampling (2 in the paper).
    start: first full-rate frame of the clip.

  Returns:
    False if an object enters during the rollout (or late in the burn-in,
    see :func:`clip_has_entering_object`) or the clip does not fit in the
    video; True otherwise.

  Raises:
    ValueError: the item has no annotations (test split).
  """
  if not bool(np.asarray(item['has_annotations'])):
    raise ValueError('this CLEVRER video has no annotations (test split); '
                     'the entering-object filter needs them')
  in_view = np.asarray(item['in_view'])
  last = start + (burn_in + rollout - 1) * frame_stride
  if start < 0 or last >= in_view.shape[0]:
    return False
  return not clip_has_entering_object(entering_frames(in_view), start,
                                      burn_in, rollout, frame_stride)


def train_clip_starts(in_view: np.ndarray, burn_in: int, rollout: int,
                      frame_stride: int) -> np.ndarray:
  """int64 [K]: every start whose clip has no late entering object.

  The official SlotFormer CLEVRER training set (``filter_enter=True``).
  """
  num_frames = np.asarray(in_view).shape[0]
  enter = entering_frames(in_view)
  span = (burn_in + rollout - 1) * frame_stride
  return np.asarray([
      s for s in range(num_frames - span)
      if not clip_has_entering_object(enter, s, burn_in, rollout,
                                      frame_stride)], np.int64)


def eval_clip_starts(in_view: np.ndarray, burn_in: int, rollout: int,
                     frame_stride: int) -> np.ndarray:
  """int64 [K]: the official evaluation clips of one video.

  The video is cut into blocks of half a clip span; in each block the first
  start without a late entering object is taken (none if all have one).
  Like the official loop, the last possible start is never a block start.
  """
  num_frames = np.asarray(in_view).shape[0]
  enter = entering_frames(in_view)
  span = (burn_in + rollout - 1) * frame_stride
  interval = max(1, span // 2)
  starts = []
  for block in range(0, num_frames - span, interval):
    for start in range(block, min(block + interval, num_frames - span)):
      if not clip_has_entering_object(enter, start, burn_in, rollout,
                                      frame_stride):
        starts.append(start)
        break
  return np.asarray(starts, np.int64)
