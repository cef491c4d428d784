"""CLEVRER: the dataset, its published layout, its conversion and its
official evaluation clips.

Stored per video (records in video-index order; O = ``Options.max_objects``
= 6, M = O + 1 instance rows): ``video`` uint8 [T, H, W, 3] (all 128 frames,
RGB), ``segmentations`` uint8 [T, H, W] (0 background, 1..N the annotated
objects, above N the frame's other proposals), ``boxes`` float32 [T, M, 4],
``visible`` bool [T, M], ``in_view`` bool [T, O], ``num_objects``,
``colors`` / ``materials`` / ``shapes`` int32 [O], ``has_annotations``,
``has_masks``, ``questions`` (JSON text), ``video_index``, ``video_name``.

Evaluation clips (``evaluation.clips='clevrer'``): an object that comes into
view during the rollout cannot be predicted from the burn-in, so the official
evaluation skips such clips (:func:`eval_clip_starts`, from ``in_view``).
The layout, each field and the rules: docs/datasets.md, "CLEVRER".
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

from slotformer_jax.data import media
from slotformer_jax.datasets import base
from slotformer_jax.files import int_in_range
from slotformer_jax.runtime import progress

logger = logging.getLogger(__name__)

NAME = 'clevrer'
SPLITS: tuple[str, ...] = ('train', 'val', 'test')
ANNOTATED_SPLITS: tuple[str, ...] = ('train', 'val')
DEFAULT_RESOLUTION = (64, 64)
COLORS: tuple[str, ...] = ('gray', 'red', 'blue', 'green', 'brown', 'cyan',
                           'purple', 'yellow')
MATERIALS: tuple[str, ...] = ('metal', 'rubber')
SHAPES: tuple[str, ...] = ('cube', 'sphere', 'cylinder')
# The official SlotFormer loader leaves this video out: its annotation is
# broken.
KNOWN_BAD_VIDEOS: frozenset[int] = frozenset({10800})
CONVERTER_VERSION = 2
QUESTION_FILES: Mapping[str, tuple[str, ...]] = {
    'train': ('train.json',), 'val': ('validation.json', 'val.json'),
    'test': ('test.json',)}
MASK_MODES: tuple[str, ...] = ('auto', 'require', 'ignore')

LAYOUT = """\
<source>/videos/{train,val,test}/video_XXXXX-YYYYY/video_NNNNN.mp4
<source>/annotations/{train,val}/annotation_XXXXX-YYYYY/annotation_NNNNN.json
<source>/derender_proposals/proposal_NNNNN.json   (optional: instance masks)
<source>/questions/{train,validation,test}.json   (optional: VQA)
(the archives from http://clevrer.csail.mit.edu/, unpacked)"""

# Converting every split is the default: a download without the test
# videos (only VQA's test predictions read them) names the way round.
_MISSING_SPLIT_HINTS = {
    'test': (' (the test videos are only needed for VQA test predictions; '
             'without them convert the others: --splits=train,val)'),
}

_VIDEO_RE = re.compile(r'^video_(\d+)\.mp4$')
_ANNOTATION_RE = re.compile(r'^annotation_(\d+)\.json$')
_PROPOSAL_RE = re.compile(r'^proposal_(\d+)\.json$')


@dataclasses.dataclass(frozen=True)
class Options(base.ConversionOptions):
  """Conversion parameters.

  Attributes:
    resolution: (H, W) of the stored frames and masks.
    num_frames: frames every video must have (128 in CLEVRER).
    max_objects: O, most annotated objects of a video; rows of the
      per-object arrays (``in_view``, ``colors`` ...). The per-instance
      arrays (``boxes``, ``visible``) have ``mask_rows`` = O + 1 rows.
    masks: 'auto' (convert the derender proposals if that folder exists),
      'require' (fail if it does not), 'ignore' (store no masks).
  """

  resolution: tuple[int, int] = DEFAULT_RESOLUTION
  num_frames: int = 128
  max_objects: int = 6
  masks: str = 'auto'
  version = CONVERTER_VERSION

  def __post_init__(self):
    super().__post_init__()
    if self.num_frames < 2:
      raise ValueError(f'num_frames must be >= 2, got {self.num_frames}')
    if not 1 <= self.max_objects <= 253:
      raise ValueError(f'max_objects must be in [1, 253], got '
                       f'{self.max_objects}')
    if self.masks not in MASK_MODES:
      raise ValueError(f'masks must be one of {MASK_MODES}, got {self.masks!r}')

  @property
  def mask_rows(self) -> int:
    """M: instance rows (annotated objects + room for other proposals)."""
    return self.max_objects + 1


@dataclasses.dataclass(frozen=True)
class VideoJob:
  """One video and its per-video files.

  Attributes:
    key: 'video_NNNNN'.
    index: NNNNN.
    video: the mp4.
    annotation: its annotation JSON; None where none is published (test).
    annotation_expected: the split has annotations (a missing one skips).
    proposal: its derender proposal JSON, or None.
    proposal_expected: masks are converted (a missing one skips).
    questions: its question entry as JSON text, '' if none.
  """

  key: str
  index: int
  video: Path
  annotation: Path | None
  annotation_expected: bool
  proposal: Path | None
  proposal_expected: bool
  questions: str = ''


# ----------------------------------------------------------------------------
# COCO run-length encoding (the masks of the derender proposals)
# ----------------------------------------------------------------------------


def rle_counts(counts: str | Sequence[int]) -> np.ndarray:
  """Run lengths int64 [K] of a COCO RLE (compressed string or list).

  Runs alternate background / foreground starting with background, over the
  mask in column-major order. The compressed string stores each run as
  5-bit groups (offset by 48, bit 0x20 = more groups follow, bit 0x10 of the
  last group = negative) and, from the fourth run on, as the difference to
  the run two places earlier.

  Raises:
    ValueError: malformed string.
  """
  if not isinstance(counts, str):
    return _runs(counts)
  runs: list[int] = []
  position = 0
  while position < len(counts):
    value, shift, more = 0, 0, True
    while more:
      if position >= len(counts):
        raise ValueError('RLE string ends inside a number')
      if shift > 40:  # a run of 2**40 pixels: no mask; and no slow bigint
        raise ValueError('an RLE number of more than 9 characters')
      group = ord(counts[position]) - 48
      if not 0 <= group < 64:
        raise ValueError(f'bad RLE character {counts[position]!r}')
      value |= (group & 0x1f) << shift
      more = bool(group & 0x20)
      position += 1
      shift += 5
      if not more and group & 0x10:
        value -= 1 << shift  # sign-extend
    if len(runs) > 2:
      value += runs[-2]
    runs.append(value)
  return _runs(runs)


# A run is at most a whole mask (CLEVRER's are 480 x 320); so bounded, no
# sum of a file's runs wraps in int64.
_MAX_RUN = 2**32


def _runs(values: Any) -> np.ndarray:
  """int64 [K] of a list of run lengths, each checked before the cast."""
  if not isinstance(values, list) or not all(type(v) is int
                                             for v in values):
    raise ValueError('RLE counts are not a list of integers')
  for value in (min(values), max(values)) if values else ():
    int_in_range(value, 0, _MAX_RUN, what='an RLE run length')
  return np.asarray(values, np.int64)


def _checked_runs(mask: Mapping[str, Any]) -> tuple[np.ndarray, int, int]:
  height, width = rle_size(mask)
  runs = rle_counts(mask['counts'])
  if (runs < 0).any() or int(runs.sum()) != height * width:
    raise ValueError(f'RLE runs sum to {int(runs.sum())}, not '
                     f'{height}x{width}')
  return runs, height, width


def decode_rle(mask: Mapping[str, Any]) -> np.ndarray:
  """bool [h, w] of a COCO RLE dict {'size': [h, w], 'counts': ...}."""
  runs, height, width = _checked_runs(mask)
  values = np.arange(len(runs)) % 2 == 1
  flat = np.repeat(values, runs)
  return flat.reshape(width, height).T


def sample_rle(mask: Mapping[str, Any], rows: np.ndarray,
               cols: np.ndarray) -> np.ndarray:
  """bool [len(rows), len(cols)]: the mask at pixels (rows[i], cols[j]).

  Looks the pixels up in the runs directly (no full-size decode), which is
  what nearest-neighbour resizing needs.
  """
  runs, height, _ = _checked_runs(mask)
  ends = np.cumsum(runs)
  flat = cols[None, :].astype(np.int64) * height + rows[:, None]
  return np.searchsorted(ends, flat, side='right') % 2 == 1


def rle_size(mask: Mapping[str, Any]) -> tuple[int, int]:
  return tuple(int_in_range(mask['size'][i], 1, 2**16, what='an RLE size')
               for i in range(2))


# ----------------------------------------------------------------------------
# Discovery
# ----------------------------------------------------------------------------


layout_error = functools.partial(base.layout_error, 'CLEVRER', LAYOUT)


def _index_files(folder: Path, pattern: re.Pattern[str],
                 suffix: str) -> dict[int, Path]:
  """{index: path} of the matching files anywhere below ``folder``."""
  found = {}
  for path in folder.rglob(f'*{suffix}'):
    match = pattern.match(path.name)
    if match:
      found[int(match.group(1))] = path
  return found


def _split_questions(source: Path, split: str) -> dict[int, str] | None:
  """{video index: its question entry as JSON text}, None if not available.

  Raises:
    ValueError: the question file exists but is not the published format.
  """
  folder = source / 'questions'
  if not folder.is_dir():
    return None
  for name in QUESTION_FILES[split]:
    path = folder / name
    if path.is_file():
      break
  else:
    logger.warning('CLEVRER: no question file for split %s in %s (looked '
                   'for %s); VQA questions will be empty.', split, folder,
                   ', '.join(QUESTION_FILES[split]))
    return None
  try:
    with open(path, 'rb') as f:
      entries = json.load(f)
    out = {}
    for entry in entries:
      out[int_in_range(entry['scene_index'], 0, 2**31 - 1,
                       what='a scene_index')] = json.dumps(entry,
                                                           sort_keys=True)
  except (OSError, ValueError, KeyError, TypeError) as error:
    raise ValueError(f'CLEVRER: cannot read the questions in {path}: expected '
                     'a JSON list of {"scene_index", "video_filename", '
                     f'"questions"}} entries ({error})') from None
  return out


def discover(source: Path, split: str, options: Options) -> list[VideoJob]:
  """The videos of ``split`` with their annotation / mask / question files.

  Raises:
    FileNotFoundError: a required folder of the published layout is
      missing, or holds no video.
    ValueError: unreadable question file.
  """
  video_dir = source / 'videos' / split
  if not video_dir.is_dir():
    raise layout_error(source, video_dir, _MISSING_SPLIT_HINTS.get(split, ''))
  videos = _index_files(video_dir, _VIDEO_RE, '.mp4')
  if not videos:
    raise layout_error(source, video_dir / 'video_XXXXX-YYYYY/video_NNNNN.mp4',
                       ' (no video found)')
  annotated = split in ANNOTATED_SPLITS
  annotations: dict[int, Path] = {}
  if annotated:
    annotation_dir = source / 'annotations' / split
    if not annotation_dir.is_dir():
      raise layout_error(source, annotation_dir,
                         ' (download "Annotations" for train and val)')
    annotations = _index_files(annotation_dir, _ANNOTATION_RE, '.json')
  proposal_dir = source / 'derender_proposals'
  use_masks = annotated and options.masks != 'ignore'
  if use_masks and not proposal_dir.is_dir():
    if options.masks == 'require':
      raise layout_error(source, proposal_dir,
                         ' (download "Object Masks and Attributes")')
    logger.warning('CLEVRER: %s not found: no masks/boxes will be stored '
                   '(needed to evaluate video prediction).', proposal_dir)
    use_masks = False
  proposals = (_index_files(proposal_dir, _PROPOSAL_RE, '.json') if use_masks
               else {})
  questions = _split_questions(source, split) or {}
  unused = sorted(set(questions) - set(videos))
  if unused:
    logger.warning('CLEVRER %s: questions about %d videos that are not in %s '
                   '(e.g. %s)', split, len(unused), video_dir, unused[:3])
  return [
      VideoJob(key=f'video_{index:05d}', index=index, video=videos[index],
               annotation=annotations.get(index), annotation_expected=annotated,
               proposal=proposals.get(index), proposal_expected=use_masks,
               questions=questions.get(index, ''))
      for index in sorted(videos)]


# ----------------------------------------------------------------------------
# Conversion
# ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Annotation:
  """The parts of one annotation JSON we store.

  in_view: bool [T_annotation, O]; attributes: int32 [O, 3] (colour,
  material, shape; -1 padding); num_objects: N.
  """

  in_view: np.ndarray
  attributes: np.ndarray
  num_objects: int


def _vocab_index(vocab: Sequence[str], value: Any, what: str) -> int:
  try:
    return vocab.index(str(value))
  except ValueError:
    raise ValueError(f'unknown {what} {value!r}') from None


def _read_annotation(job: VideoJob, options: Options) -> _Annotation:
  """Parses the object list and per-frame visibility of an annotation.

  Raises:
    media.SkipVideo: missing / broken annotation, too many objects.
  """
  if job.annotation is None:
    raise media.SkipVideo('missing_annotation',
                          f'no annotation_{job.index:05d}.json for '
                          f'{job.video}')
  data = media.load_json(job.annotation, 'annotation')
  try:
    objects = data['object_property']
    trajectory = data['motion_trajectory']
    ids = [int_in_range(o['object_id'], 0, 2**31 - 1, what='an object_id')
           for o in objects]
    if sorted(ids) != list(range(len(ids))):
      raise ValueError(f'object ids {ids} are not 0..N-1')
    if len(ids) > options.max_objects:
      raise media.SkipVideo(
          'too_many_objects',
          f'{job.annotation}: {len(ids)} objects, more than max_objects='
          f'{options.max_objects}')
    attributes = np.full((options.max_objects, 3), -1, np.int32)
    for o in objects:
      attributes[o['object_id']] = (
          _vocab_index(COLORS, o['color'], 'color'),
          _vocab_index(MATERIALS, o['material'], 'material'),
          _vocab_index(SHAPES, o['shape'], 'shape'))
    in_view = np.zeros((len(trajectory), options.max_objects), bool)
    for t, frame in enumerate(trajectory):
      for o in frame['objects']:
        object_id = int_in_range(o['object_id'], 0, 2**31 - 1,
                                 what=f'an object_id of frame {t}')
        if not object_id < len(ids):
          raise ValueError(f'frame {t} lists unknown object {object_id}')
        in_view[t, object_id] = bool(o['inside_camera_view'])
  except media.SkipVideo:
    raise
  except (KeyError, TypeError, ValueError) as error:
    raise media.SkipVideo('bad_annotation',
                          f'{job.annotation}: {type(error).__name__}: '
                          f'{error}') from None
  return _Annotation(in_view=in_view, attributes=attributes,
                     num_objects=len(ids))


def _match_object(proposal: Mapping[str, Any], attributes: np.ndarray,
                  num_objects: int) -> int | None:
  """Object id (0-based) a proposal belongs to, or None if not unique.

  Exact attribute match first; if that fails (a mis-predicted material is
  the usual case) a unique colour + shape match.
  """
  try:
    color = COLORS.index(str(proposal.get('color')))
    shape = SHAPES.index(str(proposal.get('shape')))
  except ValueError:
    return None
  material = proposal.get('material')
  material = MATERIALS.index(material) if material in MATERIALS else -1
  rows = attributes[:num_objects]
  exact = np.nonzero((rows[:, 0] == color) & (rows[:, 1] == material)
                     & (rows[:, 2] == shape))[0]
  if len(exact) == 1:
    return int(exact[0])
  loose = np.nonzero((rows[:, 0] == color) & (rows[:, 2] == shape))[0]
  if len(exact) == 0 and len(loose) == 1:
    return int(loose[0])
  return None


def boxes_from_masks(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Tight boxes of per-object masks.

  Args:
    masks: bool [T, O, H, W].

  Returns:
    boxes: float32 [T, O, 4] (ymin, xmin, ymax, xmax) normalised by H / W,
      pixel edges (rows 2..5 of H=8 give ymin=2/8, ymax=6/8); zeros where
      the mask is empty.
    visible: bool [T, O].
  """
  _, _, h, w = masks.shape
  rows = masks.any(axis=3)  # [T, O, H]
  cols = masks.any(axis=2)  # [T, O, W]
  visible = rows.any(axis=2)
  ymin = rows.argmax(axis=2)
  ymax = h - rows[..., ::-1].argmax(axis=2)
  xmin = cols.argmax(axis=2)
  xmax = w - cols[..., ::-1].argmax(axis=2)
  boxes = np.stack([ymin / h, xmin / w, ymax / h, xmax / w], axis=-1)
  return np.where(visible[..., None], boxes, 0.0).astype(np.float32), visible


@dataclasses.dataclass(frozen=True)
class _Masks:
  """The instance masks of one video at the stored resolution.

  segmentations: uint8 [T, H, W] labels (see the module doc); instances:
  bool [T, M, H, W], row k - 1 = label k; unmatched / dropped: proposals
  that matched no annotated object / did not fit in M rows.
  """

  segmentations: np.ndarray
  instances: np.ndarray
  unmatched: int
  dropped: int


def _label_frame(proposals: Sequence[Mapping[str, Any]],
                 annotation: _Annotation, rows: np.ndarray, cols: np.ndarray,
                 segmentation: np.ndarray, instances: np.ndarray
                 ) -> tuple[int, int]:
  """Fills one frame's label map and instance masks from its proposals.

  Args:
    proposals: the frame's proposal list (each with an RLE ``mask``).
    annotation: the video's objects.
    rows, cols: source pixel of each output row / column (nearest).
    segmentation: uint8 [H, W] zeros, written in place.
    instances: bool [M, H, W] zeros, written in place.

  Returns:
    (unmatched, dropped) proposal counts of the frame.
  """
  num_rows = instances.shape[0]
  taken = np.zeros(num_rows, bool)
  next_free = annotation.num_objects
  unmatched = dropped = 0
  for proposal in proposals:
    row = _match_object(proposal, annotation.attributes,
                        annotation.num_objects)
    if row is None or taken[row]:
      # Not an annotated object (or a second detection of one): still a
      # ground-truth instance of this frame, with a frame-local label.
      unmatched += 1
      while next_free < num_rows and taken[next_free]:
        next_free += 1
      if next_free >= num_rows:
        dropped += 1
        continue
      row = next_free
    taken[row] = True
    mask = sample_rle(proposal['mask'], rows, cols)
    instances[row] = mask
    # The earlier proposal wins where masks overlap (the official argmax).
    segmentation[mask & (segmentation == 0)] = row + 1
  return unmatched, dropped


def _read_masks(job: VideoJob, annotation: _Annotation,
                frame_size: tuple[int, int], options: Options) -> _Masks:
  """Instance masks at the stored resolution from the derender proposals.

  Raises:
    media.SkipVideo: missing / broken proposals, masks of another size than
      the video ('frame_size_mismatch'), frames without proposals entry.
  """
  if job.proposal is None:
    raise media.SkipVideo('missing_masks',
                          f'no derender proposal proposal_{job.index:05d}.json'
                          f' for {job.video}')
  data = media.load_json(job.proposal, 'masks')
  t_max = options.num_frames
  height, width = options.resolution
  rows = media.nearest_indices(frame_size[0], height)
  cols = media.nearest_indices(frame_size[1], width)
  segmentations = np.zeros((t_max, height, width), np.uint8)
  instances = np.zeros((t_max, options.mask_rows, height, width), bool)
  unmatched = dropped = 0
  try:
    frames = data['frames']
    # As the official loader, the list position is the frame number.
    if len(frames) < t_max:
      raise media.SkipVideo(
          'bad_masks', f'{job.proposal}: masks for {len(frames)} of {t_max} '
          'frames')
    for t in range(t_max):
      objects = frames[t]['objects']
      for proposal in objects:
        if rle_size(proposal['mask']) != tuple(frame_size):
          raise media.SkipVideo(
              'frame_size_mismatch',
              f'{job.proposal}: frame {t} has a '
              f'{"x".join(map(str, rle_size(proposal["mask"])))} mask, the '
              f'video is {frame_size[0]}x{frame_size[1]} (HxW)')
      frame_unmatched, frame_dropped = _label_frame(
          objects, annotation, rows, cols, segmentations[t], instances[t])
      unmatched += frame_unmatched
      dropped += frame_dropped
  except media.SkipVideo:
    raise
  except (KeyError, TypeError, ValueError, IndexError) as error:
    raise media.SkipVideo('bad_masks', f'{job.proposal}: '
                          f'{type(error).__name__}: {error}') from None
  return _Masks(segmentations=segmentations, instances=instances,
                unmatched=unmatched, dropped=dropped)


def convert_video(job: VideoJob, options: Options) -> dict[str, Any]:
  """Decodes, resizes and annotates one CLEVRER video (see module doc).

  Raises:
    media.SkipVideo: known-bad video, missing / broken annotation or masks,
      unreadable or truncated video, frame-count or frame-size mismatch.
  """
  if job.index in KNOWN_BAD_VIDEOS:
    raise media.SkipVideo('known_bad', f'{job.video}: its annotation is '
                          'known to be broken (left out officially too)')
  annotation = (_read_annotation(job, options) if job.annotation_expected
                else None)
  if annotation is not None and annotation.in_view.shape[0] != \
      options.num_frames:
    raise media.SkipVideo(
        'frame_count_mismatch',
        f'{job.annotation}: {annotation.in_view.shape[0]} annotated frames, '
        f'expected {options.num_frames}')
  frames, _ = media.decode_video(job.video, max_frames=options.num_frames + 1)
  if len(frames) < options.num_frames:
    raise media.SkipVideo('truncated_video',
                          f'{job.video}: decoded {len(frames)} frames, '
                          f'expected {options.num_frames}')
  if len(frames) > options.num_frames:
    raise media.SkipVideo('frame_count_mismatch',
                          f'{job.video}: more than {options.num_frames} '
                          'frames')
  frame_size = (int(frames.shape[1]), int(frames.shape[2]))
  t, (h, w), o = options.num_frames, options.resolution, options.max_objects
  m = options.mask_rows
  segmentations = np.zeros((t, h, w), np.uint8)
  boxes = np.zeros((t, m, 4), np.float32)
  visible = np.zeros((t, m), bool)
  unmatched = dropped = 0
  has_masks = annotation is not None and job.proposal_expected
  if has_masks:
    masks = _read_masks(job, annotation, frame_size, options)
    segmentations = masks.segmentations
    boxes, visible = boxes_from_masks(masks.instances)
    unmatched, dropped = masks.unmatched, masks.dropped
  return {
      'video': media.resize_frames(frames, options.resolution),
      'segmentations': segmentations,
      'boxes': boxes,
      'visible': visible,
      'in_view': (annotation.in_view if annotation is not None
                  else np.zeros((t, o), bool)),
      'num_objects': annotation.num_objects if annotation is not None else 0,
      'colors': (annotation.attributes[:, 0] if annotation is not None
                 else np.full((o,), -1, np.int32)),
      'materials': (annotation.attributes[:, 1] if annotation is not None
                    else np.full((o,), -1, np.int32)),
      'shapes': (annotation.attributes[:, 2] if annotation is not None
                 else np.full((o,), -1, np.int32)),
      'has_annotations': annotation is not None,
      'has_masks': has_masks,
      'num_unmatched_masks': unmatched,
      'num_dropped_masks': dropped,
      'questions': job.questions,
      'video_index': job.index,
      'video_name': job.key,
  }


def features(options: Options) -> tfds.features.FeaturesDict:
  t, (h, w), o = options.num_frames, options.resolution, options.max_objects
  m = options.mask_rows
  tensor = base.tensor
  return tfds.features.FeaturesDict({
      'video': tensor((t, h, w, 3), np.uint8),
      'segmentations': tensor((t, h, w), np.uint8),
      'boxes': tensor((t, m, 4), np.float32),
      'visible': tensor((t, m), np.bool_),
      'in_view': tensor((t, o), np.bool_),
      'num_objects': tfds.features.Scalar(np.int32),
      'colors': tensor((o,), np.int32),
      'materials': tensor((o,), np.int32),
      'shapes': tensor((o,), np.int32),
      'has_annotations': tfds.features.Scalar(np.bool_),
      'has_masks': tfds.features.Scalar(np.bool_),
      'num_unmatched_masks': tfds.features.Scalar(np.int32),
      'num_dropped_masks': tfds.features.Scalar(np.int32),
      'questions': tfds.features.Text(),
      'video_index': tfds.features.Scalar(np.int32),
      'video_name': tfds.features.Text(),
  })


def describe(options: Options) -> str:
  h, w = options.resolution
  return (f'CLEVRER: {options.num_frames} full-rate frames per video at '
          f'{h}x{w} (RGB), derender-proposal masks with '
          'annotation-consistent object ids, per-frame '
          'inside_camera_view, VQA questions as JSON text.')


# ----------------------------------------------------------------------------
# The official evaluation clips (no object entering late)
# ----------------------------------------------------------------------------

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


def evaluation_clips(videos: Any, num_videos: int, burn_in: int,
                     rollout: int, frame_stride: int
                     ) -> list[tuple[int, int]]:
  """(video, start) of the official CLEVRER evaluation clips of the first
  `num_videos` videos (items with `in_view` [T, O] and `has_annotations`)."""
  clips = []
  for video in progress.bar(range(num_videos), desc='find evaluation clips',
                            unit='video'):
    item = videos[video]
    if not bool(np.asarray(item.get('has_annotations', True))):
      raise ValueError(
          f'video {video} has no CLEVRER annotations (the test split has '
          "none); evaluate on the 'val' split")
    starts = eval_clip_starts(item['in_view'], burn_in, rollout,
                              frame_stride)
    clips += [(video, int(start)) for start in starts]
  if not clips:
    raise ValueError('no CLEVRER evaluation clip without entering objects '
                     f'in the first {num_videos} videos')
  return clips


DATASET = base.register(base.Converted(
    names=(NAME,), label='CLEVRER', command=NAME, splits=SPLITS,
    layout=LAYOUT, features=functools.partial(features, Options()),
    # The official models read the videos with OpenCV (nerv's VideoReader
    # without to_rgb): converted frames are RGB, handed out as BGR with
    # data.channel_order='bgr'.
    official_channel_order='bgr',
    clip_rules={'clevrer': evaluation_clips},
    options=Options, discover=discover, convert=convert_video,
    stored=features, describe=describe))
