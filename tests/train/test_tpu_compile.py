"""benchmarks/tpu_compile.py: the real train steps compiled for a TPU.

The compile test needs libtpu (pip install -e '.[tpu]') and is skipped
without it (the default install); the others run everywhere.
"""

import importlib.util
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotformer_jax import slot_models
from slotformer_jax.slot_models import chain
from slotformer_jax.data.slots import SlotSource
from slotformer_jax.data.slots import SlotWriter
from slotformer_jax.slot_models.savi import Savi
from slotformer_jax.stages import dynamics
from slotformer_jax.stages import stage1
from slotformer_jax.runtime import sharding
from tests.pipeline_helpers import load_config
from slotformer_jax.slot_models.steve import build_steve

ROOT = os.path.join(os.path.dirname(__file__), '..', '..')
SCRIPT = os.path.join(ROOT, 'benchmarks', 'tpu_compile.py')


def _benchmark():
  spec = importlib.util.spec_from_file_location('tpu_compile', SCRIPT)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def _source(config, fields, length, num_videos=4):
  """Videos as the stages read them (a list of items works as a source)."""
  rng = np.random.default_rng(0)
  height, width = config.data.resolution
  items = []
  for _ in range(num_videos):
    item = {'video': rng.integers(0, 256, (length, height, width, 3),
                                  np.uint8)}
    if 'tokens' in fields:
      grid = build_steve(config.steve, tuple(config.data.resolution),
                                config.dvae.vocab_size).token_grid
      item['tokens'] = rng.integers(0, 8, (length, grid[0] * grid[1]),
                                    dtype=np.uint16)
    for name, channels in (('flow', 3), ('depth', 1)):
      if name in fields:  # targets.py's contract: float32 [T, H, W, C]
        item[name] = rng.uniform(0, 1, (length, height, width, channels)
                                 ).astype(np.float32)
    if 'boxes' in fields:
      item['boxes'] = rng.uniform(0, 1, (length, fields['boxes'], 4)
                                  ).astype(np.float32)
    if 'slots' in fields:
      num_slots, slot_size = fields['slots']
      item['slots'] = rng.normal(size=(length, num_slots, slot_size)).astype(
          np.float32)
    items.append(item)
  return items


@pytest.mark.parametrize('variant,step', [
    ('tiny', 'savi'), ('tiny', 'slotformer'), ('steve_tiny', 'dvae'),
    ('steve_tiny', 'steve'), ('flow_tiny', 'savi')])
def test_batch_spec_is_what_the_stage_yields(variant, step, tmp_path):
  """The benchmark's abstract batch has the shapes and dtypes of the batch
  the real stage's data stream yields (else it compiles another program)."""
  bench = _benchmark()
  config = load_config('synthetic', variant)
  mesh = sharding.make_mesh()
  length = 12
  fields = {}
  if variant == 'flow_tiny':  # SAVi++'s targets, conditional on the boxes
    config.savi.initial_slots = 'boxes'
    fields = {'flow': 3, 'depth': 1, 'boxes': config.data.max_instances}
  slot_model = slot_models.get(config)
  if step in ('savi', 'dvae'):
    stage = stage1.part_stage(slot_model.part(step), '/unused', mesh,
                              _source(config, fields, length),
                              seed=config.seed)
  elif step == 'steve':
    stage = stage1.part_stage(slot_model.part(step), '/unused', mesh,
                              _source(config, {'tokens': 1}, length),
                              seed=config.seed)
  else:
    # As `Run.slots` serves them to SlotFormer: L_I's video from the
    # rollout's first frame on.
    dyn = config.slotformer
    assert dyn.image_loss_weight > 0  # the video field is checked too
    items = _source(config, {'slots': slot_model.slot_shape},
                    (dyn.burn_in + dyn.rollout) * dyn.frame_stride + 2)
    writer = SlotWriter(str(tmp_path), len(items), *slot_model.slot_shape,
                        savi_step=1)
    for index, item in enumerate(items):
      writer.add(index, item['slots'])
    writer.close()
    source = SlotSource(str(tmp_path), items, ('video',),
                        video_from=dyn.burn_in)
    stage = dynamics.dynamics_stage(
        config.slotformer, 'slotformer', '/unused', mesh, slot_model,
        {'savi': chain.param_shapes(slot_model.part('savi'))}, source,
        seed=config.seed + 1, compute_dtype=config.compute_dtype)
  batch = next(stage.batches(0))
  spec = bench.batch_spec(config, step, stage.config.batch_size)
  assert {k: (v.shape, np.dtype(v.dtype)) for k, v in batch.items()} == {
      k: (v.shape, np.dtype(v.dtype)) for k, v in spec.items()}


def test_without_libtpu_says_so_and_exits_0():
  if importlib.util.find_spec('libtpu') is not None:
    pytest.skip('libtpu is installed: the benchmark would compile')
  result = subprocess.run([sys.executable, SCRIPT], capture_output=True,
                          text=True, timeout=300, check=False)
  assert result.returncode == 0, result.stderr
  assert 'nothing compiled: libtpu is not installed' in result.stdout


def test_unknown_config_is_one_error_line():
  result = subprocess.run([sys.executable, SCRIPT, '--configs=nope'],
                          capture_output=True, text=True, timeout=300,
                          check=False)
  assert result.returncode == 2
  # (pybullet, imported by a data module, prints its build time first.)
  assert result.stderr.strip().splitlines()[-1] == (
      'error: --configs: no configs/nope.py')


def test_tiny_savi_step_compiles_for_a_tpu_slice(tmp_path):
  """With libtpu: the real SAVi train step of the tiny config, through the
  benchmark's own code path, compiled by XLA:TPU for a v5e 2x2 slice."""
  pytest.importorskip('libtpu')
  out = tmp_path / 'rows.json'
  result = subprocess.run(
      [sys.executable, SCRIPT, '--topologies=v5e:2x2',
       '--configs=synthetic:tiny', '--steps=savi', '--dtypes=float32',
       f'--json={out}'],
      capture_output=True, text=True, timeout=1200, check=False,
      env=dict(os.environ, PYTHONPATH=ROOT))
  assert result.returncode == 0, result.stderr[-2000:]
  (row,) = json.loads(out.read_text())
  assert row['status'] == 'compiled' and row['fits']
  assert row['chips'] == 4 and row['batch'] == 4
  assert row['device_kind'] == 'TPU v5 lite'
  assert row['flops'] > 0 and row['bytes_accessed'] > 0
  # The donated state is aliased to the new one: counted once.
  assert row['alias_bytes'] > 0
  assert 0 < row['hbm_bytes'] < row['chip_hbm']


@pytest.mark.parametrize('spec_name', ['slots_with_rollout_video',
                                       'video_only'])
def test_the_fed_step_gets_the_batch_it_was_compiled_for(
    tmp_path, monkeypatch, spec_name):
  """benchmarks/feed_check.py feeds an AOT-compiled step from the real
  reader: the batch must have the step's shapes, also when a slot step's
  video is shorter than its clip (L_I reads the rollout's frames only),
  which once failed as 'Argument types differ'."""
  monkeypatch.syspath_prepend(os.path.join(ROOT, 'benchmarks'))
  import feed_check  # pylint: disable=g-import-not-at-top
  spec = {'video': jax.ShapeDtypeStruct((2, 4, 16, 16, 3), np.uint8)}
  if spec_name == 'slots_with_rollout_video':
    spec = {'slots': jax.ShapeDtypeStruct((2, 6, 3, 4), np.float32),
            **spec}
  mesh = jax.sharding.Mesh(np.array(jax.local_devices()[:1]),
                           (sharding.DATA_AXIS,))

  def step(state, batch, frozen):
    del frozen
    total = sum(jnp.sum(value.astype(jnp.float32))
                for value in batch.values())
    return state + 1, {'loss': total}

  state = jnp.zeros((), jnp.int32)
  compiled = jax.jit(step).lower(state, spec, None).compile()
  result = feed_check.time_fed_vs_resident(
      compiled, state, None, spec, mesh, frame_stride=1, reader_workers=0,
      repeats=2, workdir=tmp_path, num_videos=4)
  assert result['fed_ms'] > 0 and result['resident_ms'] > 0, result
  assert result['verdict'] in ('input-bound', 'compute-bound')


def _run_gpu_check(out_dir, timeout, **env):
  """benchmarks/gpu_check.sh --smoke into `out_dir`, with `env` added. The
  script runs `python`: the one running the tests first on the PATH, not
  whatever the PATH finds first (a venv not activated)."""
  path = os.pathsep.join([os.path.dirname(sys.executable),
                          os.environ.get('PATH', '')])
  return subprocess.run(
      ['bash', os.path.join(ROOT, 'benchmarks', 'gpu_check.sh'), '--smoke',
       str(out_dir)], capture_output=True, text=True, timeout=timeout,
      check=False, env=dict(os.environ, PATH=path, **env))


@pytest.mark.slow
def test_gpu_check_smoke_writes_its_table(tmp_path):
  """benchmarks/gpu_check.sh --smoke on this machine's device (CPU here):
  the cached-compile phase, the timed run and the table, one case; then
  the same step fed by the reader (workers + device prefetch)."""
  result = _run_gpu_check(tmp_path, 1500,
                          GPU_CHECK_CASES='obj3d slotformer',
                          GPU_CHECK_DTYPES='float32',
                          GPU_CHECK_BUDGET_S='1200',
                          GPU_CHECK_CASE_TIMEOUT_S='600',
                          GPU_CHECK_FED_CASES='obj3d slotformer',
                          GPU_CHECK_FED_BUDGET_S='600')
  assert result.returncode == 0, result.stderr[-2000:]
  (row,) = [json.loads(line)
            for line in (tmp_path / 'gpu_check.jsonl').read_text().splitlines()]
  assert 'error' not in row, row
  assert row['step'] == 'slotformer' and row['steps_timed'] == 1
  assert row['median_seconds'] > 0 and row['flops'] > 0
  assert row['tflops_per_second'] == pytest.approx(
      row['flops'] / row['median_seconds'] / 1e12)
  assert np.isfinite(row['loss'])
  # The compile phase filled the persistent cache the timed run read.
  assert any((tmp_path / 'cache').iterdir())
  table = (tmp_path / 'gpu_check.md').read_text()
  assert '| synthetic:tiny | slotformer | float32 | 1 |' in table
  (fed,) = [json.loads(line) for line in
            (tmp_path / 'gpu_check_fed.jsonl').read_text().splitlines()]
  assert fed['reader_workers'] == 2 and fed['fed_ms'] > 0, fed
  assert fed['verdict'] in ('input-bound', 'compute-bound')
  assert f"| synthetic:tiny | slotformer | 2 | {fed['fed_ms']:.1f} |" in table


def test_gpu_check_names_a_case_that_crashed(tmp_path):
  """A case whose process ends without writing its row (here a usage
  error) still gets one, with the exit status and its last line, in the
  JSON rows and the table: the first GPU run must not end in an empty
  table and exit status 0."""
  result = _run_gpu_check(tmp_path, 600,
                          GPU_CHECK_CASES='obj3d no_such_step',
                          GPU_CHECK_DTYPES='float32',
                          GPU_CHECK_FED_CASES='obj3d no_such_step',
                          GPU_CHECK_FED_BUDGET_S='300')
  assert result.returncode == 0, result.stderr[-2000:]
  for name in ('gpu_check.jsonl', 'gpu_check_fed.jsonl'):
    (row,) = [json.loads(line)
              for line in (tmp_path / name).read_text().splitlines()]
    assert row['step'] == 'no_such_step', row
    assert row['error'].startswith('failed (exit 2): '), row
    assert 'invalid choice' in row['error'], row
  table = (tmp_path / 'gpu_check.md').read_text()
  assert table.count('failed (exit 2)') == 2, table
  # Each case's whole stderr is kept beside the rows.
  for name in ('obj3d_no_such_step_float32.txt', 'fed_obj3d_no_such_step.txt'):
    assert 'invalid choice' in (tmp_path / 'stderr' / name).read_text()


@pytest.mark.parametrize('name', ['synthetic_vqa', 'synthetic_contact:tiny',
                                  'synthetic_phyre:tiny'])
def test_downstream_steps_lower_on_this_machine(name):
  """Aloe's train step and the readouts' (the benchmark's `aloe` /
  `readout` rows) build and lower through the project's code; a CPU mesh
  stands in for the TPU slice."""
  bench = _benchmark()
  step = bench.DOWNSTREAM[name][0]
  config = bench.configured(bench.config_of(name, step), 'float32', '')
  assert step in bench.steps_of(config, name)
  run, args = bench.step_program(config, step, sharding.make_mesh())
  assert 'dot_general' in run.lower(*args).as_text()


def test_aloe_batch_spec_is_what_the_question_stream_yields():
  """The abstract Aloe batch has the keys, shapes and dtypes of a batch of
  `QuestionBatches.train_batches` over real embedded questions."""
  bench = _benchmark()
  config = load_config('synthetic_vqa', 'tiny')
  vqa = config.vqa
  from slotformer_jax.data import vqa_questions  # pylint: disable=g-import-not-at-top
  from slotformer_jax.tasks import vqa as vqa_task  # pylint: disable=g-import-not-at-top
  from pipeline_helpers import prepare_data  # pylint: disable=g-import-not-at-top
  prepare_data(config)  # the embedded questions (reading only opens them)
  vocab = vqa_questions.vocabulary(config)
  questions = vqa_questions.encoded_questions(config, 'train', vocab)
  num_slots, slot_size = Savi(config).slot_shape
  slots = np.zeros((vqa.video_length + vqa.rollout_frames, num_slots,
                    slot_size), np.float32)
  batches = vqa_task.QuestionBatches(
      questions, lambda name: slots, video_length=vqa.video_length,
      num_frames=vqa.num_frames, stride=vqa.frame_stride,
      max_choices=vqa.max_choices)
  batch = next(batches.train_batches(vqa.open_batch_size,
                                     vqa.choice_batch_size, seed=0))
  spec = bench.batch_spec(config, 'aloe', bench.batch_of(config, 'aloe'))
  assert {k: (v.shape, np.dtype(v.dtype)) for k, v in batch.items()} == {
      k: (v.shape, np.dtype(v.dtype)) for k, v in spec.items()}


@pytest.mark.parametrize('hbm_of,largest', [
    # HBM linear in the per-chip batch: 1 GiB + 0.25 GiB per example.
    (lambda b: (1 + 0.25 * b) * 2**30, 60),
    # Not monotonic near the limit: 52-55 need more than 56-60.
    (lambda b: (17 if 52 <= b <= 55 else 1 + 0.25 * b) * 2**30, 60),
    # A fixed part larger than the per-example one, refused far above.
    (lambda b: (6 + 0.01 * b) * 2**30 if b < 5000 else 40 * 2**30, 1000),
])
def test_largest_batch_search_brackets_the_limit(monkeypatch, hbm_of,
                                                 largest):
  """The search reports a batch that fits and one above it that does not,
  within the tolerance, in a bounded number of compiles."""
  bench = _benchmark()
  compiled = []

  def fake_hbm(config, step, mesh, chip):
    per_chip = config.savi.batch_size // 4
    compiled.append(per_chip)
    return int(hbm_of(per_chip))

  monkeypatch.setattr(bench, '_hbm_or_required', fake_hbm)
  chip = dict(hbm=16 * 2**30)
  mesh = np.empty((4,))  # only its size is read

  class FakeMesh:
    devices = mesh
  config = load_config('synthetic', 'tiny')
  out = bench.largest_batch(config, 'savi', FakeMesh(), chip, lambda _: None,
                            known={2: int(hbm_of(2))}, tolerance=0.1,
                            max_compiles=12)
  low, high = out['largest_per_chip'], out['smallest_not_fitting']
  assert hbm_of(low) <= chip['hbm'] < hbm_of(high)
  assert low < high <= max(low + 1, low * 1.1)
  assert low <= largest
  assert out['search_compiles'] == len(compiled) <= 12
  assert len(set(compiled)) == len(compiled)  # no batch compiled twice


def test_table_merges_rows_and_keeps_a_search(tmp_path):
  """benchmarks/tpu_compile_table.py: a later file's row wins; a plain
  recompile of the same program keeps the earlier row's largest batch."""
  spec = importlib.util.spec_from_file_location(
      'tpu_compile_table', os.path.join(ROOT, 'benchmarks',
                                        'tpu_compile_table.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  row = dict(topology='v5e:2x4', config='obj3d', step='savi',
             dtype='float32', chips=8, batch=64, status='compiled',
             fits=True, hbm_bytes=2 * 2**30, chip_hbm=16 * 2**30,
             flops=1.3e12, bytes_accessed=15e9, floor_seconds=15e9 / 819e9,
             compile_seconds=50.0, device_kind='TPU v5 lite')
  searched = dict(row, largest_per_chip=40, smallest_not_fitting=44,
                  tried={'8': 1, '40': 2, '44': 3}, search_compiles=3)
  failed = dict(row, step='slotformer', status='compile failed',
                why='some XLA error')
  (tmp_path / 'a.json').write_text(json.dumps([searched]))
  (tmp_path / 'b.json').write_text(json.dumps([dict(row, compile_seconds=9.0),
                                               failed]))
  rows = module.merge([str(tmp_path / 'a.json'), str(tmp_path / 'b.json')])
  assert [r['step'] for r in rows] == ['savi', 'slotformer']
  assert rows[0]['compile_seconds'] == 9.0
  assert rows[0]['largest_per_chip'] == 40
  table = module.table(rows).splitlines()
  assert '| 40 (not 44) |' in table[2] and '| bytes 2.8x |' in table[2]
  assert 'compile failed: some XLA error' in table[3]
  # K seeds are rows of their own, shown beside the one-seed row.
  seeds = dict(row, seeds=4, mesh={'seed': 4, 'data': 2},
               hbm_bytes=3 * 2**30, floor_seconds=4 * row['floor_seconds'],
               floor_per_seed_seconds=row['floor_seconds'])
  (tmp_path / 'c.json').write_text(json.dumps([seeds]))
  rows = module.merge([str(tmp_path / 'b.json'), str(tmp_path / 'c.json')])
  assert len(rows) == 3
  one, four = module.seeds_table(rows).splitlines()[2:]
  assert '| savi | v5e:2x4 | float32 | 1 | 64 |' in one
  assert '| 4 (4 seed x 2 data) | 64 | yes | 3.00 (1.50x) |' in four
  assert f"| {seeds['floor_seconds'] * 1e3:.2f} (4.00x) |" in four


@pytest.mark.parametrize('name', ['synthetic_vqa', 'synthetic_contact:tiny'])
def test_float32_only_steps_have_no_bfloat16_row(name):
  """Aloe and the readouts ignore compute_dtype: a bfloat16 row would be
  the float32 program under another name, so it is 'not built'."""
  bench = _benchmark()
  step = bench.DOWNSTREAM[name][0]
  config = bench.configured(name, 'bfloat16', '')
  row = bench.one_row(config, name, step, 'bfloat16', 'cpu',
                      sharding.make_mesh(), dict(hbm=2**34), None, print)
  assert row['status'] == 'not built'
  assert 'computes in float32' in row['why']


@pytest.mark.parametrize('dtype', ['float32', 'bfloat16'])
def test_eval_rollout_lowers_when_slotformer_batch_does_not_split(dtype):
  """The benchmark's eval_rollout row on a mesh that SlotFormer's training
  batch does not split over (a 256-chip slice, batch 128, failed before):
  the dynamics stage is only read for its parameter shapes."""
  bench = _benchmark()
  config = bench.configured('synthetic:tiny', dtype, '')
  mesh = sharding.make_mesh()
  config.slotformer.batch_size = mesh.devices.size + 1  # does not split
  run, args = bench.step_program(
      bench.with_batch(config, 'eval_rollout', mesh.devices.size),
      'eval_rollout', mesh)
  assert 'conv' in run.lower(*args).as_text()


@pytest.mark.parametrize('value', ['0', 'two', ''])
def test_seeds_flag_is_checked(value, capsys):
  assert _benchmark().main([f'--seeds={value}']) == 2
  assert 'error: --seeds' in capsys.readouterr().err


def test_several_seed_programs_are_the_trainers():
  """`--seeds=K`: the program `trainer.fit` runs for config.seeds, on the
  (seed, data) mesh it makes (2 x 2 on the 4 CPU devices): the SeedsState
  split on 'seed'; stage 1's first part on the shared [B, ...] batch,
  STEVE and SlotFormer on stacked [K, B, ...] batches, SlotFormer with [K,
  ...] frozen decoder parameters. What the pipeline refuses or runs per
  seed is not built."""
  from jax.sharding import PartitionSpec as P  # pylint: disable=g-import-not-at-top
  bench = _benchmark()
  mesh = sharding.make_mesh()
  config = bench.configured('synthetic:tiny', 'float32', '')
  batch_size = config.savi.batch_size
  _, args = bench.step_program(config, 'savi', mesh, num_seeds=2)
  state, batch, frozen = args
  assert dict(state.step.sharding.mesh.shape) == {'seed': 2, 'data': 2}
  assert state.step.shape == state.diverged_at.shape == (2,)
  for leaf in jax.tree.leaves(state.params):
    assert leaf.shape[0] == 2 and leaf.sharding.spec == P('seed')
  assert batch['video'].shape[0] == batch_size
  assert batch['video'].sharding.spec == P('data')
  assert frozen is None
  _, (state, batch, frozen) = bench.step_program(config, 'slotformer', mesh,
                                                 num_seeds=2)
  dyn = config.slotformer
  assert batch['slots'].shape[:3] == (2, dyn.batch_size,
                                      dyn.burn_in + dyn.rollout)
  assert batch['video'].shape[:3] == (2, dyn.batch_size, dyn.rollout)
  assert batch['slots'].sharding.spec == P('seed', 'data')
  for leaf in jax.tree.leaves(frozen):
    assert leaf.shape[0] == 2 and leaf.sharding.spec == P('seed')
  assert bench.several_seeds_refused(config, 'savi', 2) is None
  assert 'one seed at a time' in bench.several_seeds_refused(
      config, 'eval_rollout', 2)
  steve = bench.configured('synthetic:steve_tiny', 'float32', '')
  assert bench.several_seeds_refused(steve, 'dvae', 2) is None
  assert bench.several_seeds_refused(steve, 'steve', 2) is None
  _, (_, batch, frozen) = bench.step_program(steve, 'steve', mesh,
                                             num_seeds=2)
  assert batch['tokens'].shape[:2] == (2, steve.steve.batch_size)
  assert batch['tokens'].sharding.spec == P('seed', 'data')
  assert frozen is None
