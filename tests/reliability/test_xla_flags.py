"""The XLA:CPU flag handling (slotformer_jax/runtime/xla_flags.py).

The flag changes which convolution kernels XLA:CPU runs, never the math: a
SAVi training loss + gradients and the OBJ3D decoder's forward + backward are
computed in two fresh processes, with and without the flag, and compared.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from slotformer_jax.runtime import xla_flags

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# Computes, in a fresh process, the outputs whose equality the test checks.
_PROGRAM = r'''
import functools, sys
import numpy as np
import jax, jax.numpy as jnp
sys.path.insert(0, 'configs')
import obj3d, synthetic
from slotformer_jax import losses
from slotformer_jax.train import steps

from slotformer_jax.modules.encoders import CNNEncoder
from slotformer_jax.slot_models.savi import build_decoder
from slotformer_jax.slot_models.savi import build_savi

out = {}
if sys.argv[2] == 'convs':
  # The quickstart's convolutions alone (quick to compile): SAVi's encoder
  # (3x3, stride 2 first) and decoder (strided transposed convolutions).
  config = synthetic.get_config()
  enc = config.savi.encoder
  encoder = CNNEncoder(features=tuple(enc.features), kernel_size=enc.kernel_size,
                       strides=tuple(enc.strides), output_size=enc.output_size)
  decoder = build_decoder(config.savi.decoder,
                                 tuple(config.data.resolution))
  rng = np.random.default_rng(0)
  images = jnp.asarray(rng.uniform(-1, 1, (4, *config.data.resolution, 3)), jnp.float32)
  slots = jnp.asarray(rng.normal(size=(4, config.savi.num_slots, config.savi.slot_size)), jnp.float32)
  p = {'enc': encoder.init(jax.random.key(0), images)['params'],
       'dec': decoder.init(jax.random.key(1), slots)['params']}
  def conv_loss(p, images, slots):
    features = encoder.apply({'params': p['enc']}, images)
    recon = decoder.apply({'params': p['dec']}, slots).recon
    return jnp.mean(jnp.square(features)) + jnp.mean(jnp.square(recon - images))
  value, grads = jax.jit(jax.value_and_grad(conv_loss, argnums=(0, 1, 2)))(p, images, slots)
  out['conv_loss'] = np.asarray(value)
  for i, leaf in enumerate(jax.tree.leaves(grads)):
    out[f'conv_grad_{i}'] = np.asarray(leaf)
else:
  # The quickstart's SAVi training loss and gradients ...
  config = synthetic.get_config()
  model = build_savi(config.savi, tuple(config.data.resolution))
  video = np.random.default_rng(0).integers(
      0, 256, (2, 2, *config.data.resolution, 3), np.uint8)
  params = steps.init_params(model, jax.random.key(0), jnp.zeros((1, 2, *config.data.resolution, 3)))
  loss_fn = functools.partial(losses.savi_loss, model=model, kl_weight=0.0)
  (loss, _), grads = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(
      params, {'video': video}, None, jax.random.key(1))
  out['savi_loss'] = np.asarray(loss)
  for i, leaf in enumerate(jax.tree.leaves(grads)):
    out[f'savi_grad_{i}'] = np.asarray(leaf)
  # ... and the OBJ3D decoder (5x5, 64 channels, 64x64), the layers whose
  # kernel gradient the flag speeds up most.
  config = obj3d.get_config()
  decoder = build_decoder(config.savi.decoder,
                                 tuple(config.data.resolution))
  slots = jnp.asarray(np.random.default_rng(1).normal(
      size=(1, 2, config.savi.slot_size)), jnp.float32)
  dparams = decoder.init(jax.random.key(2), slots)['params']
  def decoder_loss(p, s):
    return jnp.mean(jnp.square(decoder.apply({'params': p}, s).recon))
  value, (gp, gs) = jax.jit(jax.value_and_grad(decoder_loss, argnums=(0, 1)))(dparams, slots)
  out['decoder_loss'] = np.asarray(value)
  out['decoder_slot_grad'] = np.asarray(gs)
  for i, leaf in enumerate(jax.tree.leaves(gp)):
    out[f'decoder_grad_{i}'] = np.asarray(leaf)
np.savez(sys.argv[1], **out)
'''


def _run_both(fast_flags, tmp_path, case):
  """Outputs of `case` without and with the flags (two processes at once),
  both with the crash fences (an AVX2-only CPU crashes without them)."""
  fences = tuple(xla_flags.CRASH_FENCE_FLAGS)
  runs = []
  for name, value in (('plain', ' '.join(xla_flags._merged(fences))),  # pylint: disable=protected-access
                      ('fast', ' '.join(xla_flags._merged(fences + tuple(fast_flags))))):  # pylint: disable=protected-access
    env = dict(os.environ, XLA_FLAGS=value, JAX_PLATFORMS='cpu',
               PYTHONPATH=REPO, **{xla_flags.SWITCH_ENV: '0'})
    path = str(tmp_path / f'{name}.npz')
    runs.append((path, subprocess.Popen(
        [sys.executable, '-c', _PROGRAM, path, case], env=env, cwd=REPO,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT)))
  outputs = []
  for path, process in runs:
    log, _ = process.communicate(timeout=900)
    assert process.returncode == 0, log.decode()[-2000:]
    outputs.append(dict(np.load(path)))
  return outputs


def _compare_fast_and_plain(tmp_path, case):
  fast = [f for f in xla_flags.FAST_CPU_FLAGS if xla_flags.supported(f)]
  if not fast:
    pytest.skip('this jaxlib supports none of the fast XLA:CPU flags')
  plain, flagged = _run_both(fast, tmp_path, case)
  assert plain.keys() == flagged.keys()
  worst = {}
  for key, reference in plain.items():
    scale = max(float(np.max(np.abs(reference))), 1e-12)
    diff = float(np.max(np.abs(flagged[key] - reference)))
    worst[key] = diff
    # Different kernels sum in a different order: float32 rounding only.
    assert diff <= 1e-4 * scale + 1e-7, (key, diff, scale)
  print(f'{case}: largest max |fast - plain|:', json.dumps(
      {k: f'{v:.2e}' for k, v in sorted(worst.items(), key=lambda kv: -kv[1])[:5]}))


@pytest.mark.slow  # 26 s (two processes compile the same gradients)
def test_fast_flags_leave_convolution_gradients_unchanged(tmp_path):
  _compare_fast_and_plain(tmp_path, 'convs')


@pytest.mark.slow
def test_fast_flags_leave_savi_step_and_obj3d_decoder_unchanged(tmp_path):
  _compare_fast_and_plain(tmp_path, 'models')


def test_user_flag_of_the_same_name_wins(monkeypatch):
  probed = []
  monkeypatch.setattr(xla_flags, 'supported', lambda f, env: probed.append(f) or True)
  name = xla_flags.flag_name(xla_flags.FAST_CPU_FLAGS[0])
  env = {'XLA_FLAGS': f'--{name}=default --xla_force_host_platform_device_count=4'}
  assert xla_flags.apply_fast_cpu_flags(environ=env) == []
  assert env['XLA_FLAGS'] == f'--{name}=default --xla_force_host_platform_device_count=4'
  assert probed == []


def test_flags_are_appended_to_the_users_flags(monkeypatch):
  monkeypatch.setattr(xla_flags, 'supported', lambda f, env: True)
  monkeypatch.setattr(xla_flags, '_backends_initialised', lambda: False)
  env = {'XLA_FLAGS': '--xla_force_host_platform_device_count=4'}
  added = xla_flags.apply_fast_cpu_flags(('--xla_a=1', '--xla_b=x'), environ=env,
                                         fences=('--xla_b=y', '--xla_c=z'))
  # Fences first; one flag per name.
  assert added == ['--xla_b=y,x', '--xla_c=z', '--xla_a=1']
  assert env['XLA_FLAGS'] == ('--xla_force_host_platform_device_count=4 '
                              '--xla_b=y,x --xla_c=z --xla_a=1')


def test_switch_disables_the_speed_flags_not_the_fences(monkeypatch):
  monkeypatch.setattr(xla_flags, 'supported', lambda f, env: True)
  monkeypatch.setattr(xla_flags, '_backends_initialised', lambda: False)
  env = {xla_flags.SWITCH_ENV: '0'}
  assert xla_flags.apply_fast_cpu_flags(('--xla_a=1',), environ=env,
                                        fences=()) == []
  assert 'XLA_FLAGS' not in env
  assert xla_flags.apply_fast_cpu_flags(
      ('--xla_a=1',), environ=env, fences=('--xla_f=-x',)) == ['--xla_f=-x']
  assert env['XLA_FLAGS'] == '--xla_f=-x'


def test_unsupported_flag_is_probed_cached_and_skipped(monkeypatch, tmp_path):
  monkeypatch.setattr(xla_flags, '_backends_initialised', lambda: False)
  env = {xla_flags.CACHE_ENV: str(tmp_path)}
  bogus = '--xla_slotformer_no_such_flag=1'
  # A real subprocess: XLA aborts on the unknown flag there, not here.
  assert xla_flags.apply_fast_cpu_flags((bogus,), environ=env, fences=()) == []
  assert 'XLA_FLAGS' not in env
  cache = json.loads(
      (tmp_path / 'slotformer_jax' / 'xla_flag_probes.json').read_text())
  assert [v for k, v in cache.items() if k.endswith(bogus)] == [False]
  # Cached: no second probe.
  monkeypatch.setattr(xla_flags, 'probe_flag', lambda f: pytest.fail('re-probed'))
  assert xla_flags.apply_fast_cpu_flags((bogus,), environ=env, fences=()) == []


def test_too_late_once_backends_started(monkeypatch):
  monkeypatch.setattr(xla_flags, 'supported', lambda f, env: True)
  import jax
  jax.devices()  # conftest's session has started the backends already
  env = {}
  assert xla_flags.apply_fast_cpu_flags(('--xla_a=1',), environ=env) == []
