"""Freed host memory stays mapped (slotformer_jax/runtime/host_memory.py).

A block larger than glibc's largest mmap threshold (32 MiB), allocated,
written and freed again and again as XLA:CPU does with a step's scratch
buffer, faults its pages in once with `keep_freed_memory()` instead of on
every round. Each case runs in a fresh process: mallopt settings last for
the whole process.
"""

import json
import os
import platform
import subprocess
import sys

import pytest

from slotformer_jax.runtime import host_memory

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

_PROGRAM = r'''
import ctypes, json, resource, sys
from slotformer_jax.runtime import host_memory
applied = host_memory.keep_freed_memory()
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
size = 57 << 20  # the quickstart's SAVi step: a 57 MiB temp buffer
rounds = 10
faults = []
for _ in range(rounds):
  before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
  block = libc.malloc(size)
  ctypes.memset(block, 1, size)
  libc.free(block)
  faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
# From another thread: with its own arena (heaps of at most 64 MiB) glibc
# would map a 100 MiB block afresh every time; with one arena
# (M_ARENA_MAX=1) it is reused like the main thread's.
import threading
threaded = []
def big():
  for _ in range(3):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = libc.malloc(100 << 20)
    if not block:
      threaded.append(None)
      return
    ctypes.memset(block, 1, 100 << 20)
    libc.free(block)
    threaded.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
thread = threading.Thread(target=big)
thread.start()
thread.join()
# Larger than 2 GiB (argv[1] MiB; 0: skipped), as the scratch of a
# three-seed SlotFormer program: the heap's free top then passes any
# positive trim threshold mallopt takes; it must still not be returned.
huge = int(sys.argv[1]) << 20 if len(sys.argv) > 1 else 0
huge_faults = []
for _ in range(2 if huge else 0):
  before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
  block = libc.malloc(huge)
  if not block:
    huge_faults.append(None)
    break
  ctypes.memset(block, 1, huge)
  libc.free(block)
  huge_faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(json.dumps({'applied': applied, 'faults': faults,
                  'pages': size // 4096, 'threaded': threaded,
                  'huge_faults': huge_faults}))
'''


def _run(*args, **env):
  environ = dict(os.environ, PYTHONPATH=REPO, JAX_PLATFORMS='cpu')
  environ.pop('GLIBC_TUNABLES', None)
  environ.update(env)
  if environ['JAX_PLATFORMS'] is None:
    del environ['JAX_PLATFORMS']
  result = subprocess.run([sys.executable, '-c', _PROGRAM, *args],
                          env=environ,
                          capture_output=True, text=True, check=True)
  return json.loads(result.stdout)


@pytest.mark.skipif(platform.libc_ver()[0] != 'glibc',
                    reason='mallopt is glibc\'s')
def test_a_freed_large_block_is_not_faulted_in_again():
  kept = _run(SLOTFORMER_MALLOC_TUNING='1')
  churned = _run(SLOTFORMER_MALLOC_TUNING='0')
  assert kept['applied'] and not churned['applied']
  pages = kept['pages']
  # Without: every round maps fresh pages and faults each one in.
  assert min(churned['faults'][1:]) > 0.9 * pages, churned
  # With: the first round faults them in, later rounds reuse them.
  assert kept['faults'][0] > 0.9 * pages, kept
  assert max(kept['faults'][1:]) < 0.01 * pages, kept
  # 100 MiB from a thread: reused too; without the settings, mapped again.
  assert None not in kept['threaded'], kept
  assert max(kept['threaded'][1:]) < 0.01 * (100 << 20) // 4096, kept
  assert min(churned['threaded']) > 0.9 * (100 << 20) // 4096, churned


@pytest.mark.skipif(platform.libc_ver()[0] != 'glibc',
                    reason='mallopt is glibc\'s')
def test_a_freed_block_above_2_gib_is_kept_too():
  # 2,304 MiB: above 2 GiB - 1, the largest positive trim threshold.
  kept = _run('2304', SLOTFORMER_MALLOC_TUNING='1')
  pages = (2304 << 20) // 4096
  assert None not in kept['huge_faults'], kept['huge_faults']
  first, second = kept['huge_faults']
  assert first > 0.9 * pages, kept['huge_faults']
  assert second < 0.01 * pages, kept['huge_faults']


def test_off_switch_and_user_tunables_win():
  assert not host_memory.keep_freed_memory(
      environ={host_memory.SWITCH_ENV: 'off'})
  assert not host_memory.keep_freed_memory(
      environ={'GLIBC_TUNABLES': 'glibc.malloc.mmap_threshold=1000000'})
  assert _run(GLIBC_TUNABLES='glibc.malloc.arena_max=2')['applied'] is False


@pytest.mark.skipif(platform.libc_ver()[0] != 'glibc',
                    reason='mallopt is glibc\'s')
def test_without_the_arena_limit_only_the_threads_large_blocks_churn():
  kept = _run(SLOTFORMER_MALLOC_TUNING='no-arena-limit')
  pages = kept['pages']
  assert kept['applied'], kept
  # The main thread's 57 MiB block is reused, as with all three settings.
  assert max(kept['faults'][1:]) < 0.01 * pages, kept
  # A thread's own arena maps a 100 MiB block afresh every time.
  assert min(kept['threaded']) > 0.9 * (100 << 20) // 4096, kept


def test_the_switch_values():
  level = host_memory.level
  assert level({}) == level({host_memory.SWITCH_ENV: 'ON'}) == host_memory.ALL
  assert level({host_memory.SWITCH_ENV: ' no-arena-limit '}) == (
      host_memory.NO_ARENA_LIMIT)
  assert level({host_memory.SWITCH_ENV: 'False'}) == host_memory.OFF
  assert host_memory.settings(host_memory.OFF) == ()
  assert host_memory.M_ARENA_MAX not in dict(
      host_memory.settings(host_memory.NO_ARENA_LIMIT))


def test_a_mistyped_switch_says_so_and_applies_all(caplog):
  assert host_memory.level(
      {host_memory.SWITCH_ENV: 'no_arena'}) == host_memory.ALL
  assert "'no_arena' is not one of" in caplog.text


def test_a_process_that_may_use_an_accelerator_is_left_alone(tmp_path):
  may = host_memory.may_compute_on_accelerator
  assert not may({'JAX_PLATFORMS': 'cpu'})
  assert may({'JAX_PLATFORMS': 'tpu'}) and may({'JAX_PLATFORMS': 'cuda,cpu'})
  assert not may({'JAX_PLATFORMS': 'cpu,cuda'})
  # JAX_PLATFORMS unset: an installed plugin (as jax[cuda12] installs one
  # under the jax_plugins namespace) is enough.
  plugin = tmp_path / 'jax_plugins' / 'xla_fake'
  plugin.mkdir(parents=True)
  (plugin / '__init__.py').write_text('')
  with_plugin = _run(JAX_PLATFORMS=None, SLOTFORMER_MALLOC_TUNING='1',
                     PYTHONPATH=os.pathsep.join([REPO, str(tmp_path)]))
  assert with_plugin['applied'] is False, with_plugin
  told_cpu = _run(JAX_PLATFORMS='cpu', SLOTFORMER_MALLOC_TUNING='1',
                  PYTHONPATH=os.pathsep.join([REPO, str(tmp_path)]))
  assert told_cpu['applied'] is True, told_cpu
