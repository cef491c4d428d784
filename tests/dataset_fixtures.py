"""Helpers that write tiny dataset fixtures in the published file formats.

Used by tests/datasets/test_datasets_*.py: mp4 files through imageio-ffmpeg's bundled
ffmpeg, COCO run-length-encoded masks, PNG frames.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image


def write_mp4(path: Path, frames: np.ndarray, *, fps: int = 25,
              lossless: bool = True) -> Path:
  """Writes uint8 [T, H, W, 3] RGB frames (H, W even) as an H.264 mp4.

  ``lossless`` uses 4:4:4 chroma with a constant rate factor of 0, so decoded
  pixels differ from the input only by colour-conversion rounding. The moov
  atom goes first (``+faststart``), so a file cut short still opens and
  decodes its first frames, like a download interrupted mid-file.
  """
  import imageio_ffmpeg  # pylint: disable=g-import-not-at-top
  path.parent.mkdir(parents=True, exist_ok=True)
  height, width = frames.shape[1:3]
  params = ['-movflags', '+faststart']
  if lossless:
    params += ['-crf', '0']
  writer = imageio_ffmpeg.write_frames(
      str(path), (width, height), fps=fps, macro_block_size=1,
      pix_fmt_out='yuv444p' if lossless else 'yuv420p',
      output_params=params, ffmpeg_log_level='error', quality=None)
  writer.send(None)
  for frame in frames:
    writer.send(np.ascontiguousarray(frame))
  writer.close()
  return path


def truncate(path: Path, fraction: float) -> Path:
  """Keeps the first ``fraction`` of the file's bytes."""
  data = path.read_bytes()
  path.write_bytes(data[:int(len(data) * fraction)])
  return path


def encode_rle(mask: np.ndarray) -> dict[str, Any]:
  """COCO compressed RLE {'size': [h, w], 'counts': str} of a bool [h, w].

  Runs alternate background / foreground over the column-major pixels,
  starting with background; from the fourth run on each is stored as the
  difference to the run two before, in 5-bit groups offset by 48 (0x20:
  another group follows; 0x10 in the last group: negative).
  """
  flat = np.asarray(mask, bool).T.reshape(-1)
  change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
  bounds = np.concatenate([[0], change, [flat.size]])
  runs = list(np.diff(bounds))
  if flat.size and flat[0]:
    runs = [0] + runs
  chars = []
  for i, run in enumerate(runs):
    value = int(run) - (int(runs[i - 2]) if i > 2 else 0)
    more = True
    while more:
      group = value & 0x1f
      value >>= 5
      more = value != -1 if group & 0x10 else value != 0
      if more:
        group |= 0x20
      chars.append(chr(group + 48))
  return {'size': [int(mask.shape[0]), int(mask.shape[1])],
          'counts': ''.join(chars)}


def write_tfrecords(path: Path, records) -> Path:
  """A TFRecord file of ``records`` (as ``tf.io.TFRecordWriter`` without
  options), framed by data/tfrecord.py."""
  from slotformer_jax.data import tfrecord  # pylint: disable=g-import-not-at-top
  with open(path, 'wb') as f:
    for data in records:
      f.write(tfrecord.encode_record(data))
  return path


def write_png(path: Path, image: np.ndarray) -> Path:
  path.parent.mkdir(parents=True, exist_ok=True)
  Image.fromarray(image).save(path)
  return path


def write_json(path: Path, payload: Any) -> Path:
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text(json.dumps(payload))
  return path


def noise_video(num_frames: int, height: int, width: int,
                seed: int = 0) -> np.ndarray:
  """Incompressible frames: a truncated file of them loses whole frames."""
  rng = np.random.default_rng(seed)
  return rng.integers(0, 256, (num_frames, height, width, 3), np.uint8)


def marker_video(num_frames: int, height: int, width: int,
                 step: int = 10, offset: int = 20) -> np.ndarray:
  """Flat frames whose grey level ``offset + step * t`` identifies frame t."""
  levels = offset + step * np.arange(num_frames)
  return np.broadcast_to(levels[:, None, None, None].astype(np.uint8),
                         (num_frames, height, width, 3)).copy()


# ----------------------------------------------------------------------------
# Kubric MOVi in its published TFDS layout (TFRecord shards + features.json
# + dataset_info.json), written without TensorFlow
# ----------------------------------------------------------------------------


def movi_a_features(num_frames: int, height: int, width: int,
                    video_as_sequence: bool = True, flow_depth: bool = True):
  """MOVi-A's feature tree (Kubric's challenges/movi/movi_a.py) built from
  TFDS connectors. ``tfds.features.Video`` needs TensorFlow to be built, so
  the videos are ``Sequence(Image)``, which is how a Video is serialized
  (it is a Sequence of Images); :func:`write_movi` writes features.json
  with the Video connector in their place."""
  import tensorflow_datasets as tfds  # pylint: disable=g-import-not-at-top
  s, h, w = num_frames, height, width
  f32, u16 = np.float32, np.uint16

  def video(dtype):
    return tfds.features.Sequence(
        tfds.features.Image(shape=(h, w, 3), dtype=dtype), length=s)

  instance = {
      'mass': f32, 'friction': f32, 'restitution': f32,
      'positions': tfds.features.Tensor(shape=(s, 3), dtype=f32),
      'quaternions': tfds.features.Tensor(shape=(s, 4), dtype=f32),
      'velocities': tfds.features.Tensor(shape=(s, 3), dtype=f32),
      'angular_velocities': tfds.features.Tensor(shape=(s, 3), dtype=f32),
      'bboxes_3d': tfds.features.Tensor(shape=(s, 8, 3), dtype=f32),
      'image_positions': tfds.features.Tensor(shape=(s, 2), dtype=f32),
      'bboxes': tfds.features.Sequence(tfds.features.BBoxFeature()),
      'bbox_frames': tfds.features.Sequence(
          tfds.features.Tensor(shape=(), dtype=np.int32)),
      'visibility': tfds.features.Tensor(shape=(s,), dtype=u16),
      'shape_label': tfds.features.ClassLabel(
          names=['cube', 'cylinder', 'sphere']),
      'size_label': tfds.features.ClassLabel(names=['small', 'large']),
      'color': tfds.features.Tensor(shape=(3,), dtype=f32),
      'color_label': tfds.features.ClassLabel(
          names=['blue', 'brown', 'cyan', 'gray', 'green', 'purple', 'red',
                 'yellow']),
      'material_label': tfds.features.ClassLabel(names=['metal', 'rubber']),
  }
  tree = {
      'metadata': {
          'video_name': tfds.features.Text(), 'width': np.int32,
          'height': np.int32, 'num_frames': np.int32,
          'num_instances': np.uint16,
          'depth_range': tfds.features.Tensor(shape=(2,), dtype=f32),
          'forward_flow_range': tfds.features.Tensor(shape=(2,), dtype=f32),
          'backward_flow_range': tfds.features.Tensor(shape=(2,), dtype=f32),
      },
      'instances': tfds.features.Sequence(feature=instance),
      'camera': {
          'focal_length': f32, 'sensor_width': f32, 'field_of_view': f32,
          'positions': tfds.features.Tensor(shape=(s, 3), dtype=f32),
          'quaternions': tfds.features.Tensor(shape=(s, 4), dtype=f32),
      },
      'events': {'collisions': tfds.features.Sequence({
          'instances': tfds.features.Tensor(shape=(2,), dtype=u16),
          'frame': np.int32, 'force': f32,
          'position': tfds.features.Tensor(shape=(3,), dtype=f32),
          'image_position': tfds.features.Tensor(shape=(2,), dtype=f32),
          'contact_normal': tfds.features.Tensor(shape=(3,), dtype=f32),
      })},
      'video': video(np.uint8),
      'segmentations': tfds.features.Sequence(
          tfds.features.Image(shape=(h, w, 1), dtype=np.uint8), length=s),
      'forward_flow': tfds.features.Sequence(
          tfds.features.Tensor(shape=(h, w, 2), dtype=u16), length=s),
      'backward_flow': tfds.features.Sequence(
          tfds.features.Tensor(shape=(h, w, 2), dtype=u16), length=s),
      'depth': tfds.features.Sequence(
          tfds.features.Image(shape=(h, w, 1), dtype=u16), length=s),
      'normal': video(u16),
      'object_coordinates': video(u16),
  }
  if not flow_depth:  # a download without them (older or trimmed)
    _drop_flow_depth(tree)
  return tfds.features.FeaturesDict(tree)


_FLOW_DEPTH = ('forward_flow', 'backward_flow', 'depth')


def _drop_flow_depth(tree: dict[str, Any]) -> None:
  for key in _FLOW_DEPTH:
    del tree[key]
    del tree['metadata'][f'{key}_range']


_VIDEO_KEYS = ('video', 'normal', 'object_coordinates')
_IMAGE_KEYS = _VIDEO_KEYS + ('segmentations', 'depth')


def png_bytes(image: np.ndarray) -> bytes:
  """PNG of uint8 / uint16 [h, w, c] (c = 1 or 3), as TFDS stores images.

  uint8 goes through PIL; PIL cannot write 16-bit RGB, so uint16 (MOVi's
  depth, normals, object coordinates) is written here: one IDAT of
  unfiltered big-endian rows (PNG spec, colour type 0 or 2).
  """
  import io  # pylint: disable=g-import-not-at-top
  import struct  # pylint: disable=g-import-not-at-top
  import zlib  # pylint: disable=g-import-not-at-top
  if image.dtype == np.uint8:
    buffer = io.BytesIO()
    Image.fromarray(image[..., 0] if image.shape[-1] == 1 else image).save(
        buffer, format='PNG')
    return buffer.getvalue()
  height, width, channels = image.shape
  rows = image.astype('>u2').reshape(height, width * channels).view(np.uint8)
  raw = np.concatenate([np.zeros((height, 1), np.uint8), rows], axis=1)

  def chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack('>I', len(data)) + kind + data
            + struct.pack('>I', zlib.crc32(kind + data) & 0xFFFFFFFF))

  header = struct.pack('>IIBBBBB', width, height, 16,
                       {1: 0, 3: 2}[channels], 0, 0, 0)
  return (b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', header)
          + chunk(b'IDAT', zlib.compress(raw.tobytes()))
          + chunk(b'IEND', b''))


def encode_movi_images(example: dict[str, Any]) -> dict[str, Any]:
  """The example with its frames as PNG bytes (TFDS's Image connector
  encodes arrays with TensorFlow; it passes bytes through)."""
  out = dict(example)
  for key in _IMAGE_KEYS:
    if key in example:
      out[key] = [png_bytes(frame) for frame in example[key]]
  return out


def movi_features_json(features, num_frames: int, height: int, width: int
                       ) -> dict[str, Any]:
  """features.json as TFDS writes it (``MessageToDict(features.to_proto())``)
  with the three videos as ``tfds.features.Video`` nodes."""
  from google.protobuf import json_format  # pylint: disable=g-import-not-at-top
  from tensorflow_datasets.core.proto import feature_pb2  # pylint: disable=g-import-not-at-top
  proto = features.to_proto()
  for key in _VIDEO_KEYS:
    node = proto.features_dict.features[key]
    dtype = node.sequence.feature.image.dtype
    node.Clear()
    node.python_class_name = (
        'tensorflow_datasets.core.features.video_feature.Video')
    node.video.CopyFrom(feature_pb2.VideoFeature(
        shape=feature_pb2.Shape(dimensions=[num_frames, height, width, 3]),
        dtype=dtype, encoding_format='png'))
  return json_format.MessageToDict(proto)


def boxes_from_ids(ids: np.ndarray, k: int):
  """Kubric's compute_bboxes for instance id k: (bboxes, bbox_frames)."""
  boxes, frames = [], []
  height, width = ids.shape[1:3]
  for t, frame in enumerate(ids):
    rows, cols = np.nonzero(frame == k)
    if rows.size:
      boxes.append((rows.min() / height, cols.min() / width,
                    (rows.max() + 1) / height, (cols.max() + 1) / width))
      frames.append(t)
  return boxes, frames


def kubric_uint16(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Kubric's encoding of float flows / depth: (uint16 values, float32
  (min, max) of the video), value = stored / 65535 * (max - min) + min."""
  low, high = float(values.min()), float(values.max())
  high = max(high, low + 1.0)
  stored = np.round((values - low) / (high - low) * 65535).astype(np.uint16)
  return stored, np.asarray([low, high], np.float32)


def movi_scene(rng: np.random.Generator, num_frames: int, height: int,
               width: int, num_instances: int, name: str) -> dict[str, Any]:
  """A MOVi-A-like example: moving coloured squares on grey (``video``,
  ``segmentations``, flows and depth consistent), one instance leaving the
  view, and the other fields random but of MOVi's shapes. Flows: a square
  moving by (dy, dx) per frame has backward flow (-dy, -dx) from frame 1 on
  and forward flow (dy, dx) up to the last frame but one, the background
  none; depth: instance k at 5 - k / 2 (later ones in front), the
  background from 10 (top row) to 6 (bottom row)."""
  s, h, w = num_frames, height, width
  video = np.full((s, h, w, 3), 100, np.uint8)
  ids = np.zeros((s, h, w), np.uint8)
  forward = np.zeros((s, h, w, 2), np.float32)
  backward = np.zeros((s, h, w, 2), np.float32)
  depth = np.broadcast_to(
      (10.0 - 4.0 * np.arange(h) / max(h - 1, 1))[None, :, None, None],
      (s, h, w, 1)).astype(np.float32)
  size = max(2, h // 5)
  start = rng.integers(0, [h - size, w - size], (num_instances, 2))
  step = rng.integers(-1, 2, (num_instances, 2))
  step[-1] = (0, size)  # the last one leaves the frame to the right
  colours = rng.integers(0, 256, (num_instances, 3))
  for t in range(s):
    for k in range(num_instances):  # later instances are in front
      y, x = start[k] + step[k] * t
      y0, x0 = max(y, 0), max(x, 0)
      y1, x1 = min(y + size, h), min(x + size, w)
      if y0 < y1 and x0 < x1:
        video[t, y0:y1, x0:x1] = colours[k]
        ids[t, y0:y1, x0:x1] = k + 1
        depth[t, y0:y1, x0:x1] = 5.0 - k / 2
        forward[t, y0:y1, x0:x1] = step[k] if t + 1 < s else 0
        backward[t, y0:y1, x0:x1] = -step[k] if t else 0
  f32 = np.float32
  instances = []
  for k in range(num_instances):
    boxes, frames = boxes_from_ids(ids, k + 1)
    instances.append({
        'mass': f32(rng.uniform(1, 3)), 'friction': f32(0.4),
        'restitution': f32(0.3),
        'positions': rng.normal(size=(s, 3)).astype(f32),
        'quaternions': rng.normal(size=(s, 4)).astype(f32),
        'velocities': rng.normal(size=(s, 3)).astype(f32),
        'angular_velocities': rng.normal(size=(s, 3)).astype(f32),
        'bboxes_3d': rng.normal(size=(s, 8, 3)).astype(f32),
        'image_positions': rng.uniform(size=(s, 2)).astype(f32),
        'bboxes': [np.asarray(b, f32) for b in boxes],
        'bbox_frames': np.asarray(frames, np.int32),
        'visibility': (ids == k + 1).sum(axis=(1, 2)).astype(np.uint16),
        'shape_label': int(rng.integers(3)), 'size_label': 1,
        'color': (colours[k] / 255).astype(f32), 'color_label': 2,
        'material_label': 0,
    })
  u16 = np.uint16
  forward, forward_range = kubric_uint16(forward)
  backward, backward_range = kubric_uint16(backward)
  depth, depth_range = kubric_uint16(depth)
  example = {
      'metadata': {'video_name': name, 'width': w, 'height': h,
                   'num_frames': s, 'num_instances': num_instances,
                   'depth_range': depth_range,
                   'forward_flow_range': forward_range,
                   'backward_flow_range': backward_range},
      'instances': instances,
      'camera': {'focal_length': f32(35), 'sensor_width': f32(32),
                 'field_of_view': f32(0.85),
                 'positions': np.zeros((s, 3), f32),
                 'quaternions': np.zeros((s, 4), f32)},
      'events': {'collisions': [{
          'instances': np.asarray([0, 65535], u16), 'frame': 1,
          'force': f32(2.5), 'position': np.zeros(3, f32),
          'image_position': np.zeros(2, f32),
          'contact_normal': np.asarray([0, 0, 1], f32)}]},
      'video': video,
      'segmentations': ids[..., None],
      'forward_flow': forward,
      'backward_flow': backward,
      'depth': depth,
      'normal': rng.integers(0, 65535, (s, h, w, 3)).astype(u16),
      'object_coordinates': rng.integers(0, 65535, (s, h, w, 3)).astype(u16),
  }
  return example


_RAGGED = ('bboxes', 'bbox_frames')


def _with_ragged(serialized: bytes, example: dict[str, Any]) -> bytes:
  """Adds instances/bboxes and instances/bbox_frames as TFDS stores ragged
  tensors (sequence rank 2): the values of all instances concatenated, and
  each instance's count."""
  from tensorflow_datasets.proto import tf_example_pb2  # pylint: disable=g-import-not-at-top
  proto = tf_example_pb2.Example.FromString(serialized)
  feature = proto.features.feature
  instances = example['instances']
  boxes = [np.asarray(b, np.float32).reshape(4) for i in instances
           for b in i['bboxes']]
  frames = [int(f) for i in instances for f in i['bbox_frames']]
  feature['instances/bboxes/ragged_flat_values'].float_list.value.extend(
      np.asarray(boxes, np.float32).reshape(-1).tolist())
  feature['instances/bboxes/ragged_row_lengths_0'].int64_list.value.extend(
      [len(i['bboxes']) for i in instances])
  feature['instances/bbox_frames/ragged_flat_values'].int64_list.value.extend(
      frames)
  feature['instances/bbox_frames/ragged_row_lengths_0'].int64_list.value.extend(
      [len(i['bbox_frames']) for i in instances])
  return proto.SerializeToString()


def write_movi(folder: Path, *, name: str = 'movi_a',
               shard_lengths: dict[str, list[int]] | None = None,
               num_frames: int = 8, size: int = 32, seed: int = 0,
               instances: tuple[int, int] = (3, 5), flow_depth: bool = True
               ) -> dict[str, list[dict[str, Any]]]:
  """Writes a MOVi-A-layout TFDS folder; returns its examples per split
  (``flow_depth=False``: without flows and depth, and their ranges).

  ``folder`` gets ``<name>-<split>.tfrecord-XXXXX-of-YYYYY`` shards of
  serialized tf.train.Example protos (TFDS's example serializer, the
  TFRecord framing of tfrecord.py), dataset_info.json (TFDS's
  ``write_metadata``) and features.json (see :func:`movi_features_json`).
  """
  import tensorflow_datasets as tfds  # pylint: disable=g-import-not-at-top
  from tensorflow_datasets.core import example_serializer  # pylint: disable=g-import-not-at-top
  shard_lengths = shard_lengths or {'train': [3, 2], 'validation': [2]}
  folder.mkdir(parents=True, exist_ok=True)
  features = movi_a_features(num_frames, size, size, flow_depth=flow_depth)
  # TFDS 4.9's serializer reaches for TensorFlow on ragged features (the
  # per-instance bboxes / bbox_frames); those two are added by hand, in its
  # layout: <key>/ragged_flat_values + <key>/ragged_row_lengths_0.
  info = features.get_serialized_info()
  info['instances'] = {k: v for k, v in info['instances'].items()
                       if k not in _RAGGED}
  serializer = example_serializer.ExampleSerializer(info)
  rng = np.random.default_rng(seed)
  examples: dict[str, list[dict[str, Any]]] = {}
  split_infos = []
  counter = 0
  for split, lengths in shard_lengths.items():
    examples[split] = []
    num_bytes = 0
    for index, length in enumerate(lengths):
      records = []
      for _ in range(length):
        example = movi_scene(rng, num_frames, size, size,
                             int(rng.integers(instances[0],
                                              instances[1] + 1)),
                             name=str(counter))
        if not flow_depth:
          example['metadata'] = dict(example['metadata'])
          _drop_flow_depth(example)
        counter += 1
        examples[split].append(example)
        encoded = features.encode_example(encode_movi_images(example))
        for key in _RAGGED:
          del encoded['instances'][key]
        records.append(_with_ragged(serializer.serialize_example(encoded),
                                    example))
      path = folder / (f'{name}-{split}.tfrecord-{index:05d}-of-'
                       f'{len(lengths):05d}')
      write_tfrecords(path, records)
      num_bytes += path.stat().st_size
    split_infos.append(tfds.core.SplitInfo(
        name=split, shard_lengths=list(lengths), num_bytes=num_bytes,
        filename_template=tfds.core.ShardedFileTemplate(
            data_dir=str(folder), dataset_name=name, split=split,
            filetype_suffix='tfrecord')))
  tfds.folder_dataset.write_metadata(
      data_dir=str(folder), features=features, split_infos=split_infos,
      version='1.0.0', check_data=False,
      filename_template=tfds.core.ShardedFileTemplate(
          data_dir=str(folder), dataset_name=name,
          filetype_suffix='tfrecord'))
  (folder / 'features.json').write_text(json.dumps(
      movi_features_json(features, num_frames, size, size), indent=4,
      sort_keys=True))
  return examples


def data_section(**fields):
  """A run's `config.data` (every field at its default) with `fields` set,
  as a config file writes it."""
  from slotformer_jax.config.defaults import base_config  # pylint: disable=g-import-not-at-top
  data = base_config().data
  for key, value in fields.items():
    data[key] = value
  return data


def write_clevrer_video(root: Path, split: str, index: int, *,
                        num_frames: int = 8, size: int = 16,
                        annotated: bool = True) -> None:
  """One CLEVRER video in the published layout (a grey level per video,
  no objects drawn), with a one-object annotation when ``annotated``; no
  derender proposals (convert with --masks=ignore)."""
  level = index // 1000 * 1000
  folder = f'{level:05d}-{level + 1000:05d}'
  frames = np.full((num_frames, size, size, 3), 40 + index % 200, np.uint8)
  write_mp4(root / 'videos' / split / f'video_{folder}' /
            f'video_{index:05d}.mp4', frames)
  if annotated:
    write_json(
        root / 'annotations' / split / f'annotation_{folder}' /
        f'annotation_{index:05d}.json',
        {'scene_index': index, 'video_filename': f'video_{index:05d}.mp4',
         'object_property': [{'object_id': 0, 'color': 'red',
                              'material': 'metal', 'shape': 'cube'}],
         'motion_trajectory': [
             {'frame_id': t, 'objects': [{'object_id': 0,
                                          'inside_camera_view': True}]}
             for t in range(num_frames)],
         'collision': []})
