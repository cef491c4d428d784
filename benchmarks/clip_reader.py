r"""Whole-video records (1.0.0) against chunked records (2.0.0): training clip
frames delivered per second on one core, the same videos, alternating rounds.

  python benchmarks/clip_reader.py [--streams=obj3d_savi,clevrer_savi,
      obj3d_li,clevrer_li,physion_dvae] [--chunks=4,4z] [--videos=24]
      [--seconds=3] [--rounds=3] [--core=0] [--workdir=DIR]

Fixtures: `reader_speed.py`'s OBJ3D-layout PNG videos of moving squares over
smooth backgrounds with renderer noise (they compress as rendered frames
do) at each dataset's stored length and resolution (OBJ3D 50x64x64,
CLEVRER 128x64x64, Physion 150x128x128), converted by `prepare` once per
layout: `--frames_per_chunk=0` (whole-video records, the layout before;
always measured) and every K of `--chunks` (`4`: uncompressed chunks, the
default; `4z`: compressed, `prepare --compress_records`). SlotFormer's L_I
stream reads random float32 slots (`slots.SlotSource`, OBJ3D 6x128,
CLEVRER 7x128) with the video frames of the same steps: with whole-video
records every clip frame's (the reader before), with chunked records only
the rollout's, from frame `burn_in` = 6 on (what `stages/dynamics.py` reads;
the loss compares no others). Rates count clip frames (clips/s x clip
length) either way.

The measurement runs in this process pinned to `--core` (BLAS / OpenMP
threads set to 1 before numpy is imported), calling
`pipeline.make_train_batch` for consecutive steps (no prefetch thread: the
reader alone). Rounds alternate the layouts (round r: K=0, K=4, ...), so
load drifts hit them alike; the median over rounds is reported with
`uptime` before and after, and the file size of each layout.
"""

from __future__ import annotations

import os

for _name in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS',
              'TF_NUM_INTRAOP_THREADS', 'TF_NUM_INTEROP_THREADS'):
  os.environ[_name] = '1'
os.environ.setdefault('JAX_PLATFORMS', 'cpu')

# pylint: disable=g-import-not-at-top,wrong-import-position
import argparse
import dataclasses
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import reader_speed  # noqa: E402

from slotformer_jax.data import chunked  # noqa: E402
from slotformer_jax.data import pipeline  # noqa: E402
from slotformer_jax.data import slots  # noqa: E402
from slotformer_jax.data import sources  # noqa: E402
from slotformer_jax.data import prepare  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Stream:
  name: str
  dataset: str
  resolution: int
  frames: int
  clip: int
  stride: int
  batch: int
  slot_shape: tuple[int, int] | None = None
  # L_I reads the video from this clip frame on (the rollout's): the
  # chunked layout's SlotSource skips the burn-in frames' video.
  video_from: int = 0


STREAMS = {s.name: s for s in (
    Stream('obj3d_savi', 'obj3d', 64, 50, 6, 1, 64),
    Stream('clevrer_savi', 'clevrer', 64, 128, 6, 1, 64),
    Stream('obj3d_li', 'obj3d', 64, 50, 16, 1, 32, (6, 128), 6),
    Stream('clevrer_li', 'clevrer', 64, 128, 16, 2, 32, (7, 128), 6),
    Stream('physion_dvae', 'physion', 128, 150, 1, 1, 64),
)}


def parse_layout(spec: str) -> tuple[int, bool]:
  """'4' -> (4, uncompressed), '4z' -> (4, compressed); '0': whole videos
  (always compressed)."""
  compressed = spec.endswith('z')
  return int(spec[:-1] if compressed else spec), compressed


def layout_name(k: int, compressed: bool) -> str:
  return 'whole' if k == 0 else f'K={k}{" zstd" if compressed else ""}'


def layout_dir(work: Path, s: Stream, videos: int, k: int,
               compressed: bool = False) -> Path:
  """The fixture's videos converted with chunks of `k` frames (0: whole
  videos, the 1.0.0 layout), `compressed` or not; the PNGs are written
  once."""
  root = work / f'{s.dataset}_r{s.resolution}_t{s.frames}_v{videos}'
  name = f'k{k}' if k == 0 else f'k{k}{"z" if compressed else "u"}'
  if not (root / f'done_{name}').exists():
    if not (root / 'OBJ3D' / 'train').is_dir():
      reader_speed.write_obj3d_like(root / 'OBJ3D', videos,
                                    resolution=s.resolution, frames=s.frames)
    prepare.main(['--dataset=obj3d', f'--source={root / "OBJ3D"}',
                  f'--data_dir={root / f"data_{name}"}', '--splits=train',
                  '--no_progress', '--num_workers=2',
                  f'--resolution={s.resolution}', f'--num_frames={s.frames}',
                  f'--frames_per_chunk={k}']
                 + (['--compress_records'] if compressed else []))
    (root / f'done_{name}').write_text('')
  return sources.find_prepared_dataset(root / f'data_{name}' / 'obj3d')


def slot_dir(work: Path, s: Stream, videos: int) -> str:
  folder = work / f'slots_v{videos}_t{s.frames}_{s.slot_shape[0]}x{s.slot_shape[1]}'
  meta = slots.read_meta(str(folder))
  if not meta or not meta.get('complete'):
    rng = np.random.default_rng(0)
    w = slots.SlotWriter(str(folder), videos, *s.slot_shape, savi_step=0)
    for v in range(videos):
      w.add(v, rng.standard_normal((s.frames, *s.slot_shape),
                                   dtype=np.float32))
    w.close()
  return str(folder)


def open_stream(work: Path, s: Stream, videos: int, k: int,
                compressed: bool = False):
  video = sources.TfdsVideoSource(layout_dir(work, s, videos, k, compressed),
                                  'train')
  if s.slot_shape is None:
    return video, ('video',)
  # Whole videos: the reader before, which handed L_I every clip frame.
  return (slots.SlotSource(slot_dir(work, s, videos), video, verify=False,
                           video_from=s.video_from if k else 0),
          ('slots', 'video'))


def rate(source, fields, s: Stream, seconds: float, first_step: int
         ) -> tuple[float, int]:
  """Delivered clip frames/s of make_train_batch (clips/s x clip length,
  however many of a clip's video frames the stream reads); the next step."""
  step, frames = first_step, 0
  kwargs = dict(batch_size=s.batch, clip_length=s.clip, seed=0,
                fields=fields, frame_stride=s.stride)
  pipeline.make_train_batch(source, step, **kwargs)  # warm: opens files
  step += 1
  started = time.perf_counter()
  while time.perf_counter() - started < seconds:
    batch = pipeline.make_train_batch(source, step, **kwargs)
    frames += batch[fields[0]].shape[0] * batch[fields[0]].shape[1]
    step += 1
  return frames / (time.perf_counter() - started), step


def size_mib(folder: Path) -> float:
  return sum(p.stat().st_size for p in folder.glob('*.array_record-*')) / 2**20


def _uptime() -> str:
  return subprocess.run(['uptime'], capture_output=True, text=True,
                        check=False).stdout.strip()


def main(argv: list[str] | None = None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--streams', default=','.join(STREAMS))
  parser.add_argument('--chunks', default=f'{chunked.FRAMES_PER_CHUNK},'
                      f'{chunked.FRAMES_PER_CHUNK}z',
                      help='chunk sizes K compared with whole videos (0); '
                      'K: uncompressed chunks, Kz: compressed')
  parser.add_argument('--videos', type=int, default=24)
  parser.add_argument('--seconds', type=float, default=3.0)
  parser.add_argument('--rounds', type=int, default=3)
  parser.add_argument('--core', type=int, default=0)
  parser.add_argument('--workdir', default='/tmp/slotformer_clip_reader')
  args = parser.parse_args(argv)
  work = Path(args.workdir)
  streams = [STREAMS[n] for n in args.streams.split(',') if n]
  ks = [(0, True)] + [parse_layout(k) for k in args.chunks.split(',')
                       if parse_layout(k)[0] != 0]
  for s in streams:  # fixtures first (the conversion uses 2 processes)
    for k in ks:
      layout_dir(work, s, args.videos, *k)
  os.sched_setaffinity(0, {args.core})
  print(f'pinned to core {args.core}; {args.videos} videos per fixture; '
        f'{args.rounds} rounds x {args.seconds:g} s, layouts alternating')
  print(f'uptime before: {_uptime()}', flush=True)
  results = {}
  for s in streams:
    opened = {k: open_stream(work, s, args.videos, *k) for k in ks}
    measured = {k: [] for k in ks}
    step = 0
    for _ in range(args.rounds):
      for k in ks:
        value, step = rate(*opened[k], s, args.seconds, step)
        measured[k].append(value)
    results[s.name] = {k: statistics.median(v) for k, v in measured.items()}
    sizes = {k: size_mib(layout_dir(work, s, args.videos, *k)) for k in ks}
    whole = results[s.name][ks[0]]
    line = ', '.join(
        f'{layout_name(*k)}: {results[s.name][k]:9,.0f} '
        f'frames/s ({results[s.name][k] / whole:.2f}x, '
        f'{sizes[k]:.1f} MiB)' for k in ks)
    print(f'{s.name:13s} {s.frames}x{s.resolution}x{s.resolution}, clip '
          f'{s.clip} stride {s.stride}, batch {s.batch}'
          f'{" + slots" if s.slot_shape else ""}: {line}', flush=True)
  print(f'uptime after: {_uptime()}')


if __name__ == '__main__':
  main()
