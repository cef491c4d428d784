"""Runs a reader of files from elsewhere on seeded, structure-aware mutations
of a valid input, in this (child) process, each case under a time bound, so
that a hang, a crash or an unexpected exception fails a test instead of
killing pytest.

  python tests/reader_fuzz.py READER SEED CASES FOLDER [SECONDS]

READER is one of `READERS`: movi_metadata (dataset_info.json and
features.json of a MOVi download), movi_records (the Example protos and PNG
frames of its records), questions and vocabulary (CLEVRER's question and
vocabulary files), phyre (meta.json, rollouts.jsonl, the rollout strips),
physion_lists (Physion's official split lists), metrics (eval/metrics.json
as the explorer page reads it), digests (a checkpoint step's sha256.json).
One JSON line per case:

  {"case": 3, "what": "type features.json .../dtype -> 'x'",
   "outcome": "read" | "refused", "type": ..., "message": ...,
   "seconds": 0.01, "problem": "..."}   # "problem" only when there is one

A case passes when the reader returns a well-formed result or refuses with
one of the exceptions its command turns into an `error:` line, whose
message holds no raw control character (`errors.printable`); it fails when
it raises anything else, takes more than SECONDS (default 5), writes a file,
or returns something malformed. The mutations know the structure: JSON
trees (a node deleted, retyped, renamed, nested 10 to 100,000 deep,
duplicated 1,000 times, hostile strings: escape sequences, '../..',
absolute paths, NUL, 100,000 characters), protobuf features (dropped,
retyped, emptied, repeated, huge counts, non-UTF-8 text), PNG headers that
claim other sizes (up to 10^6 x 10^6), truncations and byte flips; every
integer field set to the edges of int32 / int64 and past them (2^31,
2^32 + k, 2^63 - 1, -2^63, 10^400) and to floats where an int is due, and
one key repeated a thousand times (JSON text keys cannot be given one hash
value: Python randomizes str hashes; the .pth reader's int keys can, see
tests/official/test_pth_reader_hostile.py).
"""

from __future__ import annotations

import copy
import io
import json
import os
import random
import shutil
import signal
import struct
import sys
import time
import traceback
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

AS_LIMIT = 8 << 30  # address space of the child (a backstop)


class Overtime(BaseException):
  """A case ran past its time bound (raised by SIGALRM)."""


# ----------------------------------------------------------------------------
# JSON trees
# ----------------------------------------------------------------------------

HOSTILE_STRINGS = (
    '', 'x', '../../escape', '..', '/etc/passwd', 'a/b', 'a\\b', 'a\x00b',
    '\x1b[2J\x1b]0;owned\x07', 'line\nerror: forged', '\u202eevil', 'é' * 50,
    'x' * 100_000, '24', '-1', 'train', 'descriptive', 'correct', 'PAD')
HOSTILE_VALUES = (None, True, False, 0, 1, -1, 3, 2**31, 2**63, 10**30,
                  1.5, -0.0, 1e308, float('nan'), [], {}, [1, 2, 3],
                  {'a': 1}, [[[]]])
# Every number field is also set to these (`int` mutations): the edges of
# int32 / int64 and past them (2**32 + k wraps to k in int32), an int too
# large for a float, and floats where an int is due.
INTEGER_EXTREMES = (2**31 - 1, 2**31, 2**32 + 5, 2**40, -2**32 + 3,
                    2**63 - 1, 2**63, 2**64 + 1, -2**63, -2**63 - 1,
                    10**400, -10**400, 2**16 + 2, 3.0, 0.5, 1e400,
                    float('nan'))
_DEEP = '"__deep__"'
_RAW = '"__raw__"'


def _paths(tree: Any, prefix: tuple = ()) -> list[tuple]:
  """Every node's path (keys and indices) in `tree`, the root included."""
  out = [prefix]
  if isinstance(tree, dict):
    for key, value in tree.items():
      out += _paths(value, prefix + (key,))
  elif isinstance(tree, list):
    for index, value in enumerate(tree[:50]):
      out += _paths(value, prefix + (index,))
  return out


def _get(tree: Any, path: tuple) -> Any:
  for part in path:
    tree = tree[part]
  return tree


def _set(tree: Any, path: tuple, value: Any) -> Any:
  if not path:
    return value
  _get(tree, path[:-1])[path[-1]] = value
  return tree


def mutate_json(rng: random.Random, tree: Any) -> tuple[str, str]:
  """(what was done, the JSON text) of one structure-aware mutation."""
  tree = copy.deepcopy(tree)
  path = rng.choice(_paths(tree))
  node = _get(tree, path)
  where = '/'.join(map(str, path))[-80:] or '<top>'
  # Every number field (ints, and floats that may receive an int too large
  # for a float).
  integers = [p for p in _paths(tree) if type(_get(tree, p)) in (int, float)]
  kind = rng.choice(('delete', 'type', 'string', 'number', 'deep', 'wrap',
                     'duplicate', 'rename', 'swap', 'int', 'int', 'keys'))
  if kind == 'int' and integers:
    path = rng.choice(integers)
    where = '/'.join(map(str, path))[-80:] or '<top>'
    value = rng.choice(INTEGER_EXTREMES)
    shown = (f'{value!r}' if not isinstance(value, int)
             or value.bit_length() < 100 else f'<{value.bit_length()}-bit>')
    return f'int {where} -> {shown}', json.dumps(_set(tree, path, value))
  if kind == 'keys' and isinstance(node, dict) and node:
    # One key many times (JSON allows it; the last wins), with every value
    # of the node in turn: text keys cannot be made to share a hash value
    # (Python randomizes str hashes), repeated ones are their collision.
    key = rng.choice(sorted(node))
    values = list(node.values()) * (1000 // len(node) + 1)
    raw = '{' + ', '.join(f'{json.dumps(key)}: {json.dumps(v)}'
                          for v in values[:1000] + [node[key]]) + '}'
    text = json.dumps(_set(tree, path, '__raw__'))
    return f'keys {where} {key[:20]!r} x1001', text.replace(_RAW, raw, 1)
  if kind == 'delete' and path:
    parent = _get(tree, path[:-1])
    del parent[path[-1]]
    return f'delete {where}', json.dumps(tree)
  if kind == 'string':
    value = rng.choice(HOSTILE_STRINGS)
    return (f'string {where} -> {value[:20]!r}',
            json.dumps(_set(tree, path, value)))
  if kind == 'number':
    value = rng.choice((0, -1, 1, 2**31 - 1, 2**31, 2**63, 10**20, -10**20,
                        10**400, 1e6, 0.5, '7', '-3', '1' * 30))
    return f'number {where} -> {value!r}', json.dumps(_set(tree, path,
                                                            value))
  if kind == 'deep':
    depth = rng.choice((10, 40, 1000, 100_000))
    text = json.dumps(_set(tree, path, '__deep__'))
    return (f'deep {where} x{depth}',
            text.replace(_DEEP, '[' * depth + ']' * depth, 1))
  if kind == 'wrap':
    value = rng.choice(([node], {'x': node}))
    return f'wrap {where}', json.dumps(_set(tree, path, value))
  if kind == 'duplicate' and isinstance(node, list) and node:
    return (f'duplicate {where} x1000',
            json.dumps(_set(tree, path, node * (1000 // len(node) + 1))))
  if kind == 'rename' and path and isinstance(path[-1], str):
    parent = _get(tree, path[:-1])
    key = path[-1]
    new = key[:-1] if len(key) > 1 else key + key
    parent[new] = parent.pop(key)
    return f'rename {where} -> {new!r}', json.dumps(tree)
  if kind == 'swap' and isinstance(node, (dict, list)):
    value = (list(node.values()) if isinstance(node, dict)
             else {str(i): v for i, v in enumerate(node)})
    return f'swap {where}', json.dumps(_set(tree, path, value))
  value = rng.choice(HOSTILE_VALUES)
  return (f'type {where} -> {value!r}'[:120],
          json.dumps(_set(tree, path, value)))


def mutate_bytes(rng: random.Random, data: bytes) -> tuple[str, bytes]:
  """Truncation, bit flips, or a random slice doubled."""
  kind = rng.choice(('truncate', 'flip', 'double'))
  if kind == 'truncate':
    end = rng.randrange(len(data))
    return f'truncate at {end}', data[:end]
  if kind == 'flip':
    data = bytearray(data)
    for _ in range(rng.choice((1, 4, 32))):
      data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    return 'flip bits', bytes(data)
  start = rng.randrange(len(data))
  end = min(len(data), start + rng.randrange(1, 256))
  return 'double a slice', data[:end] + data[start:]


def png_claiming(width: int, height: int, data: bytes) -> bytes:
  """`data` (a PNG) with its IHDR saying width x height (CRC fixed)."""
  ihdr = bytearray(data[16:29])
  ihdr[0:8] = struct.pack('>II', width, height)
  crc = struct.pack('>I', zlib.crc32(b'IHDR' + bytes(ihdr)) & 0xFFFFFFFF)
  return data[:16] + bytes(ihdr) + crc + data[33:]


def mutate_png(rng: random.Random, data: bytes) -> tuple[str, bytes]:
  if rng.random() < 0.5:
    width, height = rng.choice(((10**6, 10**6), (12000, 12000), (1, 1),
                                (64, 64), (0, 5), (2**31 - 1, 1)))
    return f'png header {width}x{height}', png_claiming(width, height, data)
  what, mutated = mutate_bytes(rng, data)
  return f'png {what}', mutated


# ----------------------------------------------------------------------------
# The readers: each builds its valid input once, mutates it per case and
# reads it, returning a check of the result (None: well formed).
# ----------------------------------------------------------------------------


class Traceback_(Exception):
  """A video's converter raised what the writer does not turn into one
  line (only ConversionError and SkipVideo are): a traceback for the user."""


def _convert(convert: Callable[[], Any], allowed: tuple[type, ...]) -> Any:
  try:
    return convert()
  except allowed:
    raise
  except Exception as error:  # pylint: disable=broad-except
    raise Traceback_(f'{type(error).__name__}: {error}') from error


class Reader:
  """A reader under test. `refusals`: the exceptions its command prints as
  one `error:` line (anything else fails the case)."""

  refusals: tuple[type, ...] = ()

  def __init__(self, folder: Path):
    self.folder = folder

  def mutate(self, rng: random.Random, case: Path) -> str:
    raise NotImplementedError

  def read(self, case: Path) -> str | None:
    raise NotImplementedError


class MoviMetadata(Reader):
  """dataset_info.json and features.json of a MOVi download, then one
  record converted with what they say."""

  def __init__(self, folder: Path):
    super().__init__(folder)
    import dataset_fixtures as fx  # pylint: disable=g-import-not-at-top
    from slotformer_jax.data import media  # pylint: disable=g-import-not-at-top
    from slotformer_jax.datasets import movi  # pylint: disable=g-import-not-at-top
    from slotformer_jax.data import tfrecord  # pylint: disable=g-import-not-at-top
    from slotformer_jax.data.write import convert as writer  # pylint: disable=g-import-not-at-top
    self.movi, self.writer, self.media = movi, writer, media
    self.base = folder / 'base'
    fx.write_movi(self.base, shard_lengths={'train': [1]}, num_frames=3,
                  size=16, seed=0, instances=(1, 2))
    self.refusals = (FileNotFoundError, ValueError, writer.ConversionError,
                     tfrecord.TFRecordError)
    self.files = {name: json.loads((self.base / name).read_text())
                  for name in ('dataset_info.json', 'features.json')}

  def mutate(self, rng, case):
    shutil.copytree(self.base, case)
    name = rng.choice(sorted(self.files))
    what, text = mutate_json(rng, self.files[name])
    (case / name).write_text(text)
    return f'{name}: {what}'

  def read(self, case):
    movi = self.movi
    movi.read_source.cache_clear()
    options = movi.Options(resolution=(16, 16), max_objects=4)
    jobs = movi.discover(case, 'train', options)
    spec = movi.DATASET.spec(options, case)
    spec.dataset_dir(case / 'data')  # the output folder stays inside
    if not jobs:  # a split listed without shards: nothing to convert
      return None
    return _check_movi_item(_convert(
        lambda: spec.convert_fn(jobs[0]),
        (self.writer.ConversionError, self.media.SkipVideo)))


def _check_movi_item(item: dict[str, Any]) -> str | None:
  video = item['video']
  if video.dtype != np.uint8 or video.ndim != 4 or video.shape[-1] != 3:
    return f'video {video.dtype} {video.shape}'
  if item['segmentations'].shape != video.shape[:3]:
    return f'segmentations {item["segmentations"].shape}'
  if not isinstance(item['video_name'], str):
    return f'video_name {type(item["video_name"]).__name__}'
  # Flows and depth: uint16 frames of the video's size, a finite ordered
  # range each (what the reader decodes them with).
  for name, channels in (('forward_flow', 2), ('backward_flow', 2),
                         ('depth', 1)):
    if name not in item:
      return f'no {name}'
    values, value_range = item[name], item[f'{name}_range']
    if values.dtype != np.uint16 or values.shape != video.shape[:3] + (
        channels,):
      return f'{name} {values.dtype} {values.shape}'
    if (value_range.dtype != np.float32 or value_range.shape != (2,)
        or not np.all(np.isfinite(value_range))
        or value_range[0] > value_range[1]):
      return f'{name}_range {value_range!r}'
  return None


class MoviRecords(MoviMetadata):
  """The records of a MOVi shard: its Example proto's features (dropped,
  retyped, emptied, repeated, huge counts, non-UTF-8 text) and its PNG
  frames (headers that claim other sizes, damage), framed with valid
  checksums, or the framing itself damaged."""

  def __init__(self, folder: Path):
    super().__init__(folder)
    import dataset_fixtures  # pylint: disable=g-import-not-at-top
    from slotformer_jax.data import tfrecord  # pylint: disable=g-import-not-at-top
    from tensorflow_datasets.proto import tf_example_pb2  # pylint: disable=g-import-not-at-top
    self.tfrecord, self.pb2 = tfrecord, tf_example_pb2
    self.write_tfrecords = dataset_fixtures.write_tfrecords
    self.shard = next(self.base.glob('*-train.tfrecord-*'))
    self.record = next(tfrecord.iter_records(self.shard))

  def mutate(self, rng, case):
    shutil.copytree(self.base, case)
    shard = case / self.shard.name
    if rng.random() < 0.1:
      what, data = mutate_bytes(rng, self.shard.read_bytes())
      shard.write_bytes(data)
      return f'shard {what}'
    example = self.pb2.Example.FromString(self.record)
    features = example.features.feature
    key = rng.choice(sorted(features))
    feature = features[key]
    kind = rng.choice(('drop', 'retype', 'empty', 'repeat', 'value',
                       'png', 'png', 'text', 'flow'))
    what = f'{kind} {key}'
    if kind == 'drop':
      del features[key]
    elif kind == 'retype':
      values = rng.choice(([1, 2, 3], [b'x'], [0.5]))
      feature.Clear()
      field = {int: feature.int64_list, bytes: feature.bytes_list,
               float: feature.float_list}[type(values[0])]
      field.value.extend(values)
    elif kind == 'empty':
      feature.Clear()
    elif kind == 'repeat':
      for field in (feature.int64_list, feature.float_list,
                    feature.bytes_list):
        field.value.extend(list(field.value) * rng.choice((1, 10)))
    elif kind == 'value':
      if feature.int64_list.value:
        feature.int64_list.value[0] = rng.choice(
            (-1, 0, 10**9, 2**62, -2**62, 255, 256, 2**31 - 1, 2**31,
             2**32 + 5, 2**40, -2**32 + 3, 2**16 + 2, 2**63 - 1, -2**63))
      elif feature.float_list.value:
        feature.float_list.value[0] = rng.choice((float('nan'), 1e38,
                                                  -1e38))
      elif feature.bytes_list.value:
        feature.bytes_list.value[0] = b''
    elif kind == 'flow':  # flows, depth and their ranges
      key = rng.choice(('forward_flow', 'backward_flow', 'depth',
                        'metadata/forward_flow_range',
                        'metadata/backward_flow_range',
                        'metadata/depth_range'))
      feature = features[key]
      if key.endswith('_range'):
        low, high = list(feature.float_list.value)
        values = rng.choice(([high, low - 1], [float('nan'), high],
                             [low, float('inf')], [-1e30, 1e30], [low],
                             [low, high, high], [-1.0, high]))
        del feature.float_list.value[:]
        feature.float_list.value.extend(values)
        what = f'flow {key} {values}'
      elif key == 'depth':  # 16-bit PNGs: an 8-bit one, other sizes, damage
        values = feature.bytes_list.value
        index = rng.randrange(len(values))
        if rng.random() < 0.3:
          import dataset_fixtures  # pylint: disable=g-import-not-at-top
          values[index] = dataset_fixtures.png_bytes(
              np.zeros((16, 16, 1), np.uint8))
          what = f'flow depth[{index}] 8-bit'
        else:
          mutation, values[index] = mutate_png(rng, values[index])
          what = f'flow depth[{index}] {mutation}'
      else:
        values = feature.int64_list.value
        edit = rng.choice(('short', 'long', 'high', 'negative'))
        if edit == 'short':
          del values[-rng.choice((1, 2, 16 * 16)):]
        elif edit == 'long':
          values.extend([0] * rng.choice((1, 2, 16 * 16)))
        else:
          values[rng.randrange(len(values))] = (
              rng.choice((65536, 2**32 + 5, 2**63 - 1)) if edit == 'high'
              else rng.choice((-1, -2**63)))
        what = f'flow {key} {edit}'
    elif kind == 'png':
      frames = [k for k in features if k in ('video', 'segmentations')]
      key = rng.choice(frames)
      values = features[key].bytes_list.value
      index = rng.randrange(len(values))
      mutation, values[index] = mutate_png(rng, values[index])
      what = f'{key}[{index}] {mutation}'
    else:  # text
      name = features['metadata/video_name'].bytes_list.value
      name[0] = rng.choice((b'\xff\xfe\xfd', b'\x1b[2J', b'../../x',
                            b'a' * 100_000))
      what = f'video_name {name[0][:12]!r}'
    self.write_tfrecords(shard, [example.SerializeToString()])
    return what


class Questions(Reader):
  """CLEVRER's questions/train.json, encoded with a vocabulary."""

  def __init__(self, folder: Path):
    super().__init__(folder)
    from slotformer_jax.data import vqa  # pylint: disable=g-import-not-at-top
    self.vqa = vqa
    # (getattr: the same fuzz runs on versions before these checks.)
    self.refusals = (getattr(vqa, 'QuestionFileError', vqa.ConfigError),)
    self.scenes = [
        {'scene_index': 0, 'video_filename': 'video_00000.mp4',
         'questions': [
             {'question_id': 0, 'question_type': 'descriptive',
              'question': 'what color is the cube?', 'answer': 'red'},
             {'question_id': 1, 'question_type': 'predictive',
              'question': 'what will happen next?',
              'choices': [{'choice_id': 0, 'choice': 'the cube collides',
                           'answer': 'correct'},
                          {'choice_id': 1, 'choice': 'the sphere enters',
                           'answer': 'wrong'}]}]},
        {'scene_index': 1, 'video_filename': 'video_00001.mp4',
         'questions': [
             {'question_id': 0, 'question_type': 'counterfactual',
              'question': 'what will happen if the cube is removed?',
              'choices': [{'choice_id': 0, 'choice': 'the sphere collides',
                           'answer': 'wrong'}]}]}]
    self.vocab = vqa.Vocabulary.from_scenes(self.scenes)

  def mutate(self, rng, case):
    (case / 'questions').mkdir(parents=True)
    what, text = mutate_json(rng, self.scenes)
    (case / 'questions' / 'train.json').write_text(text)
    return what

  def read(self, case):
    vqa = self.vqa
    scenes = vqa.read_clevrer_questions(case, 'train')
    vqa.Vocabulary.from_scenes(scenes)
    encoded = vqa.encode_scenes(scenes, self.vocab, 8, 6)
    for question in encoded:
      if question.tokens.dtype != np.int32 or question.tokens.ndim != 2:
        return f'tokens {question.tokens.dtype} {question.tokens.shape}'
    return None


class Vocabulary(Questions):
  """A vocabulary file (as the official CLEVRER_vocab.json)."""

  def mutate(self, rng, case):
    case.mkdir()
    tree = {'q_vocab': self.vocab.questions, 'a_vocab': self.vocab.answers}
    if rng.random() < 0.1:
      (case / 'vocab.json').write_bytes(b'{"q_vocab": {"\xff": 0}}')
      return 'not UTF-8'
    what, text = mutate_json(rng, tree)
    (case / 'vocab.json').write_text(text)
    return what

  def read(self, case):
    vocab = self.vqa.Vocabulary.load(case / 'vocab.json')
    for table in (vocab.questions, vocab.answers):
      if sorted(table.values()) != list(range(len(table))):
        return f'ids {sorted(table.values())[:10]}'
    return None


class Phyre(Reader):
  """A PHYRE rollout folder: meta.json, rollouts.jsonl, frame strips."""

  def __init__(self, folder: Path):
    super().__init__(folder)
    import dataset_fixtures as fx  # pylint: disable=g-import-not-at-top
    from slotformer_jax.data import media  # pylint: disable=g-import-not-at-top
    from slotformer_jax.datasets import phyre  # pylint: disable=g-import-not-at-top
    self.phyre, self.media = phyre, media
    self.refusals = (FileNotFoundError, ValueError)
    self.meta = {'format': phyre.FORMAT,
                 'format_version': phyre.FORMAT_VERSION, 'tier': 'ball',
                 'eval_setup': 'ball_within_template', 'fold': 0, 'fps': 1,
                 'max_frames': 4, 'background': 'black',
                 'frame_size': [8, 8], 'splits': ['train']}
    self.lines = [{'id': f'00000{i}', 'task': '00002:013',
                   'action': [0.1, 0.2, 0.3], 'success': bool(i % 2),
                   'num_frames': 3} for i in range(2)]
    buffer = io.BytesIO()
    from PIL import Image  # pylint: disable=g-import-not-at-top
    Image.fromarray(fx.noise_video(1, 24, 8)[0]).save(buffer, format='PNG')
    self.strip = buffer.getvalue()

  def mutate(self, rng, case):
    frames = case / 'train' / 'frames'
    frames.mkdir(parents=True)
    meta, lines, strips = (json.dumps(self.meta),
                           [json.dumps(line) for line in self.lines],
                           {line['id']: self.strip for line in self.lines})
    target = rng.choice(('meta', 'line', 'line', 'png'))
    if target == 'meta':
      what, meta = mutate_json(rng, self.meta)
    elif target == 'line':
      index = rng.randrange(len(lines))
      what, lines[index] = mutate_json(rng, self.lines[index])
      what = f'line {index}: {what}'
    else:
      key = rng.choice(sorted(strips))
      what, strips[key] = mutate_png(rng, strips[key])
    (case / self.phyre.META_FILE).write_text(meta)
    (case / 'train' / self.phyre.INDEX_FILE).write_text(
        '\n'.join(line.replace('\n', ' ') for line in lines) + '\n')
    for key, data in strips.items():
      (frames / f'{key}.png').write_bytes(data)
    return f'{target}: {what}'

  def read(self, case):
    phyre = self.phyre
    options = phyre.Options(resolution=(8, 8), num_frames=4)
    phyre.DATASET.spec(options, case).dataset_dir(case / 'data')
    for job in phyre.discover(case, 'train', options):
      try:
        item = _convert(lambda job=job: phyre.convert_rollout(job, options),
                        (self.media.SkipVideo,))
      except self.media.SkipVideo as skip:
        if not printable_ok(skip.message):
          return f'skip message not printable: {skip.message[:80]!r}'
        continue
      if item['video'].shape != (4, 8, 8, 3):
        return f'video {item["video"].shape}'
    return None


class PhysionLists(Reader):
  """Physion's official split lists ({scenario: [relative mp4 path]})."""

  def __init__(self, folder: Path):
    super().__init__(folder)
    from slotformer_jax.datasets import physion  # pylint: disable=g-import-not-at-top
    self.physion = physion
    self.refusals = (FileNotFoundError, ValueError)
    self.listed = {'Dominoes': ['PhysionTrainMP4s/Dominoes_training_MP4s/'
                                'a.mp4'],
                   'Support': ['PhysionTrainMP4s/Support_training_MP4s/'
                               'b.mp4', 'PhysionTrainMP4s/x/c.mp4']}

  def mutate(self, rng, case):
    case.mkdir()
    what, text = mutate_json(rng, self.listed)
    (case / 'training_train.json').write_text(text)
    return what

  def read(self, case):
    physion = self.physion
    options = physion.Options(split_files=str(case))
    files = physion._listed_files(case / 'source', 'train', options)  # pylint: disable=protected-access
    root = os.path.abspath(case / 'source')
    for _, path in files:
      if not os.path.abspath(path).startswith(root + os.sep):
        return f'{path} is outside --source'
    return None


class NoCurves(Exception):
  """run_curves left the run's curves out (its own way of refusing)."""


class Metrics(Reader):
  """eval/metrics.json of a (shared) run folder, as the explorer reads it:
  it never raises; a file it cannot use leaves the curves out."""

  refusals = (NoCurves,)

  def __init__(self, folder: Path):
    super().__init__(folder)
    from slotformer_jax.evaluation import metrics_file  # pylint: disable=g-import-not-at-top
    self.metrics_file = metrics_file
    self.identity = {'savi': {'run_id': 'x', 'step': 3}}
    self.metrics = {
        'identity': self.identity,
        'protocol': {'num_videos': 2, 'split': 'test'},
        'rollout': {'slotformer': {'psnr': {'mean': 20.0,
                                            'per_step': [21.0, None, 19.5]},
                                   'ari': {'mean': 0.5}},
                    'copy_last': {'psnr': {'mean': 19.0,
                                           'per_step': [20.0, 18.0, 17.0]}}}}

  def mutate(self, rng, case):
    (case / 'eval').mkdir(parents=True)
    what, text = mutate_json(rng, self.metrics)
    (case / 'eval' / 'metrics.json').write_text(text)
    return what

  def read(self, case):
    curves, note = self.metrics_file.read_curves(
        str(case / 'eval' / 'metrics.json'), self.identity,
        {'slotformer': 'SlotFormer', 'copy_last': 'copy-last'})
    if not isinstance(note, str):
      return f'note {type(note).__name__}'
    if curves is None:
      raise NoCurves(note)  # the page goes without curves
    for metric, series in curves.items():
      if not isinstance(metric, str) or not isinstance(series, dict):
        return f'curves {type(metric).__name__}'
      for label, values in series.items():
        if not isinstance(label, str) or not all(
            v is None or isinstance(v, float) for v in values):
          return f'curve {label!r}'
    return None


class Damaged(Exception):
  """damage_of gave its verdict: the step is damaged (its way of refusing)."""


class Digests(Reader):
  """`<step>/sha256.json` of a checkpoint step (a shared run folder, a disk
  fault): `damage_of` must name the damage in one line, never raise or
  block, and call a step intact only when every file of it is listed with
  its true size and hash. Besides the JSON mutations: the digest or a
  listed file replaced by a FIFO, a link (to /dev/zero, out of the step) or
  a folder."""

  refusals = (Damaged,)

  def __init__(self, folder: Path):
    super().__init__(folder)
    from slotformer_jax.runtime import checkpoint_digest  # pylint: disable=g-import-not-at-top
    self.digest_lib = checkpoint_digest
    self.base = folder / 'base'
    data = random.Random(0)
    for name in ('_CHECKPOINT_METADATA', 'default/_METADATA',
                 'default/ocdbt.process_0/d/0a1b'):
      path = self.base / name
      path.parent.mkdir(parents=True, exist_ok=True)
      path.write_bytes(bytes(data.randrange(256) for _ in range(64)))
    checkpoint_digest.write_digest(str(self.base))
    self.digest = json.loads(
        (self.base / checkpoint_digest.DIGEST_FILE).read_text())

  def mutate(self, rng, case):
    shutil.copytree(self.base, case)
    digest = case / self.digest_lib.DIGEST_FILE
    if rng.random() < 0.15:
      listed = case / rng.choice(sorted(self.digest['files']))
      target = rng.choice([digest, listed])
      kind = rng.choice(['fifo', 'zero', 'outside', 'folder'])
      os.remove(target)
      if kind == 'fifo':
        os.mkfifo(target)
      elif kind == 'zero':
        os.symlink('/dev/zero', target)
      elif kind == 'outside':
        os.symlink(self.base / self.digest_lib.DIGEST_FILE, target)
      else:
        target.mkdir()
      return f'{target.name}: special {kind}'
    what, text = mutate_json(rng, self.digest)
    digest.write_text(text)
    return what

  def read(self, case):
    reason = self.digest_lib.damage_of(str(case), required=True)
    if reason is not None:
      if not isinstance(reason, str) or '\n' in reason:
        return f'reason {reason!r}'
      raise Damaged(reason)
    # Intact: then it lists every file with its true size and hash.
    digest = json.loads((case / self.digest_lib.DIGEST_FILE).read_text())
    if digest.get('files') != self.digest['files']:
      return 'called intact, but it lists other files, sizes or hashes'
    return None


READERS: dict[str, type[Reader]] = {
    'movi_metadata': MoviMetadata, 'movi_records': MoviRecords,
    'questions': Questions, 'vocabulary': Vocabulary, 'phyre': Phyre,
    'physion_lists': PhysionLists, 'metrics': Metrics, 'digests': Digests}


# ----------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------


def printable_ok(message: str) -> bool:
  """No character a terminal would act on, but line breaks (written apart
  from `errors.printable`, which it checks)."""
  return all(c.isprintable() or c == '\n' for c in message)


def _listing(folder: Path) -> set[str]:
  return {os.path.relpath(os.path.join(d, f), folder)
          for d, _, names in os.walk(folder) for f in names}


def _on_alarm(signum, frame):
  del signum, frame
  raise Overtime()


def run_case(reader: Reader, rng: random.Random, case: Path,
             seconds: float) -> dict[str, Any]:
  what = reader.mutate(rng, case)
  before = _listing(reader.folder)
  verdict: dict[str, Any] = {'what': what[:200]}
  started = time.perf_counter()
  signal.setitimer(signal.ITIMER_REAL, seconds)
  try:
    problem = reader.read(case)
    verdict['outcome'] = 'read'
    if problem:
      verdict['problem'] = f'read a malformed result: {problem}'
  except Overtime:
    verdict['outcome'] = 'overtime'
    verdict['problem'] = f'took more than {seconds} s'
  except BaseException as error:  # pylint: disable=broad-except
    signal.setitimer(signal.ITIMER_REAL, 0)
    message = str(error)
    verdict.update(outcome='refused', type=type(error).__name__,
                   message=message[:300])
    if not isinstance(error, reader.refusals):
      verdict['problem'] = (f'raised {type(error).__name__}: '
                            + ''.join(traceback.format_exception(error))[-800:])
    elif not printable_ok(message):
      verdict['problem'] = 'the message holds a raw control character'
  finally:
    signal.setitimer(signal.ITIMER_REAL, 0)
  verdict['seconds'] = round(time.perf_counter() - started, 3)
  written = _listing(reader.folder) - before
  if written:
    verdict['problem'] = f'wrote {sorted(written)[:3]}'
  shutil.rmtree(case, ignore_errors=True)
  return verdict


def fuzz(name: str, seed: int, cases: int, folder: Path,
         seconds: float) -> None:
  signal.signal(signal.SIGALRM, _on_alarm)
  reader = READERS[name](folder)
  rng = random.Random(seed)
  for case in range(cases):
    verdict = run_case(reader, rng, folder / f'case{case}', seconds)
    print(json.dumps({'case': case, **verdict}), flush=True)


def _limit_memory() -> None:
  try:
    import resource  # pylint: disable=g-import-not-at-top
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))
  except (ImportError, ValueError, OSError):
    pass


def main(argv: list[str]) -> None:
  if len(argv) < 5 or argv[1] not in READERS:
    raise SystemExit(__doc__)
  _limit_memory()
  fuzz(argv[1], int(argv[2]), int(argv[3]), Path(argv[4]),
       float(argv[5]) if len(argv) > 5 else 5.0)


if __name__ == '__main__':
  main(sys.argv)
