r"""Worst-case time of each reader of files from elsewhere, at its limits.

  python benchmarks/reader_limits.py                      # every reader
  python benchmarks/reader_limits.py --readers=pth,metrics --fraction=0.25

Each reader gets one input at its limit (file size, count: the constants
named below), filled with what costs it the most per byte (the smallest
items its format allows), and reads it in a child process of its own; the
script prints the seconds and the child's peak resident memory. With
`--fraction=f` the inputs are f times their limit: the readers are linear
in the input (the point of their limits), so the times scale by 1 / f.

  pth             official/pth_reader.py: a pickle of Limits.max_pickle_ops
                  opcodes (a dict of 500,000 int keys) in a file large
                  enough for the byte budget to allow them (a 64 MiB
                  storage); and the same dict with keys that share one hash
                  value (multiples of 2**61 - 1), which is refused
  pth_collide_N   N colliding keys only (no padding): before issue 53 this
                  took quadratic time
  movi_metadata   dataset_info.json of 16 MiB (movi._MAX_JSON_BYTES):
                  splits of _MAX_SHARDS shard lengths; features.json padded
                  to 16 MiB
  movi_record     one MOVi record of 24 frames of MAX_SOURCE_SIDE^2 (its
                  time is linear in the frames, up to MAX_SOURCE_FRAMES)
  questions       CLEVRER question files of MAX_QUESTION_FILE_BYTES:
                  scenes of one-word descriptive questions, scenes without
                  questions, and `[{},{},...]`
  vocabulary      a vocabulary of MAX_VOCABULARY words (64 MiB at most)
  phyre_index     a PHYRE rollouts.jsonl of MAX_INDEX_BYTES, one short line
                  per rollout
  physion_lists   a Physion split list of 256 MiB of short paths
  physion_labels  a Physion label CSV of MAX_LABEL_FILE_BYTES
  metrics         eval/metrics.json of 64 MiB: MAX_CURVES curves of
                  MAX_STEPS steps (the explorer's reader)

Memory grows with the input too: at the limit the 1 GiB and 256 MiB JSON
readers need several GiB (printed); pass --fraction on a small machine.
"""

from __future__ import annotations

import argparse
import io
import json
import resource
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path


_MIB = 1 << 20
P = 2**61 - 1  # ints that differ by a multiple of it hash alike


# ----------------------------------------------------------------------------
# Inputs: write(folder, fraction) -> what the child reads.
# ----------------------------------------------------------------------------


def _pickle_dict(keys, values_op=b'K\x00') -> bytes:
  """Protocol-2 pickle of {'state_dict': {}, 'side': {key: 0, ...}}."""
  out = io.BytesIO()
  out.write(b'\x80\x02}(X\n\x00\x00\x00state_dict}X\x04\x00\x00\x00side}(')
  for key in keys:
    if 0 <= key < 256:
      out.write(b'K' + bytes([key]))
    elif 0 <= key < 2**31:
      out.write(b'J' + key.to_bytes(4, 'little'))
    else:
      data = key.to_bytes((key.bit_length() + 8) // 8, 'little', signed=True)
      out.write(b'\x8a' + bytes([len(data)]) + data)
    out.write(values_op)
  out.write(b'uu.')
  return out.getvalue()


def _pth(path: Path, pickle_bytes: bytes, padding: int) -> None:
  """A torch.save-style zip; `padding` bytes of an unreferenced storage
  member make the file large enough for the reader's byte budget."""
  with zipfile.ZipFile(path, 'w') as archive:
    archive.writestr('archive/data.pkl', pickle_bytes)
    archive.writestr('archive/byteorder', 'little')
    if padding:
      archive.writestr('archive/data/pad', bytes(padding))
    archive.writestr('archive/version', '3\n')


def write_pth(folder: Path, fraction: float) -> list[tuple[str, str]]:
  from slotformer_jax.official import pth_reader  # pylint: disable=g-import-not-at-top
  limits = pth_reader.Limits()
  ops = int(limits.max_pickle_ops * fraction)
  keys = (ops - 11) // 2  # 11 opcodes besides the 2 per key
  # budget = 4 x file + slack must cover 2 x pickle + ops x 512.
  need = ops * pth_reader.BYTES_PER_OPCODE + 2 * 6 * keys
  padding = max(0, (need - limits.slack_bytes) // 4 + _MIB)
  cases = []
  for name, key_of in (('pth', lambda i: i), ('pth_colliding',
                                              lambda i: (i + 1) * P)):
    path = folder / f'{name}.pth'
    _pth(path, _pickle_dict(key_of(i) for i in range(keys)), padding)
    cases.append((f'{name} ({keys} keys, {ops} opcodes, '
                  f'{path.stat().st_size // _MIB} MiB)', str(path)))
  return cases


def read_pth(path: str) -> str:
  from slotformer_jax.official import pth_reader  # pylint: disable=g-import-not-at-top
  try:
    loaded = pth_reader.read_checkpoint(path)
    return f'read {len(loaded["side"])} keys'
  except pth_reader.CheckpointError as error:
    return 'refused: ' + str(error).split(': ', 2)[-1][:60]


def write_pth_collide(folder: Path, count: int) -> list[tuple[str, str]]:
  path = folder / f'collide_{count}.pth'
  _pth(path, _pickle_dict((i + 1) * P for i in range(count)), 0)
  return [(f'pth_collide ({count} colliding keys, '
           f'{path.stat().st_size // 1024} kB)', str(path))]


def write_movi_metadata(folder: Path, fraction: float
                        ) -> list[tuple[str, str]]:
  sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))
  import dataset_fixtures as fx  # pylint: disable=g-import-not-at-top
  from slotformer_jax.datasets import movi  # pylint: disable=g-import-not-at-top
  root = folder / 'movi_a' / '16x16' / '1.0.0'
  fx.write_movi(root, shard_lengths={'train': [1]}, num_frames=3, size=16,
                seed=0, instances=(1, 2))
  limit = int(movi._MAX_JSON_BYTES * fraction)  # pylint: disable=protected-access
  info = json.loads((root / 'dataset_info.json').read_text())
  # Splits of up to _MAX_SHARDS shard lengths each, as many as fit.
  per_split = movi._MAX_SHARDS  # pylint: disable=protected-access
  count, splits = 0, []
  while True:
    split = {'name': f'split{len(splits)}',
             'shardLengths': ['7'] * per_split}
    count += len(json.dumps(split)) + 2
    if count > limit:
      break
    splits.append(split)
  info['splits'] = info['splits'] + splits
  (root / 'dataset_info.json').write_text(json.dumps(info))
  # features.json as TFDS writes it, indented to the limit (its tree is
  # checked node by node; whitespace is what it may hold more of).
  text = (root / 'features.json').read_text()
  (root / 'features.json').write_text(
      text + ' ' * max(0, limit - len(text)))
  sizes = [(root / n).stat().st_size // _MIB
           for n in ('dataset_info.json', 'features.json')]
  return [(f'movi_metadata ({sizes[0]} + {sizes[1]} MiB, {len(splits)} x '
           f'{per_split} shard lengths)', str(root))]


def read_movi_metadata(path: str) -> str:
  from slotformer_jax.datasets import movi  # pylint: disable=g-import-not-at-top
  try:
    info = movi.read_source(Path(path))
    return f'read {sum(map(len, info.shard_lengths.values()))} shards'
  except ValueError as error:
    return 'refused: ' + str(error)[:60]


def write_movi_record(folder: Path, fraction: float) -> list[tuple[str, str]]:
  sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))
  import dataset_fixtures as fx  # pylint: disable=g-import-not-at-top
  from slotformer_jax.datasets import movi  # pylint: disable=g-import-not-at-top
  # MOVi's 24 frames at the largest side the reader takes (the fixture
  # makes every MOVi feature: flows, depth... of random 16-bit values, so
  # MAX_SOURCE_FRAMES of them would take tens of GiB to write); the time
  # is linear in the frames.
  frames = max(2, round(24 * fraction))
  side = movi.MAX_SOURCE_SIDE
  root = folder / 'movi_a' / f'{side}x{side}' / '1.0.0'
  fx.write_movi(root, shard_lengths={'train': [1]}, num_frames=frames,
                size=side, seed=0, instances=(1, 2))
  size = sum(p.stat().st_size for p in root.iterdir()) // _MIB
  return [(f'movi_record ({frames} frames of {side}x{side}, {size} MiB)',
           str(root))]


def read_movi_record(path: str) -> str:
  from slotformer_jax.datasets import movi  # pylint: disable=g-import-not-at-top
  options = movi.Options(resolution=(128, 128), max_objects=10)
  jobs = movi.discover(Path(path), 'train', options)
  item = movi.dataset_spec(options, Path(path)).convert_fn(jobs[0])
  return f'read {item["video"].shape}'


def write_questions(folder: Path, fraction: float) -> list[tuple[str, str]]:
  """Three question files of MAX_QUESTION_FILE_BYTES: scenes of 1,000
  one-word descriptive questions; scenes without questions (the smallest
  scene, so the most objects per byte); `[{},{},...]` (51 bytes of memory
  per byte when the whole file was parsed first; now refused at scene 0)."""
  from slotformer_jax.data import vqa  # pylint: disable=g-import-not-at-top
  limit = int(vqa.MAX_QUESTION_FILE_BYTES * fraction)
  question = ('{"question_id":0,"question_type":"descriptive",'
              '"question":"a","answer":"b"}')
  many = ('{"scene_index":0,"video_filename":"video_00000.mp4","questions":['
          + ','.join([question] * 1000) + ']}')
  empty = '{"scene_index":0,"video_filename":"v","questions":[]}'
  cases = []
  for name, scene, per_question in (('questions', many, 1000),
                                    ('questions_empty', empty, 0),
                                    ('questions_objects', '{}', 0)):
    count = (limit - 2) // (len(scene) + 1)
    path = folder / name / 'questions' / 'train.json'
    path.parent.mkdir(parents=True)
    with open(path, 'w') as f:
      f.write('[')
      block = ','.join([scene] * max(1, min(count, (8 << 20) // len(scene))))
      per_block = block.count(scene[:20]) if scene != '{}' else (
          block.count('{}'))
      written = 0
      while written + per_block <= count:
        f.write(('' if not written else ',') + block)
        written += per_block
      f.write(']')
    what = (f'{written * per_question} questions in {written} scenes'
            if per_question else f'{written} scenes')
    cases.append((f'{name} ({what}, {path.stat().st_size // _MIB} MiB)',
                  str(folder / name)))
  return cases


def read_questions(path: str) -> str:
  from slotformer_jax.data import vqa  # pylint: disable=g-import-not-at-top
  try:
    scenes = vqa.read_clevrer_questions(path, 'train')
  except vqa.QuestionFileError as error:
    return f'refused: {str(error)[-90:]}'
  return (f'read {sum(len(s["questions"]) for s in scenes)} questions, '
          f'{len(scenes)} scenes')


def write_vocabulary(folder: Path, fraction: float) -> list[tuple[str, str]]:
  from slotformer_jax.data import vqa  # pylint: disable=g-import-not-at-top
  count = int(vqa.MAX_VOCABULARY * fraction)
  words = {'PAD': 0, **{f'w{i}': i for i in range(1, count)}}
  path = folder / 'vocab.json'
  path.write_text(json.dumps({'q_vocab': words, 'a_vocab': {'PAD': 0}}))
  return [(f'vocabulary ({count} words, {path.stat().st_size // _MIB} MiB)',
           str(path))]


def read_vocabulary(path: str) -> str:
  from slotformer_jax.data import vqa  # pylint: disable=g-import-not-at-top
  return f'read {len(vqa.Vocabulary.load(path).questions)} words'


def write_phyre_index(folder: Path, fraction: float) -> list[tuple[str, str]]:
  from slotformer_jax.datasets import phyre  # pylint: disable=g-import-not-at-top
  root = folder / 'PHYRE'
  (root / 'train' / 'frames').mkdir(parents=True)
  (root / phyre.META_FILE).write_text(json.dumps({
      'format': phyre.FORMAT, 'format_version': phyre.FORMAT_VERSION,
      'tier': 'ball', 'eval_setup': 'ball_within_template', 'fold': 0,
      'fps': 1, 'frame_size': [8, 8]}))
  limit = int(phyre.MAX_INDEX_BYTES * fraction)
  line = ('{"id":"%07d","task":"00002:013","action":[0.1,0.2,0.3],'
          '"success":true,"num_frames":3}\n')
  count = limit // len(line % 0)
  with open(root / 'train' / phyre.INDEX_FILE, 'w') as f:
    for start in range(0, count, 100_000):
      f.write(''.join(line % i for i in range(start,
                                               min(count, start + 100_000))))
  size = (root / 'train' / phyre.INDEX_FILE).stat().st_size // _MIB
  return [(f'phyre_index ({count} rollouts, {size} MiB)', str(root))]


def read_phyre_index(path: str) -> str:
  from slotformer_jax.datasets import phyre  # pylint: disable=g-import-not-at-top
  options = phyre.Options(resolution=(8, 8), num_frames=3)
  return f'read {len(phyre.discover(Path(path), "train", options))} jobs'


def write_physion_lists(folder: Path, fraction: float
                        ) -> list[tuple[str, str]]:
  limit = int((256 << 20) * fraction)
  entry = '"PhysionTrainMP4s/Dominoes_training_MP4s/%07d.mp4"'
  count = limit // (len(entry % 0) + 1)
  lists = folder / 'lists'
  lists.mkdir()
  with open(lists / 'training_train.json', 'w') as f:
    f.write('{"Dominoes": [')
    for start in range(0, count, 100_000):
      f.write(('' if not start else ',') + ','.join(
          entry % i for i in range(start, min(count, start + 100_000))))
    f.write(']}')
  size = (lists / 'training_train.json').stat().st_size // _MIB
  return [(f'physion_lists ({count} paths, {size} MiB)', str(lists))]


def read_physion_lists(path: str) -> str:
  from slotformer_jax.datasets import physion  # pylint: disable=g-import-not-at-top
  files = physion._listed_files(  # pylint: disable=protected-access
      Path(path) / 'source', 'train', physion.Options(split_files=path))
  return f'read {len(files)} paths'


def write_physion_labels(folder: Path, fraction: float
                         ) -> list[tuple[str, str]]:
  from slotformer_jax.datasets import physion  # pylint: disable=g-import-not-at-top
  limit = int(physion.MAX_LABEL_FILE_BYTES * fraction)
  row = 'pilot_dominoes_%07d_img,True\n'
  count = (limit - 40) // len(row % 0)
  path = folder / 'labels.csv'
  with open(path, 'w') as f:
    f.write(f'stimulus,{physion.LABEL_COLUMN}\n')
    for start in range(0, count, 100_000):
      f.write(''.join(row % i for i in range(start,
                                              min(count, start + 100_000))))
  return [(f'physion_labels ({count} rows, {path.stat().st_size // _MIB} '
           'MiB)', str(path))]


def read_physion_labels(path: str) -> str:
  from slotformer_jax.datasets import physion  # pylint: disable=g-import-not-at-top
  return f'read {len(physion.read_labels(Path(path)))} labels'


def write_metrics(folder: Path, fraction: float) -> list[tuple[str, str]]:
  from slotformer_jax.evaluation import metrics_file  # pylint: disable=g-import-not-at-top
  curves = max(1, int(metrics_file.MAX_CURVES * fraction))
  steps = metrics_file.MAX_STEPS
  # 1e-5 and its kin: short numbers that `clean` rounds (6 bytes each).
  per_step = [1e-5] * steps
  rollout = {}  # one curve per method and metric: MAX_CURVES in all
  for i in range(curves):
    rollout.setdefault(f'm{i % 10}', {})[f'metric{i}'] = {
        'per_step': per_step}
  path = folder / 'eval' / 'metrics.json'
  path.parent.mkdir()
  path.write_text(json.dumps({'identity': {'x': 1}, 'rollout': rollout,
                              'protocol': {'num_videos': 2}},
                             separators=(',', ':')))
  return [(f'metrics ({curves} curves x {steps} steps, '
           f'{path.stat().st_size // _MIB} MiB)', str(path))]


def read_metrics(path: str) -> str:
  from slotformer_jax.evaluation import metrics_file  # pylint: disable=g-import-not-at-top
  curves, note = metrics_file.read_curves(path, {'x': 1}, {})
  if curves is None:
    return 'refused: ' + note[:60]
  return f'read {sum(len(c) for c in curves.values())} curves'


READERS = {
    'pth': (write_pth, read_pth),
    'movi_metadata': (write_movi_metadata, read_movi_metadata),
    'movi_record': (write_movi_record, read_movi_record),
    'questions': (write_questions, read_questions),
    'vocabulary': (write_vocabulary, read_vocabulary),
    'phyre_index': (write_phyre_index, read_phyre_index),
    'physion_lists': (write_physion_lists, read_physion_lists),
    'physion_labels': (write_physion_labels, read_physion_labels),
    'metrics': (write_metrics, read_metrics),
}


# ----------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------


def _peak_mib() -> int:
  """This process's peak resident memory (VmHWM: reset by exec, unlike
  ru_maxrss, which a child inherits from its parent)."""
  try:
    with open('/proc/self/status') as f:
      for line in f:
        if line.startswith('VmHWM:'):
          return int(line.split()[1]) // 1024
  except OSError:
    pass
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024


def child(reader: str, path: str) -> None:
  """Reads `path` once; prints seconds, peak RSS (MiB) and the outcome."""
  read = READERS[reader.split(':')[0]][1]
  started = time.perf_counter()
  outcome = read(path)
  seconds = time.perf_counter() - started
  peak = _peak_mib()
  print(json.dumps({'seconds': seconds, 'peak_mib': peak,
                    'outcome': outcome}))


def run_child(reader: str, path: str, timeout: float) -> dict:
  try:
    done = subprocess.run(
        [sys.executable, __file__, '--child', reader, path],
        capture_output=True, text=True, check=False, timeout=timeout)
  except subprocess.TimeoutExpired:
    return {'seconds': float('inf'), 'peak_mib': 0,
            'outcome': f'stopped after {timeout:.0f} s'}
  if done.returncode:
    return {'seconds': float('nan'), 'peak_mib': 0,
            'outcome': f'failed: {done.stderr.strip().splitlines()[-1:]}'}
  return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
  parser.add_argument('--readers', default=','.join(READERS))
  parser.add_argument('--fraction', type=float, default=1.0,
                      help='inputs at this fraction of each limit')
  parser.add_argument('--collide', default='5000,10000,20000',
                      help='counts of colliding .pth keys to time')
  parser.add_argument('--timeout', type=float, default=3600,
                      help='seconds a read may take before it is stopped')
  parser.add_argument('--child', nargs=2, help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.child:
    child(*args.child)
    return
  print(f'{"reader (input)":70s} {"seconds":>8s} {"peak MiB":>9s}  outcome')
  names = [n for n in args.readers.split(',') if n]
  counts = [int(c) for c in args.collide.split(',') if c]
  for name in names + (['pth_collide'] if counts else []):
    with tempfile.TemporaryDirectory() as folder:
      if name == 'pth_collide':
        cases = [case for count in counts for case in
                 write_pth_collide(Path(folder), count)]
        name = 'pth'
      else:
        cases = READERS[name][0](Path(folder), args.fraction)
      for label, path in cases:
        result = run_child(name, path, args.timeout)
        print(f'{label:70s} {result["seconds"]:8.2f} '
              f'{result["peak_mib"]:9d}  {result["outcome"]}', flush=True)


if __name__ == '__main__':
  main()
