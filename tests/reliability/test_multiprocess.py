"""Two processes on localhost as one run (`jax.distributed`, gloo CPU
collectives, one CPU device each, one shared workdir), SAVi's micro config:

* SIGTERM to both, or to one only: both save the step they agree on and exit
  143 (with `stop_check_every=5`: a multiple of 5), and the rerun ends
  bit-identical to an uninterrupted two-process run;
* SIGKILL of one: the other names it in one line and exits within the
  heartbeat timeout; the rerun (past a leftover orbax temporary folder) ends
  bit-identical too;
* training: the per-step metrics of two processes equal those of one process
  with two devices (every host reads its rows of one global batch plan,
  `data.pipeline.train_batches`);
* more processes than videos in a split: two processes train SAVi and
  SlotFormer, extract the slots and evaluate, and the training logs and
  metrics equal those of one process with two devices.

    python -m pytest -q tests/reliability/test_multiprocess.py          # fast one
    python -m pytest -q -m slow tests/reliability/test_multiprocess.py  # all

The default run: the SIGTERM-to-one test, the flag checks, the watchdog's
verdicts and the stop-agreement decision (unit tests without processes).
"""

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time

import jax
import numpy as np
import pytest

from slotformer_jax.config import checks
from slotformer_jax.errors import ConfigError
from slotformer_jax.runtime import processes
from slotformer_jax.runtime import sharding
from slotformer_jax.train import trainer
from slotformer_jax.runtime.checkpoint import Checkpointer

import pipeline_helpers
from slotformer_jax.workdir import identity as identity_lib
from pipeline_helpers import accept
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.run import Run

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), '..', '..'))
SYNTHETIC = os.path.join(ROOT, 'configs', 'synthetic.py') + ':tiny'
PEER_TIMEOUT = 10  # seconds (--peer_timeout)

# pipeline_helpers' SAVi micro config, as command-line overrides.
MICRO = [
    '--config.data.resolution=(16,16)', '--config.data.num_frames=8',
    '--config.data.num_train=8', '--config.data.num_val=4',
    '--config.data.num_test=4',
    '--config.savi.decoder.features=(8,8)',
    '--config.savi.encoder.features=(8,8)',
    '--config.savi.encoder.strides=(1,1)',
    '--config.savi.log_every=1', '--config.savi.checkpoint_every=1000',
]


def _free_port():
  with socket.socket() as s:
    s.bind(('localhost', 0))
    return s.getsockname()[1]


def _env(data_dir, devices=1):
  env = dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS='cpu',
             SLOTFORMER_DATA_DIR=str(data_dir),
             # Shared by every run here: a rerun's steps are cache hits.
             JAX_COMPILATION_CACHE_DIR=os.path.join(
                 tempfile.gettempdir(), 'slotformer_jax_test_xla_cache_mp'))
  env.pop('XLA_FLAGS', None)
  if devices > 1:
    env['XLA_FLAGS'] = f'--xla_force_host_platform_device_count={devices}'
  return env


def _command(workdir, steps, mode='train_savi', extra=()):
  return [sys.executable, '-m', 'slotformer_jax.main', f'--config={SYNTHETIC}',
          f'--workdir={workdir}', f'--mode={mode}', *MICRO,
          f'--config.savi.num_train_steps={steps}', *extra]


class Run:
  """N processes of one run; stderr of process i in <workdir>.<i>.log."""

  def __init__(self, workdir, data_dir, steps, num_processes=2, extra=(),
               mode='train_savi'):
    port = _free_port()
    self.logs = [f'{workdir}.{i}.log' for i in range(num_processes)]
    self.processes = []
    for i in range(num_processes):
      command = _command(workdir, steps, mode, extra=(
          f'--coordinator_address=localhost:{port}',
          f'--num_processes={num_processes}', f'--process_id={i}',
          f'--peer_timeout={PEER_TIMEOUT}', *extra))
      with open(self.logs[i], 'w') as log:
        self.processes.append(subprocess.Popen(
            command, env=_env(data_dir), stdout=log, stderr=log))

  def log(self, i):
    with open(self.logs[i]) as f:
      return f.read()

  def wait_for(self, text, i=0, timeout=600):
    deadline = time.time() + timeout
    while text not in self.log(i):
      assert time.time() < deadline, self.log(i)[-3000:]
      assert self.processes[i].poll() is None, self.log(i)[-3000:]
      time.sleep(0.2)

  def wait(self, timeout=600):
    try:
      return [p.wait(timeout=timeout) for p in self.processes]
    finally:
      for p in self.processes:
        if p.poll() is None:
          p.kill()


def _finished(run):
  statuses = run.wait()
  assert statuses == [0] * len(statuses), [run.log(i)[-3000:]
                                           for i in range(len(statuses))]


def _params(workdir, data_dir):
  """(step, {path: array}) of the newest SAVi checkpoint."""
  config = pipeline_helpers.micro_config('savi', data_dir)
  config.savi.num_train_steps = STEPS
  loaded = Run.create(config, str(workdir), sharding.make_mesh()).stage1
  params, step = loaded.params, loaded.step
  leaves = jax.tree_util.tree_flatten_with_path(params)[0]
  return step, {jax.tree_util.keystr(k): np.asarray(v) for k, v in leaves}


def _assert_same_params(a, b, data_dir):
  (step_a, a), (step_b, b) = _params(a, data_dir), _params(b, data_dir)
  assert step_a == step_b == STEPS and a.keys() == b.keys()
  for key in a:
    np.testing.assert_array_equal(a[key], b[key], err_msg=key)


STEPS = 12


@pytest.fixture(scope='module')
def data_dir(tmp_path_factory):
  return tmp_path_factory.mktemp('multiprocess_data')


@pytest.fixture(scope='module')
def uninterrupted(data_dir, tmp_path_factory):
  workdir = str(tmp_path_factory.mktemp('uninterrupted') / 'run')
  _finished(Run(workdir, data_dir, STEPS))
  return workdir


# --------------------------------------------------------------------------
# without processes
# --------------------------------------------------------------------------


def test_explicit_flags_go_together():
  assert not processes.check_flags(None, None, None)
  assert processes.check_flags('localhost:1234', 2, 1)
  with pytest.raises(ConfigError, match='missing --num_processes, '
                     '--process_id'):
    processes.check_flags('localhost:1234', None, None)
  with pytest.raises(ConfigError, match='needs a port'):
    processes.check_flags('localhost', 2, 0)
  with pytest.raises(ConfigError, match=r'must be in \[0, '):
    processes.check_flags('localhost:1234', 2, 2)


def test_processes_agree_on_a_stop_every_k_steps(monkeypatch):
  agreements = []

  def agreed_signal(local_signal):
    agreements.append(local_signal)
    return local_signal, [0] if local_signal else []

  monkeypatch.setattr(processes, 'agreed_signal', agreed_signal)
  term = trainer._TermFlag()
  term.received = signal.SIGTERM  # before update 1
  monkeypatch.setattr(jax, 'process_count', lambda: 2)
  stops = [trainer._stop_signal(term, done, 12, every=5)[0]
           for done in range(1, 13)]
  # Only after updates 5, 10 and the last (12) do the processes agree.
  assert agreements == [signal.SIGTERM] * 3
  assert [d for d, stop in enumerate(stops, 1) if stop] == [5, 10, 12]
  assert [trainer.agrees_after(d, 12, 1) for d in range(1, 13)] == [True] * 12
  # One process: its own flag after every update, no collective.
  agreements.clear()
  monkeypatch.setattr(jax, 'process_count', lambda: 1)
  assert [trainer._stop_signal(term, d, 12, every=5)[0]
          for d in (1, 2, 3)] == [signal.SIGTERM] * 3
  assert agreements == []


def test_stop_check_every_is_checked_and_not_part_of_a_run(tmp_path):
  config = pipeline_helpers.micro_config('savi', tmp_path / 'data')
  assert config.savi.stop_check_every == 1
  config.savi.stop_check_every = 0
  assert checks.check_field_kinds(config) == [
      'savi.stop_check_every must be an integer >= 1, got 0']
  config.savi.stop_check_every = 5
  assert 'stop_check_every' not in identity_lib.stage_fields(
      config.seed, config.data.to_dict(), 'savi',
      config.savi.to_dict())['savi']
  # A workdir from before the field existed stays usable.
  saved = config.to_dict()
  for section in saved.values():
    if isinstance(section, dict):
      section.pop('stop_check_every', None)
  with open(Paths.of(str(tmp_path)).config_file, 'w') as f:
    json.dump(saved, f, default=list)
  assert accept(config, str(tmp_path)) == []


def test_a_partial_set_of_flags_is_one_line(tmp_path):
  result = subprocess.run(
      _command(tmp_path / 'run', 2, extra=('--num_processes=2',)),
      env=_env(tmp_path / 'data'), capture_output=True, text=True,
      timeout=300)
  assert result.returncode == 1 and 'Traceback' not in result.stderr
  # (Other lines: libraries that print on import, e.g. pybullet's banner.)
  assert [line for line in result.stderr.splitlines()
          if line.startswith('error:')] == [
      'error: --coordinator_address, --num_processes and --process_id go '
      'together; missing --coordinator_address, --process_id (or give none '
      'of them to let jax.distributed detect the cluster)'], result.stderr


WATCH = '''
import sys, time
from slotformer_jax.runtime import processes
index, peer_exit = int(sys.argv[2]), sys.argv[3]
dog = processes.PeerWatchdog(sys.argv[1], index, 2, timeout=2,
                             interval=0.2).start()
if index == 1:
  if peer_exit == 'kill':
    time.sleep(1)
    raise SystemExit(0)  # dies without saying how: as after SIGKILL
  time.sleep(1)
  dog.finish(int(peer_exit))
  raise SystemExit(int(peer_exit))
time.sleep(8)
dog.finish(0)
print('survived')
'''


@pytest.mark.parametrize('peer_exit, status, line', [
    ('kill', 1, 'error: process 1 of 2 is lost (no heartbeat for 2 s'),
    ('1', 1, 'error: process 1 of 2 ended with exit status 1'),
    ('143', 0, 'survived'),
    ('0', 0, 'survived'),
])
def test_the_watchdog_names_a_lost_process(tmp_path, peer_exit, status, line):
  run = [subprocess.Popen(
      [sys.executable, '-c', WATCH, str(tmp_path), str(i), peer_exit],
      env=dict(os.environ, PYTHONPATH=ROOT), stdout=subprocess.PIPE,
      stderr=subprocess.STDOUT, text=True) for i in (0, 1)]
  run[1].wait(timeout=60)
  peer_ended = time.time()
  out, _ = run[0].communicate(timeout=60)
  assert run[0].returncode == status, out
  assert out.strip().splitlines()[0].startswith(line), out
  assert len(out.strip().splitlines()) == 1, out
  if status:  # within the timeout (2 s) of the peer's last sign of life
    assert time.time() - peer_ended < 2 + 3, time.time() - peer_ended


# --------------------------------------------------------------------------
# two processes
# --------------------------------------------------------------------------


@pytest.mark.parametrize('to, every', [
    pytest.param('one', 1, id='sigterm_to_one'),
    pytest.param('both', 1, id='sigterm_to_both', marks=pytest.mark.slow),
    pytest.param('one', 5, id='sigterm_to_one_every_5',
                 marks=pytest.mark.slow),
])
def test_sigterm_stops_both_processes_after_the_same_step(
    data_dir, tmp_path, to, every):
  workdir = str(tmp_path / 'run')
  run = Run(workdir, data_dir, 200,
            extra=[f'--config.savi.stop_check_every={every}'])
  run.wait_for('savi step 2:', i=1)
  targets = run.processes[1:] if to == 'one' else run.processes
  for process in targets:
    process.send_signal(signal.SIGTERM)
  assert run.wait(timeout=300) == [143, 143], [run.log(0), run.log(1)]
  stops = []
  for i in (0, 1):
    lines = [line for line in run.log(i).splitlines()
             if line.startswith(('preempted:', 'error:', 'Traceback'))]
    assert len(lines) == 1 and lines[0].startswith('preempted: savi: '
                                                   'stopped by SIGTERM to '
                                                   'process '), run.log(i)
    stops.append(lines[0].split('after step ')[1].split(';')[0])
  assert stops[0] == stops[1], stops
  steps = Checkpointer(os.path.join(workdir, 'savi', 'checkpoints'),
                       read_only=True).all_steps()
  assert steps == [int(stops[0])] and 2 <= steps[0] < 200, (steps, stops)
  assert steps[0] % every == 0, steps  # processes agree every `every` steps


@pytest.mark.slow
@pytest.mark.parametrize('to', ['one', 'both'])
def test_the_rerun_after_sigterm_is_bit_exact(data_dir, uninterrupted,
                                              tmp_path, to):
  workdir = str(tmp_path / 'run')
  run = Run(workdir, data_dir, STEPS)
  run.wait_for('savi step 3:', i=0)
  for process in run.processes[1:] if to == 'one' else run.processes:
    process.send_signal(signal.SIGTERM)
  statuses = run.wait(timeout=300)
  # A signal after the last step's agreement lets the run finish (0).
  assert statuses in ([143, 143], [0, 0]), [run.log(0), run.log(1)]
  _finished(Run(workdir, data_dir, STEPS))
  _assert_same_params(workdir, uninterrupted, data_dir)


@pytest.mark.slow
def test_sigkill_of_one_process_stops_the_other_with_one_line(
    data_dir, uninterrupted, tmp_path):
  workdir = str(tmp_path / 'run')
  # Checkpoints every 4 steps, so the rerun resumes from one.
  run = Run(workdir, data_dir, STEPS,
            extra=['--config.savi.checkpoint_every=4'])
  run.wait_for('savi step 5:', i=0)
  run.processes[1].kill()
  killed = time.time()
  status = run.processes[0].wait(timeout=120)
  took = time.time() - killed
  print(f'the survivor stopped {took:.1f} s after the kill')
  log = run.log(0)
  assert status == processes.LOST_PROCESS_EXIT, log
  assert took < PEER_TIMEOUT + 15, took
  assert 'Traceback' not in log and 'Fatal' not in log, log
  errors = [line for line in log.splitlines() if line.startswith('error:')]
  assert len(errors) == 1 and errors[0].startswith(
      'error: process 1 of 2 is lost'), log
  # As a save cut short by the kill leaves it: the rerun must not mind.
  checkpoints = os.path.join(workdir, 'savi', 'checkpoints')
  os.makedirs(os.path.join(checkpoints, '7.orbax-checkpoint-tmp-0', 'default'),
              exist_ok=True)
  _finished(Run(workdir, data_dir, STEPS))
  _assert_same_params(workdir, uninterrupted, data_dir)


def _train_log(workdir, stage='savi'):
  """{step: {metric: value}} of a stage's train_log.jsonl, timing left out."""
  with open(os.path.join(workdir, stage, 'train_log.jsonl')) as f:
    rows = [json.loads(line) for line in f]
  return {row.pop('step'): {k: v for k, v in row.items()
                            if k != 'steps_per_second'} for row in rows}


@pytest.mark.slow
def test_two_processes_train_as_one_process_with_two_devices(
    data_dir, uninterrupted, tmp_path):
  """The global batch of a step does not depend on how it is split over
  hosts (`data.pipeline.train_batches`), so 2 processes x 1 device and
  1 process x 2 devices log the same losses, step by step."""
  workdir = str(tmp_path / 'run')
  result = subprocess.run(_command(workdir, STEPS),
                          env=_env(data_dir, devices=2), capture_output=True,
                          text=True, timeout=600)
  assert result.returncode == 0, result.stderr[-3000:]
  one, two = _train_log(workdir), _train_log(uninterrupted)
  assert sorted(one) == sorted(two) == list(range(1, STEPS + 1))
  worst = 0.0
  for step in one:
    assert one[step].keys() == two[step].keys(), step
    for key in sorted(one[step], key=lambda k: (k != 'loss', k)):
      value = one[step][key]
      np.testing.assert_allclose(two[step][key], value, rtol=1e-5,
                                 err_msg=f'step {step} {key}')
      worst = max(worst, abs(two[step][key] - value) / max(abs(value), 1e-30))
  print(f'step 1 loss: {two[1]["loss"]!r} (2 processes), {one[1]["loss"]!r} '
        f'(1 process); largest relative difference {worst:.3g}')


# pipeline_helpers' micro SlotFormer, as overrides; one validation and one
# test video, fewer than the two processes.
FEW_VIDEOS = [
    '--config.data.num_val=1', '--config.data.num_test=1',
    '--config.slotformer.burn_in=2', '--config.slotformer.rollout=2',
    '--config.slotformer.num_train_steps=2', '--config.slot_lstm.train=False',
    '--config.extraction.chunk_length=4', '--config.extraction.batch_size=2',
    '--config.evaluation.rollout_steps=6', '--config.evaluation.batch_size=2',
    '--config.evaluation.chunk_length=4',
    "--config.evaluation.metrics=('psnr','ari')",
    '--config.evaluation.savi_metrics=False',
]


MODES = ('train_savi', 'extract_slots', 'train_slotformer', 'evaluate')


def _numbers(tree, prefix=''):
  """{path: float} of every number in a JSON tree, 'identity' left out."""
  if isinstance(tree, dict):
    out = {}
    for key, value in tree.items():
      if key != 'identity':
        out.update(_numbers(value, f'{prefix}/{key}'))
    return out
  if isinstance(tree, list):
    out = {}
    for i, value in enumerate(tree):
      out.update(_numbers(value, f'{prefix}/{i}'))
    return out
  if isinstance(tree, (int, float)) and not isinstance(tree, bool):
    return {prefix: float(tree)}
  return {}


def _metrics(workdir):
  with open(os.path.join(workdir, 'eval', 'metrics.json')) as f:
    return _numbers(json.load(f))


@pytest.mark.slow
def test_more_processes_than_videos_extract_and_evaluate(data_dir, tmp_path):
  """One process with two devices, then two processes, train SAVi and
  SlotFormer, extract the slots (one video per split for two processes) and
  evaluate: the same training logs and metrics."""
  few_data = tmp_path / 'few_data'
  one_process = str(tmp_path / 'one')
  env = _env(few_data, devices=2)
  for mode in MODES:
    result = subprocess.run(_command(one_process, 2, mode, FEW_VIDEOS),
                            env=env, capture_output=True, text=True,
                            timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
  two_processes = str(tmp_path / 'two')
  for mode in MODES:
    _finished(Run(two_processes, few_data, 2, mode=mode, extra=FEW_VIDEOS))
  for stage in ('savi', 'slotformer'):
    one, two = _train_log(one_process, stage), _train_log(two_processes,
                                                           stage)
    assert one.keys() == two.keys() and one, (stage, one, two)
    for step in one:
      for key in one[step]:
        np.testing.assert_allclose(two[step][key], one[step][key], rtol=1e-5,
                                   err_msg=f'{stage} step {step} {key}')
  one, two = _metrics(one_process), _metrics(two_processes)
  assert one.keys() == two.keys() and one, (one, two)
  for key in one:
    if 'time' not in key and 'seconds' not in key:
      np.testing.assert_allclose(two[key], one[key], rtol=1e-4, atol=1e-6,
                                 err_msg=key)


LATE = '''
import os, sys, time
from slotformer_jax.runtime import processes
index, delay = int(sys.argv[2]), float(sys.argv[3])
if index == 1:
  if delay < 0:
    raise SystemExit(0)  # never starts its watchdog
  # `delay` after process 0's watchdog started, whatever the imports took.
  while not os.path.exists(os.path.join(sys.argv[1], '0')):
    time.sleep(0.01)
  time.sleep(delay)
dog = processes.PeerWatchdog(sys.argv[1], index, 2, timeout=1, interval=0.2,
                             startup_timeout=4).start()
time.sleep(6 if index == 0 else 6 - delay)
dog.finish(0)
print('survived')
'''


@pytest.mark.parametrize('delay, status, line', [
    (2.5, 0, 'survived'),  # starts after `timeout`, within `startup_timeout`
    (-1, 1, 'error: process 1 of 2 never started (no heartbeat within 4 s)'),
])
def test_the_watchdog_waits_for_a_peer_slow_to_start(tmp_path, delay, status,
                                                     line):
  """A peer that has not written its first heartbeat (a loaded host still
  importing) is not 'lost' after `timeout`, only after `startup_timeout`.
  Before the grace, process 0 declared process 1 lost when it started more
  than `timeout` later."""
  run = [subprocess.Popen(
      [sys.executable, '-c', LATE, str(tmp_path), str(i), str(delay)],
      env=dict(os.environ, PYTHONPATH=ROOT), stdout=subprocess.PIPE,
      stderr=subprocess.STDOUT, text=True) for i in (0, 1)]
  run[1].communicate(timeout=60)
  out, _ = run[0].communicate(timeout=60)
  assert run[0].returncode == status, out
  assert out.strip().splitlines()[0].startswith(line), out
