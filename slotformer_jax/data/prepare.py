"""Converts a downloaded dataset into the project's array_record format.

Usage::

    python -m slotformer_jax.data.prepare --dataset=clevrer \
        --source=/path/to/CLEVRER --data_dir=/path/to/data

``--dataset`` is the ``command`` of a converted dataset
(``slotformer_jax/datasets/``: obj3d, clevrer, physion, phyre, movi, and any
registered one); ``--source`` is the folder holding the files in their
published layout. The result goes to
``<data_dir>/<name>/<config>/2.0.0``; conversion is parallel, resumable,
skips and reports broken videos, and splits over hosts with
``--process_index`` / ``--process_count``. The layouts and what every
conversion does: docs/datasets.md.
"""

from __future__ import annotations

import signal
import sys

try:
  import argparse
  import dataclasses
  import logging
  from collections.abc import Sequence
  from pathlib import Path
  from typing import Any

  from slotformer_jax import datasets
  from slotformer_jax.data import chunked
  from slotformer_jax.data.sources import resolve_data_dir
  from slotformer_jax.data.write import convert as writer
  from slotformer_jax.datasets import clevrer
  from slotformer_jax.datasets.base import ConversionError
  from slotformer_jax.errors import printable
except KeyboardInterrupt:  # Ctrl-C while the libraries import
  if __name__ == '__main__':  # not a worker re-importing this file
    print('interrupted: Ctrl-C; nothing was converted yet', file=sys.stderr)
  sys.exit(128 + signal.SIGINT)

# CLI flag -> Options field; a flag given for a dataset without that field is
# an error rather than silently ignored.
_OPTION_FLAGS: dict[str, str] = {
    'resolution': 'resolution', 'num_frames': 'num_frames',
    'max_objects': 'max_objects', 'masks': 'masks',
    'val_fraction': 'val_fraction', 'split_files': 'split_files',
    'test_fraction': 'test_fraction', 'frame_stride': 'frame_stride',
    'fps': 'fps', 'fit': 'fit'}


def parse_resolution(text: str) -> tuple[int, int]:
  """'64' -> (64, 64); '64x96' or '64,96' -> (64, 96) (H, W)."""
  parts = text.lower().replace(',', 'x').split('x')
  try:
    values = tuple(int(p) for p in parts)
  except ValueError:
    raise argparse.ArgumentTypeError(f'bad resolution {text!r}') from None
  if len(values) == 1:
    values = values * 2
  if len(values) != 2:
    raise argparse.ArgumentTypeError(f'bad resolution {text!r}')
  return values  # type: ignore[return-value]


def _defaults(what: str) -> str:
  """'clevrer 64, movi 64, ...': each converter's default option `what`
  (the paper's; 'resolution': its height)."""
  values = []
  for command, dataset in sorted(datasets.converters().items()):
    value = getattr(dataset.options(), what, None)
    if value is not None:
      values.append(f'{command} {value[0] if what == "resolution" else value}')
  return ', '.join(values)


def build_parser() -> argparse.ArgumentParser:
  parser = argparse.ArgumentParser(
      prog='python -m slotformer_jax.data.prepare',
      description=__doc__.split('\n\n')[0],
      formatter_class=argparse.RawDescriptionHelpFormatter,
      epilog='Per-dataset layouts and defaults: docs/datasets.md')
  parser.add_argument('--dataset', required=True,
                      choices=sorted(datasets.converters()))
  parser.add_argument('--source', required=True, type=Path,
                      help='folder with the downloaded files (published '
                      'layout)')
  parser.add_argument('--data_dir', type=Path, default=None,
                      help='output root (default: $SLOTFORMER_DATA_DIR or '
                      '~/.cache/slotformer_jax)')
  parser.add_argument('--splits', default=None,
                      help='comma-separated subset of the dataset\'s splits '
                      '(default: all)')
  parser.add_argument('--resolution', type=parse_resolution, default=None,
                      help='H or HxW of the stored frames (default: the '
                      f'paper\'s: {_defaults("resolution")})')
  parser.add_argument('--num_frames', type=int, default=None,
                      help=f'frames kept per video ({_defaults("num_frames")})')
  parser.add_argument('--max_objects', type=int, default=None,
                      help='clevrer: rows of the per-object arrays (6); '
                      'movi: rows of the per-instance arrays, ids above it '
                      'dropped (10 for MOVi-A/B/C, 23 for D/E/F)')
  parser.add_argument('--masks', choices=clevrer.MASK_MODES, default=None,
                      help='clevrer: use derender_proposals if present '
                      '(auto), demand them (require) or skip them (ignore)')
  parser.add_argument('--val_fraction', type=float, default=None,
                      help='physion: share of Training / Readout videos in '
                      'the *_val splits (0.05)')
  parser.add_argument('--test_fraction', type=float, default=None,
                      help='videos: share of a folder without split '
                      'folders hashed into test (0.1; --val_fraction: val)')
  parser.add_argument('--frame_stride', type=int, default=None,
                      help='videos: keep every n-th frame (1), after --fps')
  parser.add_argument('--fps', type=float, default=None,
                      help='videos: resample each file to this frame rate '
                      'first (0: its own rate)')
  parser.add_argument('--fit', choices=('crop', 'pad'), default=None,
                      help='videos: fill the frame and cut the centre '
                      '(crop) or show it whole between black bars (pad)')
  parser.add_argument('--split_files', default=None,
                      help='physion: folder with the official split lists '
                      '(training_train.json, ...)')
  parser.add_argument('--limit', type=int, default=None,
                      help='convert only the first N videos of each split '
                      '(a trial run; stored in a separate folder)')
  parser.add_argument('--num_workers', type=int, default=None,
                      help='conversion processes (default: all cores)')
  parser.add_argument('--videos_per_shard', type=int, default=32,
                      help='videos per array_record file = resume unit')
  parser.add_argument('--process_index', type=int, default=0)
  parser.add_argument('--process_count', type=int, default=1)
  parser.add_argument('--max_skip_fraction', type=float, default=0.05,
                      help='fail if a split skips more than this fraction')
  parser.add_argument('--overwrite', action='store_true',
                      help='delete an existing conversion with the same '
                      'parameters first')
  parser.add_argument('--no_progress', action='store_true',
                      help='no progress bar')
  parser.add_argument('--frames_per_chunk', type=int,
                      default=chunked.FRAMES_PER_CHUNK,
                      help='frames per record (data/chunked.py); 0 writes '
                      'the whole-video records of the 1.0.0 layout (for '
                      'benchmarks)')
  parser.add_argument('--compress_records', action='store_true',
                      help='compress the chunk records (array_record\'s '
                      'default zstd): less disk, about a third of the clips '
                      'per reader core (data/chunked.py)')
  return parser


def make_options(dataset: datasets.Converted, args: argparse.Namespace
                 ) -> Any:
  """The dataset's Options from the CLI flags that were given."""
  fields = {f.name for f in dataclasses.fields(dataset.options)}
  kwargs = {}
  for flag, field in _OPTION_FLAGS.items():
    value = getattr(args, flag)
    if value is None:
      continue
    if field not in fields:
      raise ValueError(f'--{flag} does not apply to --dataset={args.dataset}')
    kwargs[field] = value
  return dataset.options(**kwargs)


def selected_splits(dataset: datasets.Converted, text: str | None,
                    source: Path | None = None) -> tuple[str, ...]:
  if not text:
    # A dataset whose splits depend on the download (MOVi-A has no 'test').
    if source is not None and dataset.available_splits is not None:
      return dataset.available_splits(source)
    return dataset.splits
  splits = tuple(s.strip() for s in text.split(',') if s.strip())
  unknown = [s for s in splits if s not in dataset.splits]
  if unknown:
    raise ValueError(f'unknown splits {unknown}; {dataset.command} has '
                     f'{dataset.splits}')
  return splits


def run(args: argparse.Namespace) -> writer.ConversionResult:
  """Discovers, converts and reports; see the module docstring."""
  dataset = datasets.converters()[args.dataset]
  source = args.source.expanduser()
  if not source.is_dir():
    raise FileNotFoundError(
        f'--source={source} is not a folder. Expected the published '
        f'{args.dataset} layout:\n{dataset.layout}')
  options = make_options(dataset, args)
  splits = selected_splits(dataset, args.splits, source)
  spec = dataset.spec(options, source)
  if args.limit is not None:
    if args.limit < 1:
      raise ValueError(f'--limit must be >= 1, got {args.limit}')
    spec = dataclasses.replace(
        spec, config_name=f'{spec.config_name}_first{args.limit}',
        params={**spec.params, 'limit': args.limit})
  jobs = {}
  for split in splits:
    found = dataset.discover(source, split, options)
    jobs[split] = found[:args.limit] if args.limit else found
    logging.info('%s %s: %d videos', args.dataset, split, len(jobs[split]))
  data_dir = resolve_data_dir(args.data_dir)
  result = writer.convert(
      spec, jobs, data_dir, num_workers=args.num_workers,
      videos_per_shard=args.videos_per_shard,
      process_index=args.process_index, process_count=args.process_count,
      max_skip_fraction=args.max_skip_fraction, overwrite=args.overwrite,
      progress=not args.no_progress, frames_per_chunk=args.frames_per_chunk,
      compressed=args.compress_records)
  print(writer.summary(result))
  if result.complete:
    print(f'Read it with data config name={spec.name!r}, '
          f'data_dir={str(data_dir)!r}'
          + (f', resolution={tuple(options.resolution)}'
             if hasattr(options, 'resolution') else ''))
  return result


def main(argv: Sequence[str] | None = None) -> int:
  logging.basicConfig(level=logging.INFO,
                      format='%(levelname)s %(name)s: %(message)s')
  parser = build_parser()
  args = parser.parse_args(argv)
  try:
    run(args)
  except (FileNotFoundError, ValueError, ConversionError) as error:
    # Input problems: a clear message, no traceback; names from the
    # download are escaped where they are quoted, `printable` keeps
    # anything else a terminal acts on from reaching it.
    print(f'error: {printable(error)}', file=sys.stderr)
    return 1
  except KeyboardInterrupt:
    # Finished shards are kept (each is renamed when complete).
    print('interrupted: Ctrl-C; re-run the same command to convert the '
          'remaining shards', file=sys.stderr)
    return 128 + signal.SIGINT
  return 0


if __name__ == '__main__':
  sys.exit(main())
