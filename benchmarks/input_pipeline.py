r"""The host input rate each training step needs at its roofline floor, and
today's reader per host core.

  python benchmarks/input_pipeline.py [--configs=obj3d,clevrer,phyre,physion]
      [--seconds=3] [--rounds=3] [--videos=24] [--core=0] [--workdir=DIR]
      [--no_measure]
      [--markdown] [--json=out.json]

For every step of the paper configs that `benchmarks/tpu_compile.py`
compiled (docs/experiments/tpu_compile.json: SAVi / stochastic SAVi, dVAE,
STEVE, SlotFormer, the evaluation rollout, Aloe, the readouts):

* **the need**: the step's global batch over its roofline floor on a
  v5e-8 (`v5e:2x4`, 8 chips, one host) and a v4-8 (`v4:2x2x1`, 4 chips, one
  host), from the JSON's bfloat16 row where one compiled, else its float32
  row (the column says which), in clips/s, frames/s and MB/s per host, at
  the floor and at twice the floor (a step twice as slow as its floor needs
  half the rate). "Frames" are what one clip carries: video frames where
  the step reads video, slot frames where it reads only slots (SlotFormer
  without L_I, Aloe, readouts). Bytes are the batch as the data stream
  yields it (`tpu_compile.batch_spec`: uint8 frames, float32 slots,
  uint16 STEVE tokens, Aloe's question tokens).
* **a GPU estimate**: the same program's global FLOPs and bytes (XLA:TPU's
  per-chip counts x chips, v5e-8 row) spread over 8 H100 SXM (one host),
  floor = max(FLOPs / 989.4 TFLOP/s, bytes / 3.35 TB/s) per GPU. It is an
  estimate from XLA:TPU's counts, not a GPU compile; the readout runs on
  one chip, so on one GPU.
* **today's reader per core** (unless `--no_measure`): the stream the
  stage reads, built by the project's own readers (`pipeline.train_batches`
  over converted videos, `slots.SlotSource`, `tokens.TokenSource`,
  `tasks.vqa.QuestionBatches`; the readout's in-memory gather as
  `tasks.readout.fit` does it), in one child process pinned to one core
  (`--core`; one thread for BLAS / OpenMP / TensorFlow), on fixtures made
  here: OBJ3D-layout videos of moving squares (`reader_speed.py`'s) at the
  dataset's resolution and stored length (OBJ3D 50, CLEVRER 128, PHYRE 15,
  Physion 150 frames: docs/datasets.md), converted by `prepare` (since
  the chunked layout, 2.0.0: a record per 4 frames, so a clip reads only
  its chunks; `benchmarks/clip_reader.py` compares it with the whole-video
  records before), and random slots / tokens of the configs' shapes. From it: host
  cores per chip = need (clips/s) / reader (clips/s per core) / chips per
  host. The script also times whole-video reads of each fixture
  (frames/s) and prints what reading only the clip's frames at that
  per-frame rate would give: the estimate made before the chunked layout,
  kept for comparison with the measured reader.

The evaluation rollout is listed for its need only (it is not a training
step); its reader is not measured. Steps the JSON has no row for (SlotFormer
without L_I on OBJ3D / CLEVRER, with L_I on PHYRE / Physion) are named, with
no floor made up for them.

Run it on an otherwise idle core for numbers you compare; it prints
`uptime` before and after the measurement.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
TPU_JSON = ROOT / 'docs' / 'experiments' / 'tpu_compile.json'

# One host of each platform: the compile topology, chips on the host.
PLATFORMS = {'v5e-8': dict(topology='v5e:2x4', chips_per_host=8),
             'v4-8': dict(topology='v4:2x2x1', chips_per_host=4)}
# NVIDIA H100 SXM5 spec sheet: 1,979 TFLOP/s bf16 Tensor Core "with
# sparsity", half without; 3,350 GB/s HBM3 (the sources are cited in
# docs/performance.md, "Feeding the chips"). 8 per host (HGX boards,
# a3-highgpu-8g, p5.48xlarge).
GPU = dict(name='8x H100 SXM (estimate)', peak_flops=989.4e12,
           hbm_bandwidth=3.35e12, per_host=8)
# The goal: at most this many host cores per chip at 2x the floor.
CORES_PER_CHIP_GOAL = 4
# Frames stored per video by the conversions (docs/datasets.md): the reader
# reads all of them for every clip.
VIDEO_FRAMES = {'obj3d': 50, 'clevrer': 128, 'phyre': 15, 'physion': 150}
# (config, step) pairs, in the order of docs/performance.md's table.
STEPS = (
    ('obj3d', 'savi'), ('obj3d', 'slotformer'), ('obj3d', 'eval_rollout'),
    ('clevrer', 'savi'), ('clevrer', 'slotformer'),
    ('clevrer', 'eval_rollout'), ('clevrer_vqa', 'aloe'),
    ('phyre', 'savi'), ('phyre', 'slotformer'), ('phyre', 'eval_rollout'),
    ('phyre:planning', 'readout'),
    ('physion', 'dvae'), ('physion', 'steve'), ('physion', 'slotformer'),
    ('physion', 'eval_rollout'), ('physion_contact', 'readout'))
# The video config each run config belongs to (for --configs).
FAMILY = {'clevrer_vqa': 'clevrer', 'phyre:planning': 'phyre',
          'physion_contact': 'physion'}


# ---------------------------------------------------------------------------
# The arithmetic (pure; tests/pipeline/test_input_need.py)
# ---------------------------------------------------------------------------


def pick_row(rows: list[dict[str, Any]], config: str, step: str,
             topology: str) -> dict[str, Any] | None:
  """The compiled row of (config, step, topology): bfloat16 if it compiled,
  else float32; None if neither did."""
  by_dtype = {r['dtype']: r for r in rows
              if (r['config'], r['step'], r['topology']) == (config, step,
                                                            topology)
              and r.get('status') == 'compiled' and r.get('floor_seconds')}
  return by_dtype.get('bfloat16') or by_dtype.get('float32')


def need(batch: int, floor_seconds: float, frames_per_clip: int,
         bytes_per_clip: float, slowdown: float = 1.0) -> dict[str, float]:
  """Per-host input rate of a step taking `slowdown` x its floor for a
  global batch of `batch` clips (one host feeds the whole batch)."""
  clips = batch / (floor_seconds * slowdown)
  return dict(clips_per_s=clips, frames_per_s=clips * frames_per_clip,
              mb_per_s=clips * bytes_per_clip / 1e6)


def gpu_floor(row: dict[str, Any], gpus: int, peak_flops: float,
              hbm_bandwidth: float) -> float:
  """Roofline floor (s) of `row`'s program spread over `gpus` GPUs: its
  global FLOPs and bytes (per-chip counts x chips) / gpus against one GPU's
  peaks."""
  flops = row['flops'] * row['chips'] / gpus
  moved = row['bytes_accessed'] * row['chips'] / gpus
  return max(flops / peak_flops, moved / hbm_bandwidth)


def cores_per_chip(clips_per_s: float, reader_clips_per_core: float,
                   chips_per_host: int) -> float:
  """Host cores per chip to deliver `clips_per_s` at the measured rate."""
  return clips_per_s / reader_clips_per_core / chips_per_host


def clip_shape(spec: dict[str, Any], step: str) -> tuple[int, int, int]:
  """(rows per batch, frames per clip, bytes per clip) of a batch spec
  (`{field: object with .shape and .dtype}`; the first axis is the batch).
  Frames: video frames if the batch has video, else slot (feature)
  frames."""
  import numpy as np  # pylint: disable=g-import-not-at-top
  if step == 'aloe':  # open + multiple-choice rows, the same slot frames
    rows = spec['open_slots'].shape[0] + spec['choice_slots'].shape[0]
    frames = spec['open_slots'].shape[1]
  else:
    lead = next(spec[k] for k in ('video', 'slots', 'features') if k in spec)
    rows, frames = lead.shape[0], lead.shape[1]
  total = sum(math.prod(v.shape) * np.dtype(v.dtype).itemsize
              for v in spec.values())
  return rows, frames, total // rows


# ---------------------------------------------------------------------------
# What each step reads
# ---------------------------------------------------------------------------


@dataclasses.dataclass
class Stream:
  """How a step's training reader is built (for the measurement).

  kind: 'clips' (video clips, + STEVE tokens), 'slots', 'slots+video',
  'aloe', 'readout', 'whole_video' (whole videos of a fixture read and
  decompressed, frames/s), or ''
  (not measured)."""
  kind: str
  dataset: str = ''
  resolution: int = 0
  video_frames: int = 0
  clip_length: int = 0
  stride: int = 1
  slot_shape: tuple[int, int] = (0, 0)
  tokens: int = 0
  batch: int = 0
  feature_frames: int = 0
  # 'slots+video': the clip frame the video is read from (L_I reads the
  # rollout's frames only, as stages/dynamics.py does).
  video_from: int = 0

  @property
  def key(self) -> str:
    return json.dumps(dataclasses.asdict(self), sort_keys=True)


def whole_video_stream(s: Stream) -> Stream:
  """Whole-video reads of the fixture that video stream `s` reads."""
  return Stream('whole_video', s.dataset, s.resolution, s.video_frames)


def _benchmarks_on_path() -> None:
  for path in (ROOT, ROOT / 'configs', ROOT / 'benchmarks'):
    if str(path) not in sys.path:
      sys.path.insert(0, str(path))


def describe(config_name: str, step: str) -> dict[str, Any]:
  """The step's batch and stream, from its config (imports the project)."""
  _benchmarks_on_path()
  os.environ.setdefault('JAX_PLATFORMS', 'cpu')
  import tpu_compile  # pylint: disable=g-import-not-at-top
  from slotformer_jax import slot_models  # pylint: disable=g-import-not-at-top
  config = tpu_compile.load_config(config_name)
  batch = tpu_compile.batch_of(config, step)
  spec = tpu_compile.batch_spec(config, step, batch)
  rows, frames, clip_bytes = clip_shape(spec, step)
  dataset = config.data.name
  res = int(config.data.resolution[0])
  stored = VIDEO_FRAMES.get(dataset, 0)
  slot_shape = tuple(slot_models.get(config).slot_shape)
  fields = sorted(spec)
  if step == 'aloe':
    reads = 'slots, question tokens'
  elif step == 'readout':
    reads = 'slot features (in memory)'
  else:
    reads = ', '.join(f for f in ('video', 'tokens', 'slots') if f in spec)
  if step in ('savi', 'dvae', 'steve'):
    length = {'savi': config.savi.clip_length, 'dvae': 1,
              'steve': config.steve.clip_length}[step]
    stream = Stream('clips', dataset, res, stored, length, 1,
                    tokens=(spec['tokens'].shape[2] if 'tokens' in spec
                            else 0), batch=batch)
  elif step == 'slotformer':
    dyn = config.slotformer
    stream = Stream('slots+video' if 'video' in spec else 'slots', dataset,
                    res, stored, dyn.burn_in + dyn.rollout,
                    dyn.frame_stride, slot_shape, batch=batch,
                    video_from=dyn.burn_in if 'video' in spec else 0)
  elif step == 'aloe':
    vqa = config.vqa
    stream = Stream('aloe', dataset, slot_shape=slot_shape, batch=batch,
                    video_frames=vqa.video_length + vqa.rollout_frames)
  elif step == 'readout':
    stream = Stream('readout', dataset, slot_shape=slot_shape, batch=batch,
                    feature_frames=spec['features'].shape[1])
  else:
    stream = Stream('')
  variant = ''
  if step == 'slotformer':
    variant = ('with L_I' if config.slotformer.image_loss_weight > 0
               else 'without L_I')
  return dict(config=config_name, step=step, variant=variant, batch=rows,
              frames_per_clip=frames, bytes_per_clip=clip_bytes,
              fields=fields, reads=reads, stream=stream,
              stochastic=bool(config.savi.get('stochastic', False)),
              slot_model=config.slot_model)


# ---------------------------------------------------------------------------
# The measurement (one child process on one core)
# ---------------------------------------------------------------------------


def _fixture(work: Path, dataset: str, resolution: int, frames: int,
             videos: int):
  """Converted OBJ3D-layout videos of `frames` frames at `resolution`."""
  import reader_speed  # pylint: disable=g-import-not-at-top
  from slotformer_jax import datasets  # pylint: disable=g-import-not-at-top
  from slotformer_jax.config import defaults  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import prepare  # pylint: disable=g-import-not-at-top
  root = work / f'{dataset}_r{resolution}_t{frames}_v{videos}'
  if not (root / 'done').exists():
    if not (root / 'OBJ3D' / 'train').is_dir():
      reader_speed.write_obj3d_like(root / 'OBJ3D', videos,
                                    resolution=resolution, frames=frames)
    prepare.main(['--dataset=obj3d', f'--source={root / "OBJ3D"}',
                  f'--data_dir={root / "data"}', '--splits=train',
                  '--no_progress', '--num_workers=2',
                  f'--resolution={resolution}', f'--num_frames={frames}'])
    (root / 'done').write_text('')
  data = defaults.base_config().data
  data.name, data.data_dir = 'obj3d', str(root / 'data')
  data.resolution = (resolution, resolution)
  return datasets.get_video_source(data, 'train')


def _slot_dir(work: Path, num_videos: int, frames: int, slot_shape,
              seed: int = 0) -> str:
  from slotformer_jax.data import slots  # pylint: disable=g-import-not-at-top
  import numpy as np  # pylint: disable=g-import-not-at-top
  folder = work / f'slots_v{num_videos}_t{frames}_{slot_shape[0]}x{slot_shape[1]}'
  if slots.read_meta(str(folder)) is None or not slots.read_meta(
      str(folder)).get('complete'):
    rng = np.random.default_rng(seed)
    writer = slots.SlotWriter(str(folder), num_videos, *slot_shape,
                              savi_step=0)
    for video in range(num_videos):
      writer.add(video, rng.standard_normal(
          (frames, *slot_shape), dtype=np.float32))
    writer.close()
  return str(folder)


def _token_dir(work: Path, num_videos: int, frames: int, tokens: int) -> str:
  import numpy as np  # pylint: disable=g-import-not-at-top
  folder = work / f'tokens_v{num_videos}_t{frames}_{tokens}'
  from slotformer_jax.data import slots  # pylint: disable=g-import-not-at-top
  meta = slots.read_meta(str(folder))
  if not meta or not meta.get('complete'):
    rng = np.random.default_rng(0)
    writer = slots.TokenWriter(str(folder), num_videos, tokens,
                                    dvae_step=0)
    for video in range(num_videos):
      writer.add(video, rng.integers(0, 4096, (frames, tokens),
                                     dtype=np.uint16))
    writer.close()
  return str(folder)


def prepare_fixtures(streams: list[Stream], work: Path, videos: int) -> None:
  """Makes every fixture the streams read (run before pinning to a core:
  the conversion uses 2 worker processes)."""
  for s in streams:
    if s.kind in ('clips', 'slots+video'):
      _fixture(work, s.dataset, s.resolution, s.video_frames, videos)
    if s.kind in ('slots', 'slots+video'):
      _slot_dir(work, videos, s.video_frames, s.slot_shape)
    if s.kind == 'clips' and s.tokens:
      _token_dir(work, videos, s.video_frames, s.tokens)


def _rate(batches, seconds: float, rows_of) -> float:
  """Rows (clips / questions / examples) per second of an iterator."""
  rows_of(next(batches))  # warm: starts the prefetch thread, opens files
  count, started = 0, time.perf_counter()
  while time.perf_counter() - started < seconds:
    count += rows_of(next(batches))
  return count / (time.perf_counter() - started)


def measure_stream(s: Stream, work: Path, videos: int,
                   seconds: float) -> float:
  """Clips (Aloe: questions; readout: examples) per second that today's
  reader delivers for stream `s`, in this process."""
  import numpy as np  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import pipeline  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import slots  # pylint: disable=g-import-not-at-top
  first_rows = lambda batch: next(iter(batch.values())).shape[0]
  if s.kind == 'whole_video':  # whole videos, random order: frames/s read
    import reader_speed  # pylint: disable=g-import-not-at-top
    return reader_speed.time_random_access(
        _fixture(work, s.dataset, s.resolution, s.video_frames, videos),
        seconds)
  if s.kind in ('clips', 'slots', 'slots+video'):
    fields: tuple[str, ...]
    if s.kind == 'clips':
      source = _fixture(work, s.dataset, s.resolution, s.video_frames, videos)
      fields = ('video',)
      if s.tokens:
        source = slots.TokenSource(
            _token_dir(work, videos, s.video_frames, s.tokens), source)
        fields += ('tokens',)
    else:
      video = (_fixture(work, s.dataset, s.resolution, s.video_frames, videos)
               if s.kind == 'slots+video' else None)
      source = slots.SlotSource(
          _slot_dir(work, videos, s.video_frames, s.slot_shape), video,
          verify=False, video_from=s.video_from)
      fields = ('slots',) + (('video',) if video is not None else ())
    stream = pipeline.train_batches(
        source, batch_size=s.batch, clip_length=s.clip_length, seed=0,
        fields=fields, frame_stride=s.stride)
    try:
      return _rate(stream, seconds, first_rows)
    finally:
      stream.close()
  if s.kind == 'aloe':
    from slotformer_jax.data import vqa as vqa_data  # pylint: disable=g-import-not-at-top
    from slotformer_jax.tasks import vqa as vqa_task  # pylint: disable=g-import-not-at-top
    _benchmarks_on_path()
    import clevrer_vqa  # pylint: disable=g-import-not-at-top
    vqa = clevrer_vqa.get_config().vqa
    path = work / f'vqa_slots_v{videos}_t{s.video_frames}.npy'
    if not path.exists():
      rng = np.random.default_rng(0)
      np.save(path, rng.standard_normal(
          (videos, s.video_frames, *s.slot_shape), dtype=np.float32))
    array = np.load(path, mmap_mode='r')
    length = vqa.max_question_len + vqa.max_choice_len
    choices = vqa.max_choices
    questions = []
    for v in range(videos):  # one open and one multiple-choice per video
      questions.append(vqa_data.EncodedQuestion(
          v, f'v{v}', 2 * v, 0, '', np.zeros((1, length), np.int32),
          np.zeros((1, length), bool), answer=0))
      questions.append(vqa_data.EncodedQuestion(
          v, f'v{v}', 2 * v + 1, 1, '',
          np.zeros((choices, length), np.int32),
          np.zeros((choices, length), bool),
          choice_ids=np.arange(choices, dtype=np.int32),
          choice_labels=np.zeros(choices, np.int32)))
    batches = vqa_task.QuestionBatches(
        questions, lambda name: array[int(name[1:])],
        video_length=vqa.video_length, num_frames=vqa.num_frames,
        stride=vqa.frame_stride, max_choices=choices)
    stream = batches.train_batches(s.batch // 2, s.batch // 2, seed=0)
    return _rate(stream, seconds, lambda b: b['open_slots'].shape[0]
                 + b['choice_slots'].shape[0])
  if s.kind == 'readout':
    rng = np.random.default_rng(0)
    examples = 4 * s.batch
    features = rng.standard_normal(
        (examples, s.feature_frames, *s.slot_shape), dtype=np.float32)
    labels = rng.random(examples, dtype=np.float32)

    def gathers():  # as tasks.readout.fit: a permutation per epoch
      while True:
        order = rng.permutation(examples)
        for i in range(examples // s.batch):
          index = order[i * s.batch:(i + 1) * s.batch]
          yield {'features': features[index], 'labels': labels[index]}
    return _rate(gathers(), seconds, first_rows)
  raise ValueError(f'no measurement for stream kind {s.kind!r}')


def _child_env() -> dict[str, str]:
  env = dict(os.environ)
  for name in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS',
               'TF_NUM_INTRAOP_THREADS', 'TF_NUM_INTEROP_THREADS'):
    env[name] = '1'
  env['JAX_PLATFORMS'] = 'cpu'
  env['PYTHONPATH'] = os.pathsep.join(
      [str(ROOT)] + [p for p in env.get('PYTHONPATH', '').split(os.pathsep)
                     if p])
  return env


def measure_pinned(streams: list[Stream], work: Path, videos: int,
                   seconds: float, core: int, rounds: int = 1
                   ) -> dict[str, float]:
  """{stream key: clips/s, the median over `rounds`} measured by one child
  process pinned to `core` from its start (every thread it makes inherits
  the affinity)."""
  with tempfile.NamedTemporaryFile('w', suffix='.json', delete=False) as f:
    json.dump([dataclasses.asdict(s) for s in streams], f)
    spec_path = f.name
  out_path = spec_path + '.out'
  try:
    subprocess.run(
        [sys.executable, __file__, f'--child={spec_path}',
         f'--child_out={out_path}', f'--workdir={work}',
         f'--videos={videos}', f'--seconds={seconds}',
         f'--rounds={rounds}'],
        env=_child_env(), check=True,
        preexec_fn=lambda: os.sched_setaffinity(0, {core}))
    with open(out_path) as f:
      return json.load(f)
  finally:
    for path in (spec_path, out_path):
      if os.path.exists(path):
        os.unlink(path)


def _child(args) -> None:
  with open(args.child) as f:
    streams = [Stream(**{**d, 'slot_shape': tuple(d['slot_shape'])})
               for d in json.load(f)]
  print(f'reader child: pinned to cores {sorted(os.sched_getaffinity(0))}',
        flush=True)
  measured: dict[str, list[float]] = {s.key: [] for s in streams}
  for round_ in range(args.rounds):  # streams interleaved round by round
    for s in streams:
      rate = measure_stream(s, Path(args.workdir), args.videos, args.seconds)
      measured[s.key].append(rate)
      unit = 'frames/s (whole videos)' if s.kind == 'whole_video' else (
          'questions/s' if s.kind == 'aloe' else 'clips/s')
      print(f'  round {round_ + 1}: {s.kind:11s} {s.dataset:8s} '
            f'clip {s.clip_length:2d} stride {s.stride} '
            f'(videos of {s.video_frames} frames, {s.resolution}px): '
            f'{rate:9.1f} {unit}', flush=True)
  with open(args.child_out, 'w') as f:  # the median over rounds
    json.dump({k: statistics.median(v) for k, v in measured.items()}, f)


# ---------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------


def build_rows(json_rows: list[dict[str, Any]], configs: set[str],
               rates: dict[str, float] | None) -> list[dict[str, Any]]:
  out = []
  for config_name, step in STEPS:
    if FAMILY.get(config_name, config_name.split(':')[0]) not in configs:
      continue
    d = describe(config_name, step)
    stream = d.pop('stream')
    row = dict(d, evaluation=step == 'eval_rollout', platforms={})
    rate = (rates or {}).get(stream.key) if stream.kind else None
    row['reader_clips_per_core'] = rate
    row['reader_frames_per_core'] = (rate * d['frames_per_clip']
                                     if rate else None)
    row['reader_kind'] = stream.kind
    whole = ((rates or {}).get(whole_video_stream(stream).key)
              if stream.kind in ('clips', 'slots+video') else None)
    row['whole_video_frames_per_core'] = whole
    row['video_frames_stored'] = stream.video_frames if whole else None
    # Were only the clip's frames read (at the whole-video rate per frame):
    row['clip_only_clips_per_core'] = (whole / stream.clip_length
                                       if whole else None)
    for platform, p in PLATFORMS.items():
      compiled = pick_row(json_rows, config_name, step, p['topology'])
      if compiled is None:
        row['platforms'][platform] = None
        continue
      chips_per_host = (1 if compiled['chips'] == 1 else p['chips_per_host'])
      entry = dict(dtype=compiled['dtype'],
                   floor_ms=compiled['floor_seconds'] * 1e3,
                   chips_per_host=chips_per_host)
      for label, slowdown in (('floor', 1.0), ('twice', 2.0)):
        entry[label] = need(d['batch'], compiled['floor_seconds'],
                            d['frames_per_clip'], d['bytes_per_clip'],
                            slowdown)
        entry[label]['cores_per_chip'] = (
            cores_per_chip(entry[label]['clips_per_s'], rate,
                           chips_per_host) if rate else None)
        clip_only = row['clip_only_clips_per_core']
        entry[label]['cores_per_chip_clip_only'] = (
            cores_per_chip(entry[label]['clips_per_s'], clip_only,
                           chips_per_host) if clip_only else None)
      row['platforms'][platform] = entry
    v5e = pick_row(json_rows, config_name, step,
                   PLATFORMS['v5e-8']['topology'])
    if v5e is not None:
      gpus = 1 if v5e['chips'] == 1 else GPU['per_host']
      floor = gpu_floor(v5e, gpus, GPU['peak_flops'], GPU['hbm_bandwidth'])
      entry = dict(dtype=v5e['dtype'], floor_ms=floor * 1e3,
                   chips_per_host=gpus)
      for label, slowdown in (('floor', 1.0), ('twice', 2.0)):
        entry[label] = need(d['batch'], floor, d['frames_per_clip'],
                            d['bytes_per_clip'], slowdown)
        entry[label]['cores_per_chip'] = (
            cores_per_chip(entry[label]['clips_per_s'], rate, gpus)
            if rate else None)
        clip_only = row['clip_only_clips_per_core']
        entry[label]['cores_per_chip_clip_only'] = (
            cores_per_chip(entry[label]['clips_per_s'], clip_only, gpus)
            if clip_only else None)
      row['platforms']['gpu'] = entry
    out.append(row)
  return out


def _fmt(value: float | None, digits: int = 0) -> str:
  if value is None:
    return '-'
  if value >= 100 or digits == 0:
    return f'{value:,.0f}'
  return f'{value:.{digits}f}'


def print_report(rows: list[dict[str, Any]]) -> None:
  for row in rows:
    name = f"{row['config']} {row['step']}"
    if row['variant']:
      name += f" ({row['variant']})"
    if row['evaluation']:
      name += ' [evaluation, not a training step]'
    print(f"\n{name}: global batch {row['batch']}, "
          f"{row['frames_per_clip']} frames / clip, "
          f"{row['bytes_per_clip'] / 1e3:.1f} kB / clip "
          f"({', '.join(row['fields'])})")
    rate = row['reader_clips_per_core']
    print('  reader today, one core: ' + (
        f"{rate:,.1f} clips/s = {row['reader_frames_per_core']:,.0f} "
        'frames/s' if rate else 'not measured'))
    if row['whole_video_frames_per_core']:
      print(f"  whole-video reads, one core: "
            f"{row['whole_video_frames_per_core']:,.0f} frames/s of "
            f"{row['video_frames_stored']}-frame videos; reading only the "
            f"clip's frames at that rate: "
            f"{row['clip_only_clips_per_core']:,.1f} clips/s (estimate)")
    for platform in ('v5e-8', 'v4-8', 'gpu'):
      entry = row['platforms'].get(platform)
      label = GPU['name'] if platform == 'gpu' else platform
      if entry is None:
        print(f'  {label:24s} no compiled row in tpu_compile.json')
        continue
      parts = []
      for which, text in (('floor', 'at floor'), ('twice', 'at 2x floor')):
        n = entry[which]
        parts.append(
            f"{text}: {_fmt(n['clips_per_s'])} clips/s, "
            f"{_fmt(n['frames_per_s'])} frames/s, {_fmt(n['mb_per_s'])} MB/s"
            + (f", {_fmt(n['cores_per_chip'], 1)} cores/chip"
               if n['cores_per_chip'] is not None else '')
            + (f" ({_fmt(n['cores_per_chip_clip_only'], 1)} reading only "
               'the clip)' if n['cores_per_chip_clip_only'] is not None
               else ''))
      print(f"  {label:24s} floor {entry['floor_ms']:.2f} ms "
            f"({entry['dtype']} row; {entry['chips_per_host']} chips / host)"
            f"\n    " + '\n    '.join(parts))


def print_markdown(rows: list[dict[str, Any]]) -> None:
  print('| config | step | reads | batch x frames | v5e-8 floor ms (dtype) '
        '| need on v5e-8 at 2x floor: frames/s, MB/s | 8x H100 estimate: '
        'floor ms; need at 2x floor: frames/s, MB/s | reader today: '
        'frames/s per core | host cores / chip at 2x v5e-8 floor | '
        'on 8x H100 | v5e-8, reading only the clip (estimate) |')
  print('|---|---|---|---|---|---|---|---|---|---|---|')
  for row in rows:
    v5e, gpu = row['platforms'].get('v5e-8'), row['platforms'].get('gpu')
    step = row['step'] + (f" ({row['variant']})" if row['variant'] else '')
    if row['evaluation']:
      step += ' (evaluation)'
    cells = [row['config'], step, row['reads'],
             f"{row['batch']} x {row['frames_per_clip']}"]
    if v5e:
      cells += [f"{v5e['floor_ms']:.2f} ({v5e['dtype']})",
                f"{_fmt(v5e['twice']['frames_per_s'])}, "
                f"{_fmt(v5e['twice']['mb_per_s'])}"]
    else:
      cells += ['no row', '-']
    cells.append(f"{gpu['floor_ms']:.2f}; {_fmt(gpu['twice']['frames_per_s'])}"
                 f", {_fmt(gpu['twice']['mb_per_s'])}" if gpu else '-')
    cells.append(_fmt(row['reader_frames_per_core']))
    cells.append(_fmt(v5e['twice']['cores_per_chip'], 1) if v5e else '-')
    cells.append(_fmt(gpu['twice']['cores_per_chip'], 1) if gpu else '-')
    cells.append(_fmt(v5e['twice']['cores_per_chip_clip_only'], 1)
                 if v5e else '-')
    print('| ' + ' | '.join(cells) + ' |')


def main(argv: list[str] | None = None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--configs', default='obj3d,clevrer,phyre,physion',
                      help='video configs (their Aloe / readout included)')
  parser.add_argument('--seconds', type=float, default=3.0,
                      help='seconds of reading per stream')
  parser.add_argument('--videos', type=int, default=24,
                      help='videos per fixture')
  parser.add_argument('--rounds', type=int, default=3,
                      help='measurements per stream (the median is used)')
  parser.add_argument('--core', type=int, default=0,
                      help='the core the reader is measured on')
  parser.add_argument('--workdir', default=None,
                      help='keep the fixtures here (reused when present)')
  parser.add_argument('--no_measure', action='store_true',
                      help='the need only, no reader measurement')
  parser.add_argument('--markdown', action='store_true',
                      help='also print docs/performance.md\'s table')
  parser.add_argument('--json', default=None, help='write the rows here')
  parser.add_argument('--child', default=None, help=argparse.SUPPRESS)
  parser.add_argument('--child_out', default=None, help=argparse.SUPPRESS)
  args = parser.parse_args(argv)
  if args.child:
    _benchmarks_on_path()
    _child(args)
    return
  configs = set(args.configs.split(','))
  json_rows = json.loads(TPU_JSON.read_text())
  rates = None
  if not args.no_measure:
    streams = {}
    for config_name, step in STEPS:
      if FAMILY.get(config_name, config_name.split(':')[0]) in configs:
        s = describe(config_name, step)['stream']
        if s.kind:
          streams[s.key] = s
        if s.kind in ('clips', 'slots+video'):
          w = whole_video_stream(s)
          streams[w.key] = w
    with tempfile.TemporaryDirectory() as tmp:
      work = Path(args.workdir or tmp)
      work.mkdir(parents=True, exist_ok=True)
      prepare_fixtures(list(streams.values()), work, args.videos)
      print('uptime before:', _uptime(), flush=True)
      rates = measure_pinned(list(streams.values()), work, args.videos,
                             args.seconds, args.core, args.rounds)
      print('uptime after: ', _uptime(), flush=True)
  rows = build_rows(json_rows, configs, rates)
  print_report(rows)
  absent = [f"{r['config']} slotformer {'without' if r['variant'] == 'with L_I' else 'with'} L_I"
            for r in rows if r['step'] == 'slotformer']
  if absent:
    print('\nNo compiled row (no floor, no need computed): '
          + '; '.join(absent) + '.')
  over = [f"{r['config']} {r['step']} "
          f"({r['platforms']['v5e-8']['twice']['cores_per_chip']:.1f})"
          for r in rows if r['platforms'].get('v5e-8')
          and not r['evaluation']
          and r['platforms']['v5e-8']['twice']['cores_per_chip'] is not None
          and r['platforms']['v5e-8']['twice']['cores_per_chip']
          > CORES_PER_CHIP_GOAL]
  if rates is not None:
    print(f'\nTraining steps over {CORES_PER_CHIP_GOAL} host cores per chip '
          'at 2x the v5e-8 floor with today\'s reader: '
          + ('; '.join(over) if over else 'none') + '.')
  if args.markdown:
    print()
    print_markdown(rows)
  if args.json:
    Path(args.json).write_text(json.dumps(rows, indent=1))


def _uptime() -> str:
  try:
    return subprocess.run(['uptime'], capture_output=True, text=True,
                          check=False).stdout.strip()
  except OSError:
    return 'load average ' + ' '.join(f'{x:.2f}' for x in os.getloadavg())


if __name__ == '__main__':
  main()
