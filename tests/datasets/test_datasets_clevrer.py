"""CLEVRER: fixtures in the published layout -> convert -> read back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import dataset_fixtures as fx
from slotformer_jax import datasets
from slotformer_jax.datasets import clevrer
from slotformer_jax.data import media
from slotformer_jax.data import pipeline
from slotformer_jax.data import prepare
from slotformer_jax.data import sources
from slotformer_jax.data.write import convert as writer
from slotformer_jax.datasets import clevrer as clevrer_clips
from dataset_fixtures import data_section

# ffmpeg runs as a subprocess (fork + exec at once), which JAX's fork warning
# does not tell apart from a bare fork when JAX was imported by another test.
pytestmark = pytest.mark.filterwarnings(
    r'ignore:os\.fork\(\) was called:RuntimeWarning')

T = 16            # frames per fixture video (CLEVRER: 128)
SRC_H, SRC_W = 32, 48   # fixture frame size (CLEVRER: 320 x 480, same ratio)
RES = 16          # converted resolution
ROWS = media.nearest_indices(SRC_H, RES)
COLS = media.nearest_indices(SRC_W, RES)

# Annotated objects: (color, material, shape, RGB, first visible frame).
OBJECTS = (
    ('red', 'rubber', 'sphere', (200, 30, 30), 0),
    ('blue', 'metal', 'cube', (30, 30, 200), 0),
    ('green', 'rubber', 'cylinder', (30, 200, 30), 9),   # enters at frame 9
)
ENTER_FRAME = 9
OVERLAP_FRAME = 5


def object_mask(k: int, t: int) -> np.ndarray:
  """bool [SRC_H, SRC_W] full-resolution mask of object k at frame t."""
  mask = np.zeros((SRC_H, SRC_W), bool)
  if t < OBJECTS[k][4]:
    return mask
  if k == 0:    # moves right; overlaps object 1 at OVERLAP_FRAME
    x = 2 + 2 * t
    mask[6:16, x:x + 10] = True
    if t == OVERLAP_FRAME:
      mask[6:22, x:x + 24] = True
  elif k == 1:
    mask[14:26, 20:34] = True
  else:
    mask[22:30, 2 + t:10 + t] = True
  return mask


def frame_level(t: int) -> int:
  return 40 + 5 * t


def make_video() -> np.ndarray:
  frames = np.zeros((T, SRC_H, SRC_W, 3), np.uint8)
  for t in range(T):
    frames[t] = frame_level(t)
    for k in (2, 1, 0):
      frames[t][object_mask(k, t)] = OBJECTS[k][3]
  return frames


def spurious_mask() -> np.ndarray:
  """A detection that matches no annotated object (listed last, every frame)."""
  mask = np.zeros((SRC_H, SRC_W), bool)
  mask[0:3, 40:46] = True
  return mask


def proposals(t: int, *, size: tuple[int, int] = (SRC_H, SRC_W)) -> list:
  """The frame's proposals: order varies, one wrong material, one spurious."""
  entries = []
  for k, (color, material, shape, _, _) in enumerate(OBJECTS):
    mask = object_mask(k, t)
    if not mask.any():
      continue
    if k == 1 and t % 3 == 0:
      material = 'rubber'  # mis-predicted: matched by colour + shape
    rle = fx.encode_rle(mask) if size == (SRC_H, SRC_W) else fx.encode_rle(
        np.zeros(size, bool))
    entries.append({'mask': rle, 'color': color, 'material': material,
                    'shape': shape, 'score': 0.99, 'frame_index': t})
  if t == OVERLAP_FRAME:
    entries = [entries[1], entries[0]] + entries[2:]  # object 1 listed first
  elif t % 2:
    entries = entries[::-1]
  entries.append({'mask': fx.encode_rle(spurious_mask()), 'color': 'yellow',
                  'material': 'metal', 'shape': 'cube', 'score': 0.5})
  return entries


def proposal_order(t: int) -> list[int]:
  order = [k for k in range(3) if object_mask(k, t).any()]
  if t == OVERLAP_FRAME:
    return [order[1], order[0]] + order[2:]
  return order[::-1] if t % 2 else order


def annotation(index: int, *, frames: int = T) -> dict:
  return {
      'scene_index': index, 'video_filename': f'video_{index:05d}.mp4',
      'object_property': [
          {'object_id': k, 'color': c, 'material': m, 'shape': s}
          for k, (c, m, s, _, _) in enumerate(OBJECTS)],
      'motion_trajectory': [
          {'frame_id': t, 'objects': [
              {'object_id': k, 'location': [0, 0, 0],
               'inside_camera_view': t >= OBJECTS[k][4]}
              for k in range(len(OBJECTS))]}
          for t in range(frames)],
      'collision': [],
  }


def video_path(root: Path, split: str, index: int) -> Path:
  level = index // 1000
  return (root / 'videos' / split /
          f'video_{level * 1000:05d}-{(level + 1) * 1000:05d}' /
          f'video_{index:05d}.mp4')


def annotation_path(root: Path, split: str, index: int) -> Path:
  level = index // 1000
  return (root / 'annotations' / split /
          f'annotation_{level * 1000:05d}-{(level + 1) * 1000:05d}' /
          f'annotation_{index:05d}.json')


def add_video(root: Path, split: str, index: int, *, with_annotation=True,
              with_proposal=True) -> None:
  """One video with its annotation and proposals (copied from a template)."""
  template = root.parent / 'template.mp4'
  if not template.exists():
    fx.write_mp4(template, make_video())
  target = video_path(root, split, index)
  target.parent.mkdir(parents=True, exist_ok=True)
  target.write_bytes(template.read_bytes())
  if with_annotation:
    fx.write_json(annotation_path(root, split, index), annotation(index))
  if with_proposal:
    fx.write_json(root / 'derender_proposals' / f'proposal_{index:05d}.json',
                  {'video_index': index, 'video_name': f'sim_{index:05d}',
                   'frames': [{'frame_index': t, 'objects': proposals(t)}
                              for t in range(T)]})


def question_entry(index: int, text: str) -> dict:
  return {'scene_index': index, 'video_filename': f'video_{index:05d}.mp4',
          'questions': [{'question_id': 0, 'question_type': 'descriptive',
                         'question': text, 'answer': 'red'}]}


@pytest.fixture(scope='module')
def converted(tmp_path_factory):
  base = tmp_path_factory.mktemp('clevrer')
  root = base / 'CLEVRER'
  add_video(root, 'train', 0)
  add_video(root, 'train', 1)
  add_video(root, 'val', 10000)
  add_video(root, 'test', 15000, with_annotation=False, with_proposal=False)
  fx.write_json(root / 'questions' / 'train.json',
                [question_entry(0, 'What color is the sphere?')])
  fx.write_json(root / 'questions' / 'validation.json',
                [question_entry(10000, 'Is it moving?')])
  fx.write_json(root / 'questions' / 'test.json',
                [question_entry(15000, 'What will happen next?')])
  data_dir = base / 'data'
  code = prepare.main([
      '--dataset=clevrer', f'--source={root}', f'--data_dir={data_dir}',
      f'--resolution={RES}', f'--num_frames={T}', '--num_workers=1',
      '--no_progress'])
  assert code == 0
  return data_dir


def source_for(data_dir: Path, split: str, **extra) -> sources.VideoSource:
  config = data_section(name='clevrer', data_dir=str(data_dir),
                        resolution=(RES, RES), **extra)
  return datasets.get_video_source(config, split)


def expected_masks(t: int) -> tuple[np.ndarray, np.ndarray]:
  """Resized instance masks [4, RES, RES] and the label map [RES, RES].

  Rows 0..2: the annotated objects; row 3: the spurious proposal, which is
  listed last in every frame and gets the first label after the objects.
  """
  full = [object_mask(k, t) for k in range(3)] + [spurious_mask()]
  small = np.stack([m[ROWS][:, COLS] for m in full])
  labels = np.zeros((RES, RES), np.uint8)
  for k in proposal_order(t) + [3]:
    labels[(labels == 0) & small[k]] = k + 1
  return small, labels


def test_shapes_frames_and_fields(converted):
  train = source_for(converted, 'train')
  assert len(train) == 2
  item = train[1]
  assert item['video'].shape == (T, RES, RES, 3)
  assert item['video'].dtype == np.uint8
  assert item['segmentations'].shape == (T, RES, RES)
  # Instance rows: 6 objects + 1 (the official boxes are padded to 7 too).
  assert item['boxes'].shape == (T, 7, 4) and item['boxes'].dtype == np.float32
  assert item['visible'].shape == (T, 7) and item['in_view'].shape == (T, 6)
  assert str(item['video_name'].item(), 'utf-8') == 'video_00001'
  assert int(item['video_index']) == 1
  assert int(item['num_objects']) == 3
  assert bool(item['has_annotations']) and bool(item['has_masks'])
  # Full-rate frames in order: the background level encodes the frame.
  corner = item['video'][:, -1, -1, :].astype(int)
  np.testing.assert_allclose(corner.mean(-1), [frame_level(t) for t in range(T)],
                             atol=3)
  np.testing.assert_array_equal(item['colors'][:3], [
      clevrer.COLORS.index(o[0]) for o in OBJECTS])
  np.testing.assert_array_equal(item['colors'][3:], -1)


def test_masks_ids_boxes(converted):
  item = source_for(converted, 'train')[0]
  for t in range(T):
    small, labels = expected_masks(t)
    np.testing.assert_array_equal(item['segmentations'][t], labels,
                                  err_msg=f'frame {t}')
    for k in range(4):
      visible = small[k].any()
      assert item['visible'][t, k] == visible
      if visible:
        ys, xs = np.nonzero(small[k])
        np.testing.assert_allclose(
            item['boxes'][t, k],
            [ys.min() / RES, xs.min() / RES, (ys.max() + 1) / RES,
             (xs.max() + 1) / RES])
      else:
        np.testing.assert_array_equal(item['boxes'][t, k], 0)
  # Overlap: object 1 is listed first in that frame, so it keeps the pixels
  # both masks cover, while object 0's box still spans its whole mask.
  small, _ = expected_masks(OVERLAP_FRAME)
  both = small[0] & small[1]
  assert both.any()
  assert (item['segmentations'][OVERLAP_FRAME][both] == 2).all()
  # Ids stay with the objects although the proposal order changes per frame.
  assert (item['segmentations'][:, :, :] == 3).any(axis=(1, 2)).tolist() == [
      t >= ENTER_FRAME for t in range(T)]
  # The spurious yellow cube (one per frame) matched no annotated object but
  # is still a ground-truth instance, as in the official evaluation.
  assert (item['segmentations'] == 4).any(axis=(1, 2)).all()
  assert not item['visible'][:, 4:].any()
  assert int(item['num_unmatched_masks']) == T
  assert int(item['num_dropped_masks']) == 0


def _proposal(mask: np.ndarray, color: str, material: str, shape: str) -> dict:
  return {'mask': fx.encode_rle(mask), 'color': color, 'material': material,
          'shape': shape}


def test_label_frame_duplicates_and_overflow():
  """Second detections of an object and extra proposals get frame labels."""
  annotation = clevrer._Annotation(
      in_view=np.ones((1, 2), bool),
      attributes=np.array([[1, 1, 1], [2, 0, 0]], np.int32),
      num_objects=2)
  h = w = 6
  masks = np.zeros((5, h, w), bool)
  for i in range(5):
    masks[i, i, :] = True   # one row each
  props = [
      _proposal(masks[0], 'blue', 'metal', 'cube'),        # object 1
      _proposal(masks[1], 'red', 'rubber', 'sphere'),      # object 0
      _proposal(masks[2], 'red', 'rubber', 'sphere'),      # object 0 again
      _proposal(masks[3], 'purple', 'metal', 'cylinder'),  # no such object
      _proposal(masks[4], 'cyan', 'metal', 'cube'),        # no row left
  ]
  rows = cols = media.nearest_indices(h, h)
  segmentation = np.zeros((h, w), np.uint8)
  instances = np.zeros((4, h, w), bool)   # M = 2 objects + 2
  unmatched, dropped = clevrer._label_frame(props, annotation, rows, cols,
                                            segmentation, instances)
  assert (unmatched, dropped) == (3, 1)
  np.testing.assert_array_equal(segmentation[:, 0], [2, 1, 3, 4, 0, 0])
  np.testing.assert_array_equal(instances[:, :, 0].argmax(1), [1, 0, 2, 3])


def test_enter_filter_on_converted_item(converted):
  item = source_for(converted, 'val')[0]
  np.testing.assert_array_equal(
      clevrer_clips.entering_frames(item['in_view']), [ENTER_FRAME])
  # Clip frames 0, 2, ..., 8: the object enters after the clip.
  assert clevrer_clips.clevrer_eval_filter(item, burn_in=3, rollout=2,
                                           frame_stride=2)
  # Clip frames 0 .. 10: it enters during the rollout.
  assert not clevrer_clips.clevrer_eval_filter(item, burn_in=3, rollout=3,
                                               frame_stride=2)
  # Clip frames 6 .. 14 (burn-in 6, 8, 10, 12): it enters before burn-in
  # frame 10, so it is seen in burn-in frames 10 and 12 only: filtered.
  assert not clevrer_clips.clevrer_eval_filter(item, burn_in=4, rollout=1,
                                               frame_stride=2, start=6)
  # Clip frames 2 .. 14, burn-in 2 .. 12: seen in burn-in frames 10 and 12
  # only, filtered; from start 3 it is seen in burn-in frames 9, 11, 13: kept.
  assert not clevrer_clips.clevrer_eval_filter(item, burn_in=6, rollout=1,
                                               frame_stride=2, start=2)
  assert clevrer_clips.clevrer_eval_filter(item, burn_in=6, rollout=1,
                                           frame_stride=2, start=3)
  # A clip that does not fit in the video is never used.
  assert not clevrer_clips.clevrer_eval_filter(item, burn_in=6, rollout=6,
                                               frame_stride=2)


def test_clip_window_matches_official_rule():
  # Official: entry t is bad iff start + (burn_in - 3) * s < t <= start +
  # (burn_in + rollout - 1) * s.
  enter = np.array([10])
  for start in range(0, 8):
    for stride in (1, 2):
      first = start + (6 - 3) * stride
      last = start + (6 + 4 - 1) * stride
      assert clevrer_clips.clip_has_entering_object(
          enter, start, 6, 4, stride) == (first < 10 <= last)
  # Entering at frame 0 .. first is fine; first + 1 is not.
  assert not clevrer_clips.clip_has_entering_object(np.array([3]), 0, 6, 4,
                                                    1)
  assert clevrer_clips.clip_has_entering_object(np.array([4]), 0, 6, 4, 1)


def test_entering_frames_constructed():
  in_view = np.zeros((12, 4), bool)
  in_view[:, 0] = True          # visible throughout: never enters
  in_view[3:, 1] = True         # enters at 3
  in_view[3:, 2] = True         # also at 3: counted once
  in_view[5:8, 3] = True        # enters at 5, leaves, re-enters at 10
  in_view[10:, 3] = True
  np.testing.assert_array_equal(clevrer_clips.entering_frames(in_view),
                                [3, 5, 10])


def test_official_clip_starts_constructed():
  in_view = np.zeros((40, 2), bool)
  in_view[:, 0] = True
  in_view[20:, 1] = True   # enters at 20
  starts = clevrer_clips.train_clip_starts(in_view, burn_in=3, rollout=2,
                                           frame_stride=2)
  # span 8: a start s is bad iff s < 20 <= s + 8, i.e. 12 <= s <= 19.
  np.testing.assert_array_equal(
      starts, [s for s in range(40 - 8) if not 12 <= s <= 19])
  evals = clevrer_clips.eval_clip_starts(in_view, burn_in=3, rollout=2,
                                         frame_stride=2)
  # Blocks of 4 starting at 0, 4, ..., 28; in block [12, 16) and [16, 20)
  # every start is bad; [20, 24) starts at 20.
  np.testing.assert_array_equal(evals, [0, 4, 8, 20, 24, 28])


def test_splits_without_annotations_and_questions(converted):
  test = source_for(converted, 'test')
  item = test[0]
  assert not bool(item['has_annotations']) and not bool(item['has_masks'])
  assert not item['segmentations'].any()
  with pytest.raises(ValueError, match='no annotations'):
    clevrer_clips.clevrer_eval_filter(item, 3, 2, 2)
  questions = json.loads(item['questions'].item())
  assert questions['questions'][0]['question'] == 'What will happen next?'
  val = source_for(converted, 'val')[0]
  assert json.loads(val['questions'].item())['scene_index'] == 10000
  train = source_for(converted, 'train')
  assert train[1]['questions'].item() == b''  # no question for video 1


def test_channel_order_and_stride(converted):
  rgb = source_for(converted, 'train')[0]['video']
  bgr = source_for(converted, 'train', channel_order='bgr')[0]['video']
  np.testing.assert_array_equal(bgr, rgb[..., ::-1])
  with pytest.raises(ValueError, match='channel_order'):
    source_for(converted, 'train', channel_order='rgba')
  # Subsampling by 2 for video prediction is the reader's frame_stride.
  batch = pipeline.make_train_batch(
      source_for(converted, 'train'), 0, batch_size=2, clip_length=4,
      seed=0, fields=('video', 'segmentations'), frame_stride=2)
  levels = batch['video'][:, :, -1, -1].mean(-1)
  steps = np.diff(levels, axis=1)
  np.testing.assert_allclose(steps, 10, atol=3)  # 2 frames x 5 levels


def _bad_source(base: Path) -> Path:
  root = base / 'CLEVRER'
  add_video(root, 'train', 0)                              # fine
  add_video(root, 'train', 1, with_annotation=False)       # no annotation
  add_video(root, 'train', 2)                              # truncated
  truncated = video_path(root, 'train', 2)
  fx.write_mp4(truncated, fx.noise_video(T, SRC_H, SRC_W))
  fx.truncate(truncated, 0.6)
  add_video(root, 'train', 3)                              # not a video
  video_path(root, 'train', 3).write_bytes(b'\x00not an mp4' * 100)
  add_video(root, 'train', 4)                              # masks too small
  fx.write_json(root / 'derender_proposals' / 'proposal_00004.json',
                {'frames': [{'frame_index': t,
                             'objects': proposals(t, size=(16, 24))}
                            for t in range(T)]})
  add_video(root, 'train', 5)                              # 15-frame annotation
  fx.write_json(annotation_path(root, 'train', 5), annotation(5, frames=T - 1))
  return root


def test_bad_inputs_are_skipped_and_reported(tmp_path, capsys):
  root = _bad_source(tmp_path)
  args = ['--dataset=clevrer', f'--source={root}',
          f'--data_dir={tmp_path / "data"}', f'--resolution={RES}',
          f'--num_frames={T}', '--splits=train', '--num_workers=1',
          '--no_progress', '--videos_per_shard=2']
  # 5 of 6 videos are bad: the default limit refuses the dataset ...
  assert prepare.main(args) == 1
  err = capsys.readouterr().err
  assert 'Too many videos could not be converted' in err
  # ... and accepting the skips finishes it without decoding anything again.
  result = prepare.run(prepare.build_parser().parse_args(
      args + ['--max_skip_fraction=0.9']))
  assert result.complete and result.videos_processed == 0
  assert result.num_examples == {'train': 1}
  assert result.skip_counts() == {'train': {
      'missing_annotation': 1, 'truncated_video': 1, 'unreadable_video': 1,
      'frame_size_mismatch': 1, 'frame_count_mismatch': 1}}
  report = json.loads((result.dataset_dir / writer.REPORT_FILE).read_text())
  assert {s['key'] for s in report['skipped']} == {
      'video_00001', 'video_00002', 'video_00003', 'video_00004',
      'video_00005'}
  item = source_for(tmp_path / 'data', 'train')[0]
  assert str(item['video_name'].item(), 'utf-8') == 'video_00000'


def test_missing_folders_name_the_layout(tmp_path):
  root = tmp_path / 'CLEVRER'
  add_video(root, 'train', 0)
  options = clevrer.Options(num_frames=T)
  with pytest.raises(FileNotFoundError, match=r'videos/val') as error:
    clevrer.discover(root, 'val', options)
  assert 'annotation_NNNNN.json' in str(error.value)
  (root / 'annotations').rename(tmp_path / 'elsewhere')
  with pytest.raises(FileNotFoundError, match=r'annotations/train'):
    clevrer.discover(root, 'train', options)
  with pytest.raises(FileNotFoundError, match='derender_proposals'):
    (tmp_path / 'elsewhere').rename(root / 'annotations')
    (root / 'derender_proposals').rename(tmp_path / 'masks')
    clevrer.discover(root, 'train',
                     clevrer.Options(num_frames=T, masks='require'))
  # 'auto' without the folder converts without masks.
  jobs = clevrer.discover(root, 'train', options)
  assert not jobs[0].proposal_expected


def test_unprepared_dataset_error_names_the_command(tmp_path):
  config = data_section(name='clevrer', data_dir=str(tmp_path))
  with pytest.raises(FileNotFoundError,
                     match='python -m slotformer_jax.data.prepare'):
    datasets.get_video_source(config, 'train')


def test_rle_round_trip():
  rng = np.random.default_rng(0)
  for _ in range(50):
    h, w = rng.integers(1, 30, 2)
    mask = rng.random((h, w)) < rng.random()
    rle = fx.encode_rle(mask)
    np.testing.assert_array_equal(clevrer.decode_rle(rle), mask)
    rows = media.nearest_indices(h, 5)
    cols = media.nearest_indices(w, 7)
    np.testing.assert_array_equal(clevrer.sample_rle(rle, rows, cols),
                                  mask[rows][:, cols])
  with pytest.raises(ValueError):
    clevrer.decode_rle({'size': [4, 4], 'counts': '3'})  # runs sum to 3
