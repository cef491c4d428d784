"""Kill and preemption checks that run real processes (minutes).

    python -m pytest -q -m slow tests/reliability/test_reliability_slow.py

* SIGTERM during training saves the current step and exits 143 (Ctrl-C,
  SIGINT: the same, exit 130); the rerun finishes with parameters
  bit-identical to an uninterrupted run.
* Killing the synthetic-data generation (kill -9) takes its worker
  processes with it, and the rerun leaves no `incomplete.*` folder.
"""

import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from slotformer_jax.runtime import sharding
from slotformer_jax.run import Run
from slotformer_jax.runtime.checkpoint import Checkpointer

import pipeline_helpers

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), '..', '..'))
SYNTHETIC = os.path.join(ROOT, 'configs', 'synthetic.py') + ':tiny'

pytestmark = pytest.mark.slow

# pipeline_helpers' SAVi micro config, as command-line overrides.
MICRO = [
    '--config.data.resolution=(16,16)', '--config.data.num_frames=8',
    '--config.data.num_train=8', '--config.data.num_val=4',
    '--config.data.num_test=4',
    '--config.savi.decoder.features=(8,8)',
    '--config.savi.encoder.features=(8,8)',
    '--config.savi.encoder.strides=(1,1)',
    '--config.savi.num_train_steps=30', '--config.savi.log_every=1',
    '--config.savi.checkpoint_every=1000',
]


def _env(data_dir):
  env = dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS='cpu',
             SLOTFORMER_DATA_DIR=str(data_dir))
  env.pop('XLA_FLAGS', None)  # one device, as a plain user run
  return env


def _command(workdir):
  return [sys.executable, '-m', 'slotformer_jax.main', f'--config={SYNTHETIC}',
          f'--workdir={workdir}', '--mode=train_savi', *MICRO]


def _micro_config(data_dir):
  config = pipeline_helpers.micro_config('savi', data_dir)
  config.savi.num_train_steps = 30
  return config


@pytest.fixture(scope='module')
def uninterrupted(tmp_path_factory):
  """(data dir, workdir) of a run to the end."""
  base = tmp_path_factory.mktemp('uninterrupted')
  subprocess.run(_command(base / 'run'), env=_env(base / 'data'), check=True,
                 capture_output=True, timeout=900)
  return base / 'data', base / 'run'


@pytest.mark.parametrize('signum, name', [(signal.SIGTERM, 'SIGTERM'),
                                          (signal.SIGINT, 'SIGINT')])
def test_sigterm_saves_the_current_step_and_the_rerun_is_bit_exact(
    uninterrupted, tmp_path, signum, name):
  data_dir, uninterrupted = uninterrupted
  env = _env(data_dir)

  preempted = tmp_path / 'preempted'
  process = subprocess.Popen(_command(preempted), env=env,
                             stderr=subprocess.PIPE, text=True)
  for line in process.stderr:  # wait until a few steps have run
    if 'savi step 5:' in line:
      break
  process.send_signal(signum)
  rest = process.stderr.read()
  assert process.wait(timeout=300) == 128 + signum, rest
  assert f'preempted: savi: stopped by {name} after step ' in rest, rest
  assert 'Traceback' not in rest and 'KeyboardInterrupt' not in rest, rest
  steps = Checkpointer(str(preempted / 'savi' / 'checkpoints'),
                       read_only=True).all_steps()
  assert len(steps) == 1 and 5 <= steps[0] < 30, steps  # saved at SIGTERM

  subprocess.run(_command(preempted), env=env, check=True,
                 capture_output=True, timeout=900)
  config = _micro_config(data_dir)
  mesh = sharding.make_mesh()
  a = Run.create(config, str(uninterrupted), mesh).stage1
  b = Run.create(config, str(preempted), mesh).stage1
  (a, step_a), (b, step_b) = (a.params, a.step), (b.params, b.step)
  assert step_a == step_b == 30
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _children(pid):
  """Live processes whose parent is `pid` (Linux /proc)."""
  found = []
  for entry in os.listdir('/proc'):
    if not entry.isdigit():
      continue
    try:
      with open(f'/proc/{entry}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    except OSError:
      continue
    if int(fields[1]) == pid and fields[0] != 'Z':
      found.append(int(entry))
  return found


def _alive(pid):
  try:
    with open(f'/proc/{pid}/stat') as f:
      return f.read().rsplit(')', 1)[1].split()[0] != 'Z'
  except OSError:
    return False


GENERATE = '''
import sys
from slotformer_jax.data.write.generate import Output
from slotformer_jax.datasets import synthetic
from slotformer_jax.datasets.synthetic import SyntheticConfig
if __name__ == '__main__':  # spawn workers re-import this script
  config = SyntheticConfig(resolution=(32, 32), num_frames=12, num_train=64,
                           num_val=2, num_test=2)
  synthetic.generate(config, Output(sys.argv[1], 2))
  print('done')
'''


def test_killed_generation_takes_its_workers_and_leaves_nothing(tmp_path):
  env = _env(tmp_path)
  script = tmp_path / 'generate.py'
  script.write_text(GENERATE)
  parent = subprocess.Popen([sys.executable, str(script), str(tmp_path)],
                            env=env)
  deadline = time.time() + 300
  workers = []
  while time.time() < deadline and len(workers) < 2:
    time.sleep(1)
    # The pool's workers, below the resource tracker: grandchildren too.
    workers = [c for child in _children(parent.pid)
               for c in [child] + _children(child)]
  assert workers, 'no worker processes appeared'
  time.sleep(3)  # let them render something
  os.kill(parent.pid, signal.SIGKILL)
  parent.wait()
  deadline = time.time() + 30
  while time.time() < deadline and any(_alive(w) for w in workers):
    time.sleep(0.5)
  assert not any(_alive(w) for w in workers), 'orphaned workers'

  leftovers = list(tmp_path.glob('synthetic_obj3d/*/incomplete.*'))
  assert leftovers, 'the kill left no partial build: the test proves nothing'
  result = subprocess.run([sys.executable, str(script), str(tmp_path)],
                          env=env, capture_output=True, text=True,
                          timeout=900)
  assert result.returncode == 0, result.stderr
  assert not list(tmp_path.glob('synthetic_obj3d/*/incomplete.*'))
  assert list(tmp_path.glob('synthetic_obj3d/*/2.0.0/dataset_info.json'))
