"""Test-session setup: 4 fake CPU devices, so sharded code paths run too.

XLA reads the flag when jax initialises its backends, so it is set here,
before any test module imports jax.
"""

import gc
import os
import signal

# Python's cyclic collector, at its default thresholds, runs a full
# collection over the test process's large heap (jax's caches of thousands
# of traced programs) every few seconds while jax traces: 4% of a pipeline
# file's time. Collected less often here; the collector stays on (memory:
# docs/performance.md, "The test suite's wall time").
gc.set_threshold(50_000, 20, 100)

# A test run started as a background job of a script (`cmd &`, nohup)
# inherits SIGINT ignored, and so would every process a test starts: the
# tests that press Ctrl-C on one (tests/reliability) would see it ignored,
# as such a run rightly does. The tests start theirs as from a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
  signal.signal(signal.SIGINT, signal.default_int_handler)

_FLAG = '--xla_force_host_platform_device_count=4'
if _FLAG not in os.environ.get('XLA_FLAGS', ''):
  os.environ['XLA_FLAGS'] = (os.environ.get('XLA_FLAGS', '') + ' ' + _FLAG).strip()
os.environ.setdefault('JAX_PLATFORMS', 'cpu')

# The faster XLA:CPU convolution path, as main.py uses it (imports no jax).
from slotformer_jax.runtime import xla_flags  # noqa: E402
xla_flags.apply_fast_cpu_flags()
# Freed step buffers stay mapped, as in main.py, but without main's one
# malloc arena: the suite compiles far more than it steps, and one arena
# slows XLA's compiler threads down (runtime/host_memory.py). Set in the
# environment, so the processes tests start (main among them) do the same;
# a value already there wins.
from slotformer_jax.runtime import host_memory  # noqa: E402
os.environ.setdefault(host_memory.SWITCH_ENV, host_memory.NO_ARENA_LIMIT)
host_memory.keep_freed_memory()

import tempfile  # noqa: E402

# The suite compiles far more than it runs: cheaper than users' runs
# (compile_level.py; JAX_DISABLE_MOST_OPTIMIZATIONS=0 runs it as users
# compile; tests/reliability/test_xla_crash_fence.py always does).
import compile_level  # noqa: E402
compile_level.apply()
# Several tests compile the same small programs (e.g. a training run and its
# resumed copy); XLA's persistent cache turns the repeats into lookups. In
# the environment too, so the `main` processes tests start share it (their
# default is a cache in each test's own data folder, always cold).
_CACHE = os.path.join(tempfile.gettempdir(), 'slotformer_jax_test_xla_cache')
os.environ.setdefault('JAX_COMPILATION_CACHE_DIR', _CACHE)

import jax  # noqa: E402

jax.config.update('jax_compilation_cache_dir',
                  os.environ['JAX_COMPILATION_CACHE_DIR'])
jax.config.update('jax_persistent_cache_min_compile_time_secs', 0.5)
jax.config.update('jax_persistent_cache_min_entry_size_bytes', 0)


import pytest  # noqa: E402

# Variants whose sibling (named) stays in the default suite: they run with
# `-m slow`, so that the default suite stays near its 10-minute aim on 2 CPU
# cores (tests/README.md).
SLOW_VARIANTS = {
    'pipeline/test_pipeline_end_to_end.py::'
    'test_rerun_resumes_without_recomputing[steve]': '[savi]',
    'pipeline/test_pipeline_end_to_end.py::'
    'test_stage_two_on_a_read_only_stage_one[steve]': '[savi]',
    'train/test_steve_training.py::'
    'test_four_device_step_equals_one_device_step[steve]':
        'train/test_training.py [slotformer]',
    'train/test_steve_training.py::test_train_step_traces_once[dvae]':
        '[steve]',
    'train/test_training.py::'
    'test_four_device_step_equals_one_device_step[stochastic_savi]':
        '[slotformer]',
    'train/test_precision.py::test_bfloat16_step_close_to_float32[savi]':
        '[slotformer]',
    'modules/test_kernel_forms.py::test_slotformer_rollout_forms_agree[4]':
        '[0]',
    'reliability/test_multiprocess.py::'
    'test_sigterm_stops_both_processes_after_the_same_step[sigterm_to_one]':
        'test_processes_agree_on_a_stop_every_k_steps (the agreement, a fake '
        'all-gather); one process: train/test_training.py',
    'reliability/test_multiprocess.py::'
    'test_the_watchdog_names_a_lost_process[143-0-survived]':
        '[0-0-survived]',
    'reliability/test_multiprocess.py::'
    'test_the_watchdog_waits_for_a_peer_slow_to_start[2.5-0-survived]':
        'test_a_process_that_never_starts_is_named_in_time',
    'reliability/test_multiprocess.py::'
    'test_the_watchdog_waits_for_a_peer_slow_to_start[-1-1-error: process 1 '
    'of 2 never started (no heartbeat within 4 s)]':
        'test_a_process_that_never_starts_is_named_in_time',
    'evaluation/test_explore.py::'
    'test_explorer_is_jitted_once_per_shape_and_matches_the_rollouts':
        "the explorer's interventions, one test each (same file)",
    'train/test_tensorboard.py::test_off_by_config_writes_no_event_file':
        'test_logging_settings_never_block_a_workdir',
    # Moved to keep the default suite near its 15-minute aim
    # (docs/performance.md, "The test suite's wall time").
    'train/test_seeds.py::test_seed_k_of_k_seeds_is_the_one_seed_run'
    '[savi-1-vmap]':
        "[savi-1-auto]; the vmapped step: pipeline/test_seeds_pipeline.py's "
        "seeds split on 2 devices",
    'train/test_steve_training.py::test_train_step_traces_once[steve]':
        'train/test_training.py::test_train_step_traces_once (the trainer '
        'code is shared)',
    'datasets/test_datasets_obj3d.py::'
    'test_obj3d_config_runs_the_pipeline_on_converted_data':
        "the file's other tests (the converted layout read by the config); "
        "the stages: pipeline/test_pipeline_end_to_end.py",
    'pipeline/test_vqa_clevrer_questions.py::'
    'test_a_question_set_of_one_kind_trains[predictive]': '[descriptive]',
}


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items):
  for item in items:
    if item.nodeid.split('tests/', 1)[-1] in SLOW_VARIANTS:
      item.add_marker(pytest.mark.slow)


def _cpu() -> tuple[str, set[str]]:
  """(model name, feature flags) from /proc/cpuinfo; ('unknown', set()) elsewhere."""
  model, features = 'unknown', set()
  try:
    with open('/proc/cpuinfo') as f:
      for line in f:
        key, _, value = line.partition(':')
        if key.strip() == 'model name' and model == 'unknown':
          model = value.strip()
        elif key.strip() == 'flags' and not features:
          features = set(value.split())
  except OSError:
    pass
  return model, features


def _machine_line() -> str:
  model, features = _cpu()
  width = ('AVX-512' if 'avx512f' in features else
           'AVX2 only' if 'avx2' in features else 'no AVX2')
  return (f'cpu: {model} ({width}, {os.cpu_count()} cores); '
          f'XLA_FLAGS={os.environ.get("XLA_FLAGS", "")}; '
          'JAX_DISABLE_MOST_OPTIMIZATIONS='
          f'{os.environ.get("JAX_DISABLE_MOST_OPTIMIZATIONS", "")}')


def pytest_report_header(config):
  """The CPU family and XLA's flags in every run's log (the header, and the
  summary, which `-q` keeps): XLA:CPU picks its kernels by the CPU's vector
  width, and jaxlib 0.10.2 crashed on AVX2-only CPUs where AVX-512 ones ran
  (runtime/xla_flags.py's crash fence). Nothing else in the suite depends
  on which of the two it gets."""
  del config
  return [_machine_line()]


def pytest_terminal_summary(terminalreporter):
  terminalreporter.write_line(_machine_line())


def pytest_xdist_auto_num_workers(config):
  """`-n auto` (setup.cfg): one worker per core, at most 4 (each holds jax
  and its compiled programs, ~2 GB); the compile cache on disk is shared."""
  del config
  return min(os.cpu_count() or 1, 4)
