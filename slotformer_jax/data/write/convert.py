"""Per-video conversion jobs -> a resumable ``array_record`` TFDS folder: the
steps every converted dataset shares.

A converted dataset (``datasets/base.py:Converted``) describes its output with
a :class:`~slotformer_jax.datasets.base.Conversion` (feature spec + a
per-video ``convert_fn``) and lists its inputs as *jobs* (picklable, each
with a unique ``key``); :func:`convert` cuts every split into shards of
``videos_per_shard`` jobs, converts them in worker processes (host ``p`` of
``P`` takes shards ``p, p + P, ...``), keeps every finished shard (so an
interrupted conversion resumes), skips and counts the videos whose
``convert_fn`` raises :class:`media.SkipVideo`, and writes the metadata only
when every shard exists and at most ``max_skip_fraction`` of a split was
skipped, so a broken download never becomes a dataset. Output:
``<data_dir>/<name>/<config_name>/<VERSION>/`` in the layout of
``data/chunked.py``; what a conversion promises: docs/datasets.md, "What
every conversion does".
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import logging
import math
import os
import shutil
import time
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import tensorflow_datasets as tfds
import tqdm

from slotformer_jax.data import chunked
from slotformer_jax.data import media
from slotformer_jax.data.video_names import NAMES_FILE
from slotformer_jax.data.write import records as chunked_writer
from slotformer_jax.data.write.pool import process_pool
from slotformer_jax.data.write.pool import wait_done
from slotformer_jax.data.write.records import record_checksums
from slotformer_jax.datasets.base import Conversion
from slotformer_jax.datasets.base import ConversionError
from slotformer_jax.files import write_json_atomic

logger = logging.getLogger(__name__)

# The chunked layout (data/chunked.py): a video is a header record and
# records of FRAMES_PER_CHUNK frames, so a training clip decompresses only
# its chunks. Folders of the whole-video layout before it are '1.0.0' (still
# read, see sources.TfdsVideoSource).
VERSION = chunked.TFDS_VERSION

_DATASET_INFO = 'dataset_info.json'
_PROGRESS_DIR = '_progress'
REPORT_FILE = 'conversion_report.json'


class Job(Protocol):
  """One input video; ``key`` is unique within its split and stable."""

  key: str


@dataclasses.dataclass(frozen=True)
class SkipRecord:
  """A video left out of the dataset, and why."""

  split: str
  key: str
  reason: str
  message: str


@dataclasses.dataclass(frozen=True)
class ConversionResult:
  """Outcome of :func:`convert`.

  Attributes:
    dataset_dir: the TFDS version folder.
    complete: whether the metadata is written (False while other hosts still
      have shards to convert).
    num_examples: {split: videos written}.
    skipped: every skipped video (all shards, including earlier runs).
    videos_processed: videos converted by this call (0 when resumed from a
      finished state).
    seconds: wall time of this call.
  """

  dataset_dir: Path
  complete: bool
  num_examples: dict[str, int]
  skipped: tuple[SkipRecord, ...]
  videos_processed: int
  seconds: float

  def skip_counts(self) -> dict[str, dict[str, int]]:
    """{split: {reason: count}}."""
    counts: dict[str, Counter[str]] = {}
    for record in self.skipped:
      counts.setdefault(record.split, Counter())[record.reason] += 1
    return {split: dict(c) for split, c in counts.items()}


@dataclasses.dataclass(frozen=True)
class _ShardTask:
  spec: Conversion
  split: str
  index: int
  num_shards: int
  jobs: tuple[Any, ...]
  dataset_dir: Path
  frames_per_chunk: int = chunked.FRAMES_PER_CHUNK
  compressed: bool = False


def shard_filename(name: str, split: str, index: int, num_shards: int) -> str:
  """TFDS's default shard naming, which ``write_metadata`` parses back."""
  return f'{name}-{split}.array_record-{index:05d}-of-{num_shards:05d}'


def _progress_dir(dataset_dir: Path) -> Path:
  return dataset_dir / _PROGRESS_DIR


def _sidecar_path(dataset_dir: Path, split: str, index: int) -> Path:
  return _progress_dir(dataset_dir) / f'{split}-{index:05d}.json'


def _manifest_path(dataset_dir: Path, split: str) -> Path:
  return _progress_dir(dataset_dir) / f'{split}-manifest.json'


def _write_json_atomic(path: Path, payload: Any) -> None:
  # A temporary name of its own per writer (hosts sharing data_dir may write
  # the same file, e.g. the manifest, at once), fsynced, then renamed.
  write_json_atomic(path, payload)


def _convert_shard(task: _ShardTask) -> dict[str, Any]:
  """Converts one chunk of videos into one shard file (runs in a worker).

  Returns the sidecar payload: {'keys': written keys, 'skipped': [...],
  'num_bytes': file size}.
  """
  # Imported here: workers are spawned and only need it in this function.
  from array_record.python import array_record_module  # pylint: disable=g-import-not-at-top

  layout = chunked.Layout(task.spec.features_fn(), task.frames_per_chunk,
                          task.compressed)
  serializer = chunked_writer.VideoSerializer(layout)
  final = task.dataset_dir / shard_filename(
      task.spec.name, task.split, task.index, task.num_shards)
  # Written inside _progress/ so a half-written file never matches the
  # shard-name pattern that write_metadata scans for.
  tmp = _progress_dir(task.dataset_dir) / (final.name + '.tmp')
  keys, skipped, frames, num_records = [], [], [], 0
  writer = array_record_module.ArrayRecordWriter(os.fspath(tmp),
                                                 layout.record_options)
  try:
    for job in task.jobs:
      try:
        example = task.spec.convert_fn(job)
      except media.SkipVideo as skip:
        skipped.append({'key': job.key, 'reason': skip.reason,
                        'message': skip.message})
        continue
      except ConversionError:
        raise  # a damaged input: its message names the file and the fix
      except Exception as error:
        # Not an input problem we know how to classify: stop, naming the
        # video, rather than silently dropping it.
        raise RuntimeError(f'converting {task.split}/{job.key} failed: '
                           f'{type(error).__name__}: {error}') from error
      records, num_frames = serializer.records(example)
      for record in records:
        writer.write(record)
      num_records += len(records)
      keys.append(job.key)
      frames.append(num_frames)
  finally:
    writer.close()
  os.replace(tmp, final)
  payload = {'keys': keys, 'skipped': skipped,
             'num_bytes': final.stat().st_size, 'num_frames': frames,
             'num_records': num_records,
             'frames_per_chunk': task.frames_per_chunk,
             'compressed': layout.record_options == chunked.RECORD_OPTIONS}
  _write_json_atomic(_sidecar_path(task.dataset_dir, task.split, task.index),
                     payload)
  return payload


def _check_manifest(dataset_dir: Path, split: str, keys: list[str],
                    spec: Conversion, videos_per_shard: int) -> None:
  """Records the split's job list, or checks it against an earlier run's."""
  path = _manifest_path(dataset_dir, split)
  manifest = {'keys': keys, 'videos_per_shard': videos_per_shard,
              'params': json.loads(json.dumps(dict(spec.params)))}
  if path.is_file():
    with open(path) as f:
      previous = json.load(f)
    if previous != manifest:
      what = ('videos_per_shard' if previous.get('videos_per_shard')
              != videos_per_shard else 'list of input videos'
              if previous.get('keys') != keys else 'conversion parameters')
      raise ConversionError(
          f'{dataset_dir} holds an unfinished conversion of split {split!r} '
          f'with a different {what}; finishing it would mix inputs. Re-run '
          'with the same inputs and options, or pass --overwrite to start '
          'over.')
    return
  _write_json_atomic(path, manifest)


def _load_sidecars(dataset_dir: Path, name: str, split: str,
                   num_shards: int) -> list[dict[str, Any] | None]:
  """The sidecar of every finished shard of a split (None: not finished)."""
  out = []
  for index in range(num_shards):
    path = _sidecar_path(dataset_dir, split, index)
    shard = dataset_dir / shard_filename(name, split, index, num_shards)
    if path.is_file() and shard.is_file():
      with open(path) as f:
        out.append(json.load(f))
    else:
      out.append(None)
  return out


def _run_tasks(tasks: list[_ShardTask], num_workers: int, progress: bool,
               total_videos: int, desc: str) -> Iterator[tuple[_ShardTask,
                                                               dict[str, Any]]]:
  """Runs shard tasks (in worker processes if num_workers > 1)."""
  bar = tqdm.tqdm(total=total_videos, unit='video', desc=desc,
                  disable=not progress, dynamic_ncols=True)
  skipped = 0
  try:
    if num_workers <= 1:
      for task in tasks:
        payload = _convert_shard(task)
        skipped += len(payload['skipped'])
        bar.update(len(task.jobs))
        bar.set_postfix(skipped=skipped)
        yield task, payload
      return
    pool = process_pool(num_workers)
    try:
      futures = {pool.submit(_convert_shard, task): task for task in tasks}
      order = {future: index for index, future in enumerate(futures)}
      pending = set(futures)
      while pending:
        # Not as_completed: Ctrl-C must not land inside its locks (pool.py).
        done = wait_done(pending)
        pending -= done
        for future in sorted(done, key=order.__getitem__):
          task = futures[future]
          try:
            payload = future.result()
          except concurrent.futures.process.BrokenProcessPool as error:
            raise RuntimeError(
                'Conversion worker processes died (out of memory?). With the '
                '"spawn" start method they re-import the main script, so a '
                'script that converts data must do so under '
                "`if __name__ == '__main__':`; or use --num_workers=1."
            ) from error
          skipped += len(payload['skipped'])
          bar.update(len(task.jobs))
          bar.set_postfix(skipped=skipped)
          yield task, payload
    finally:
      # On an error or Ctrl-C, drop queued shards instead of converting them.
      pool.shutdown(wait=True, cancel_futures=True)
  finally:
    bar.close()


def _finished_splits(dataset_dir: Path) -> set[str]:
  """Splits listed in an existing dataset_info.json."""
  path = dataset_dir / _DATASET_INFO
  if not path.is_file():
    return set()
  with open(path) as f:
    info = json.load(f)
  return {split['name'] for split in info.get('splits', [])}


def _manifest_splits(dataset_dir: Path) -> list[str]:
  progress = _progress_dir(dataset_dir)
  if not progress.is_dir():
    return []
  return sorted(p.name[:-len('-manifest.json')]
                for p in progress.glob('*-manifest.json'))


def convert(spec: Conversion, jobs: Mapping[str, Sequence[Job]],
            data_dir: str | os.PathLike[str], *,
            num_workers: int | None = None, videos_per_shard: int = 32,
            process_index: int = 0, process_count: int = 1,
            max_skip_fraction: float = 0.05, overwrite: bool = False,
            progress: bool = True,
            frames_per_chunk: int = chunked.FRAMES_PER_CHUNK,
            compressed: bool = False) -> ConversionResult:
  """Converts the jobs of every split into ``spec.dataset_dir(data_dir)``.

  Args:
    spec: the output description.
    jobs: {split: jobs in the order the records should have}.
    data_dir: root of the converted datasets.
    num_workers: worker processes (default: available cores; 1 converts in
      this process).
    videos_per_shard: videos per shard file = resume granularity.
    process_index, process_count: multi-host conversion; this host converts
      shards ``process_index, process_index + process_count, ...``.
    max_skip_fraction: fail (before writing the metadata) if a split skips
      more than this fraction of its videos.
    overwrite: delete an existing (finished or partial) conversion with the
      same parameters first.
    progress: show a progress bar.
    frames_per_chunk: frames per record (``data/chunked.py``; 0 writes the
      whole-video records of the 1.0.0 layout, for tests and benchmarks,
      into a ``1.0.0`` folder).
    compressed: compress the chunks (``chunked.Layout.compressed``; a
      conversion resumed with the other choice stops in one line).

  Raises:
    ConversionError: too many skipped videos, or an unfinished conversion
      with different inputs.
    ValueError: bad arguments (empty split, duplicate keys).
  """
  started = time.time()
  if videos_per_shard < 1:
    raise ValueError(f'videos_per_shard must be >= 1, got {videos_per_shard}')
  if process_count < 1 or not 0 <= process_index < process_count:
    raise ValueError(f'need 0 <= process_index < process_count, got '
                     f'{process_index} / {process_count}')
  dataset_dir = spec.dataset_dir(data_dir)
  if not frames_per_chunk:
    dataset_dir = dataset_dir.parent / chunked_writer.WHOLE_VIDEO_VERSION
  if overwrite and dataset_dir.exists():
    logger.info('Deleting %s (--overwrite)', dataset_dir)
    shutil.rmtree(dataset_dir)
  finished = _finished_splits(dataset_dir)
  todo = {split: list(split_jobs) for split, split_jobs in jobs.items()
          if split not in finished}
  if finished and not todo:
    logger.info('%s is already prepared (splits %s); pass --overwrite to '
                'convert again.', dataset_dir, sorted(finished))
    return _result_from_report(dataset_dir, started)
  try:
    _progress_dir(dataset_dir).mkdir(parents=True, exist_ok=True)
  except OSError as error:  # read-only, no permission, a file in the path
    raise ConversionError(
        f'cannot write the dataset folder {dataset_dir} ({error.strerror}); '
        'set --data_dir (or $SLOTFORMER_DATA_DIR) to a folder you can '
        'write') from None

  plans: dict[str, int] = {}
  tasks: list[_ShardTask] = []
  for split, split_jobs in todo.items():
    keys = [job.key for job in split_jobs]
    if not keys:
      raise ValueError(f'split {split!r} has no videos')
    duplicates = [k for k, n in Counter(keys).items() if n > 1]
    if duplicates:
      raise ValueError(f'split {split!r} has duplicate video keys, e.g. '
                       f'{duplicates[:3]}')
    _check_manifest(dataset_dir, split, keys, spec, videos_per_shard)
    num_shards = math.ceil(len(keys) / videos_per_shard)
    plans[split] = num_shards
    done = _load_sidecars(dataset_dir, spec.name, split, num_shards)
    for index in range(process_index, num_shards, process_count):
      if done[index] is None:
        tasks.append(_ShardTask(
            spec=spec, split=split, index=index, num_shards=num_shards,
            jobs=tuple(split_jobs[index * videos_per_shard:
                                  (index + 1) * videos_per_shard]),
            dataset_dir=dataset_dir, frames_per_chunk=frames_per_chunk,
            compressed=compressed))

  processed = sum(len(t.jobs) for t in tasks)
  if tasks:
    workers = num_workers or len(os.sched_getaffinity(0))
    workers = max(1, min(workers, len(tasks)))
    logger.info('Converting %d videos (%d shards) into %s with %d worker(s)',
                processed, len(tasks), dataset_dir, workers)
    for task, payload in _run_tasks(tasks, workers, progress, processed,
                                    f'{spec.name} {",".join(sorted(todo))}'):
      for skip in payload['skipped']:
        logger.warning('Skipped %s/%s: %s', task.split, skip['key'],
                       skip['message'])

  # Every split this folder has a manifest for (earlier runs included).
  incomplete = []
  split_payloads: dict[str, list[dict[str, Any]]] = {}
  for split in sorted(set(_manifest_splits(dataset_dir)) | set(plans)):
    with open(_manifest_path(dataset_dir, split)) as f:
      manifest = json.load(f)
    num_shards = math.ceil(len(manifest['keys'])
                           / manifest['videos_per_shard'])
    sidecars = _load_sidecars(dataset_dir, spec.name, split, num_shards)
    missing = sum(s is None for s in sidecars)
    if missing:
      incomplete.append(f'{split}: {missing} of {num_shards} shards')
    else:
      split_payloads[split] = sidecars
  if incomplete:
    message = (f'{dataset_dir}: shards still missing ({"; ".join(incomplete)})'
               '; other hosts are converting them, or an earlier run was '
               'interrupted. Re-run the same command to finish; the metadata '
               'is written once every shard exists.')
    logger.warning(message)
    print(message)
    return ConversionResult(
        dataset_dir=dataset_dir, complete=False, num_examples={},
        skipped=_skips(split_payloads), videos_processed=processed,
        seconds=time.time() - started)

  skipped = _skips(split_payloads)
  _check_skip_fraction(split_payloads, skipped, max_skip_fraction,
                       dataset_dir)
  _write_metadata(spec, dataset_dir, split_payloads)
  result = ConversionResult(
      dataset_dir=dataset_dir, complete=True,
      num_examples={split: sum(len(p['keys']) for p in payloads)
                    for split, payloads in split_payloads.items()},
      skipped=skipped, videos_processed=processed,
      seconds=time.time() - started)
  _write_report(spec, result)
  return result


def _skips(split_payloads: Mapping[str, list[dict[str, Any]]]
           ) -> tuple[SkipRecord, ...]:
  return tuple(
      SkipRecord(split=split, key=s['key'], reason=s['reason'],
                 message=s['message'])
      for split, payloads in split_payloads.items()
      for payload in payloads for s in payload['skipped'])


def _check_skip_fraction(split_payloads: Mapping[str, list[dict[str, Any]]],
                         skipped: Sequence[SkipRecord],
                         max_skip_fraction: float, dataset_dir: Path) -> None:
  problems = []
  for split, payloads in split_payloads.items():
    written = sum(len(p['keys']) for p in payloads)
    reasons = Counter(s.reason for s in skipped if s.split == split)
    total = written + sum(reasons.values())
    if written == 0 or sum(reasons.values()) > max_skip_fraction * total:
      problems.append(f'{split}: skipped {sum(reasons.values())} of {total} '
                      f'videos ({dict(reasons)})')
  if problems:
    examples = '\n  '.join(s.message for s in skipped[:5])
    raise ConversionError(
        'Too many videos could not be converted (limit --max_skip_fraction='
        f'{max_skip_fraction}):\n  ' + '\n  '.join(problems) +
        f'\nFirst problems:\n  {examples}\nFix the download (the converted '
        f'shards in {dataset_dir} are kept; re-running only converts what '
        'is missing), or raise --max_skip_fraction to accept the skips.')


def _write_metadata(spec: Conversion, dataset_dir: Path,
                    split_payloads: Mapping[str, list[dict[str, Any]]]) -> None:
  # Before dataset_info.json, the completion marker.
  _write_json_atomic(dataset_dir / NAMES_FILE, {
      split: [key for payload in payloads for key in payload['keys']]
      for split, payloads in sorted(split_payloads.items())})
  chunk_sizes = {p.get('frames_per_chunk') for payloads in
                 split_payloads.values() for p in payloads}
  if len(chunk_sizes) != 1 or None in chunk_sizes:
    raise ConversionError(
        f'{dataset_dir} holds shards written with different chunk sizes '
        f'({sorted(map(str, chunk_sizes))}); convert again with --overwrite.')
  # Sidecars from before the choice existed: compressed chunks.
  compression = {p.get('compressed', True) for payloads in
                 split_payloads.values() for p in payloads}
  if len(compression) != 1:
    raise ConversionError(
        f'{dataset_dir} holds shards written compressed and uncompressed '
        '(a conversion resumed with the other --compress_records); convert '
        'again with --overwrite, or resume with the first choice.')
  layout = chunked.Layout(spec.features_fn(), chunk_sizes.pop(),
                          compression.pop())
  chunked_writer.write_index(dataset_dir, layout, {
      split: [t for p in payloads for t in p['num_frames']]
      for split, payloads in split_payloads.items()})
  split_infos = [
      tfds.core.SplitInfo(name=split,
                          shard_lengths=[p['num_records'] for p in payloads],
                          num_bytes=sum(p['num_bytes'] for p in payloads))
      for split, payloads in sorted(split_payloads.items())]
  tfds.folder_dataset.write_metadata(
      data_dir=os.fspath(dataset_dir), features=spec.features_fn(),
      split_infos=split_infos, version=dataset_dir.name,
      # check_data reads an example through tf.data, which needs TensorFlow.
      check_data=False, description=spec.description,
      metadata=tfds.core.MetadataDict(
          conversion=json.loads(json.dumps(dict(spec.params)))))
  # Verified whenever the dataset is opened (see data/integrity.py).
  record_checksums(dataset_dir)


def record_video_names(dataset_dir: str | os.PathLike[str]) -> bool:
  """Writes ``video_names.json`` into a folder converted before it was
  written, from the progress files its conversion kept (the keys of each
  shard, in record order). Returns False, writing nothing, when those are
  gone; the readers then refuse the folder with the command that converts it
  again."""
  dataset_dir = Path(dataset_dir)
  names = {}
  for split in _manifest_splits(dataset_dir):
    with open(_manifest_path(dataset_dir, split)) as f:
      manifest = json.load(f)
    num_shards = math.ceil(len(manifest['keys'])
                           / manifest['videos_per_shard'])
    keys = []
    for index in range(num_shards):
      path = _sidecar_path(dataset_dir, split, index)
      if not path.is_file():
        return False
      with open(path) as f:
        keys += json.load(f)['keys']
    names[split] = keys
  if not names:
    return False
  _write_json_atomic(dataset_dir / NAMES_FILE, names)
  return True


def _write_report(spec: Conversion, result: ConversionResult) -> None:
  report = {
      'dataset': spec.name, 'config': spec.config_name,
      'params': json.loads(json.dumps(dict(spec.params))),
      'num_examples': result.num_examples,
      'skip_counts': result.skip_counts(),
      'skipped': [dataclasses.asdict(s) for s in result.skipped],
  }
  _write_json_atomic(result.dataset_dir / REPORT_FILE, report)


def _result_from_report(dataset_dir: Path, started: float) -> ConversionResult:
  path = dataset_dir / REPORT_FILE
  report = {}
  if path.is_file():
    with open(path) as f:
      report = json.load(f)
  return ConversionResult(
      dataset_dir=dataset_dir, complete=True,
      num_examples=dict(report.get('num_examples', {})),
      skipped=tuple(SkipRecord(**s) for s in report.get('skipped', [])),
      videos_processed=0, seconds=time.time() - started)


def summary(result: ConversionResult) -> str:
  """A few human-readable lines about a conversion."""
  lines = [f'Dataset folder: {result.dataset_dir}']
  if not result.complete:
    lines.append('Not finished: shards are missing (see the message above).')
  for split, count in sorted(result.num_examples.items()):
    lines.append(f'  {split}: {count} videos')
  counts = result.skip_counts()
  if counts:
    lines.append(f'Skipped {len(result.skipped)} videos (listed in '
                 f'{result.dataset_dir / REPORT_FILE}):')
    for split, reasons in sorted(counts.items()):
      lines.append(f'  {split}: ' + ', '.join(
          f'{reason} x{n}' for reason, n in sorted(reasons.items())))
  else:
    lines.append('No video was skipped.')
  if result.videos_processed:
    lines.append(f'Converted {result.videos_processed} videos in '
                 f'{result.seconds:.1f} s '
                 f'({result.videos_processed / max(result.seconds, 1e-9):.1f}'
                 ' videos/s).')
  return '\n'.join(lines)

