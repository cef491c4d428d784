r"""The training loop's own host time per step: the real loop, a step that
does nothing.

  python benchmarks/loop_overhead.py --config=configs/synthetic.py \
      --workdir=/tmp/lo --modes=train_savi,extract_slots,train_slotformer \
      [--steps=300] [--json=out.json] [--processes=2 --stop_check_every=1,10]

Each mode runs `slotformer_jax.main` in a fresh process with the trainer's
jitted update (`trainer.jit_update`) replaced by one that only advances
`state.step` and returns constant metrics. Everything else is the real
loop: the stage's batches from its reader (prefetch thread and all), the
transfer to the device (`sharding.to_global_batch`), the progress bar, the
stop check, logging every `log_every` steps (a device -> host fetch), the
final checkpoint. Modes that are not training (prepare_data, extract_slots,
tokenize_frames) run as they are, so that the next stage has its inputs
(computed by the untrained models: only their shapes matter here).

Per training mode it prints the host time per step (median and mean of
the intervals between successive updates, after `--skip` steps) split
into: waiting for the reader's next batch, `to_global_batch`, dispatching
the update, and the rest of the loop; and the reader's own time per batch
(built in its background thread, on the same cores).

`--processes=2` starts that many processes on localhost
(`--coordinator_address`), one CPU device each, and runs every training
mode once per value of `--stop_check_every`: every process then
all-gathers the stop signal after every `stop_check_every` steps
(`processes.agreed_signal`); the all-gather's own time per call is
reported too.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import time

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')
_RESULT_TAG = 'LOOP_OVERHEAD_RESULT '
# The config section each training mode trains.
SECTIONS = {'train_savi': 'savi', 'train_dvae': 'dvae', 'train_steve': 'steve',
            'train_slotformer': 'slotformer', 'train_slot_lstm': 'slot_lstm'}


# ---- inside one process of `slotformer_jax.main` ---------------------------

def _install_probes(record: dict) -> None:
  """Replaces the update with a no-op and times the loop's parts."""
  import jax  # pylint: disable=g-import-not-at-top
  import jax.numpy as jnp  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import pipeline  # pylint: disable=g-import-not-at-top
  from slotformer_jax.runtime import processes  # pylint: disable=g-import-not-at-top
  from slotformer_jax.runtime import sharding  # pylint: disable=g-import-not-at-top
  from slotformer_jax.train import trainer  # pylint: disable=g-import-not-at-top

  clock = time.perf_counter
  for key in ('update', 'to_global', 'next', 'make', 'allgather'):
    record[key] = []

  def jit_update(stage, mesh, optimizer, seed):
    del stage, optimizer, seed
    replicated = sharding.replicated_sharding(mesh)

    def nothing(state, batch, frozen_params):
      del batch, frozen_params
      return state.replace(step=state.step + 1), {
          'loss': jnp.zeros((), jnp.float32),
          'param_norm': jnp.ones((), jnp.float32)}

    update = jax.jit(nothing, in_shardings=(
        replicated, sharding.batch_sharding(mesh), replicated),
                     out_shardings=(replicated, replicated),
                     donate_argnums=(0,))

    def timed(*args):
      start = clock()
      out = update(*args)
      record['update'].append((start, clock()))
      return out
    return timed

  def timed_call(name, function):
    def timed(*args, **kwargs):
      start = clock()
      out = function(*args, **kwargs)
      record[name].append((start, clock()))
      return out
    return timed

  def timed_stream(stream):
    while True:
      start = clock()
      try:
        batch = next(stream)
      except StopIteration:
        return
      record['next'].append((start, clock()))
      yield batch

  train_batches = pipeline.train_batches

  def timed_train_batches(*args, **kwargs):
    return timed_stream(train_batches(*args, **kwargs))

  trainer.jit_update = jit_update
  sharding.to_global_batch = timed_call('to_global', sharding.to_global_batch)
  pipeline.make_train_batch = timed_call('make', pipeline.make_train_batch)
  pipeline.train_batches = timed_train_batches
  processes.agreed_signal = timed_call('allgather', processes.agreed_signal)


def _summary(record: dict, skip: int) -> dict:
  """ms per step of each part, from the timestamps of the steps after `skip`."""
  updates = record['update'][skip:]
  if len(updates) < 3:
    return {'steps_timed': len(updates)}
  starts = [s for s, _ in updates]
  intervals = [b - a for a, b in zip(starts, starts[1:])]

  # Only what happened between the first and the last timed update (the
  # first all-gather compiles its program).
  window = (starts[0], starts[-1])

  def durations(name):
    return [e - s for s, e in record[name] if window[0] <= s < window[1]]

  def ms_per_step(name):
    return 1e3 * sum(durations(name)) / len(intervals)

  total = 1e3 * statistics.mean(intervals)
  parts = {'next_batch_wait': ms_per_step('next'),
           'to_global_batch': ms_per_step('to_global'),
           'update_dispatch': ms_per_step('update'),
           'stop_check_allgather': ms_per_step('allgather')}
  gathers = durations('allgather')
  return {
      'steps_timed': len(intervals),
      'ms_per_step_median': 1e3 * statistics.median(intervals),
      'ms_per_step_mean': total,
      **{f'ms_{k}': v for k, v in parts.items()},
      'ms_rest_of_loop': total - sum(parts.values()),
      'reader_ms_per_batch': 1e3 * statistics.mean(
          [e - s for s, e in record['make'][skip:]] or [0.0]),
      'allgather_calls': len(gathers),
      'allgather_ms_per_call_median': (
          1e3 * statistics.median(gathers) if gathers else None),
      'allgather_ms_per_call_mean': (
          1e3 * statistics.mean(gathers) if gathers else None),
  }


def _child(argv: list[str], skip: int) -> None:
  sys.path.insert(0, ROOT)
  from slotformer_jax import main as main_lib  # pylint: disable=g-import-not-at-top
  record: dict = {}
  _install_probes(record)
  status = 0
  try:
    main_lib.run_main([sys.argv[0], *argv])
  except SystemExit as exit_:
    status = exit_.code if isinstance(exit_.code, int) else (
        0 if exit_.code is None else 1)
  if record['update']:
    print(_RESULT_TAG + json.dumps(_summary(record, skip)), flush=True)
  sys.exit(status)


# ---- the driver ------------------------------------------------------------

def _free_port() -> int:
  with socket.socket() as s:
    s.bind(('localhost', 0))
    return s.getsockname()[1]


def _load() -> str:
  with open('/proc/loadavg') as f:
    return ' '.join(f.read().split()[:3])


def _run_mode(args, mode: str, extra: list[str], processes: int,
              stop_check_every: int | None) -> dict | None:
  base = [f'--config={args.config}', f'--workdir={args.workdir}',
          f'--mode={mode}', *extra]
  if stop_check_every is not None and mode in SECTIONS:
    # Not part of a run's identity: any value resumes the same workdir.
    base.append(f'--config.{SECTIONS[mode]}.stop_check_every='
                f'{stop_check_every}')
  env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep
             + os.environ.get('PYTHONPATH', ''))
  port = _free_port()
  commands = []
  for i in range(processes):
    command = base + ([f'--coordinator_address=localhost:{port}',
                       f'--num_processes={processes}', f'--process_id={i}']
                      if processes > 1 else [])
    commands.append([sys.executable, os.path.abspath(__file__), '--child',
                     f'--skip={args.skip}', '--', *command])
  load_before = _load()
  started = time.time()
  children = [subprocess.Popen(c, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
              for c in commands]
  outputs = [c.communicate()[0] for c in children]
  wall = time.time() - started
  for i, (child, output) in enumerate(zip(children, outputs)):
    if child.returncode != 0:
      sys.exit(f'{mode} (process {i}) failed with status '
               f'{child.returncode}:\n{output[-3000:]}')
  results = [json.loads(line[len(_RESULT_TAG):])
             for line in outputs[0].splitlines()
             if line.startswith(_RESULT_TAG)]
  if not results:
    return None
  return dict(results[-1], mode=mode, processes=processes,
              stop_check_every=stop_check_every, wall_s=round(wall, 1),
              load_before=load_before, load_after=_load())


def _print(result: dict) -> None:
  line = (f"{result['mode']:<17} P={result['processes']} "
          f"every={result['stop_check_every']}: "
          f"{result['ms_per_step_median']:.2f} ms/step median, "
          f"{result['ms_per_step_mean']:.2f} mean = reader wait "
          f"{result['ms_next_batch_wait']:.2f} + to_global_batch "
          f"{result['ms_to_global_batch']:.2f} + update dispatch "
          f"{result['ms_update_dispatch']:.2f} + stop check "
          f"{result['ms_stop_check_allgather']:.2f} + rest "
          f"{result['ms_rest_of_loop']:.2f}; reader builds a batch in "
          f"{result['reader_ms_per_batch']:.2f} ms")
  if result['allgather_ms_per_call_median'] is not None:
    line += (f"; all-gather {result['allgather_ms_per_call_median']:.2f} ms "
             f"median, {result['allgather_ms_per_call_mean']:.2f} mean x "
             f"{result['allgather_calls']}")
  print(line + f" (load {result['load_before']} -> {result['load_after']})",
        flush=True)


def main() -> None:
  if '--child' in sys.argv:
    own = sys.argv[1:sys.argv.index('--')]
    skip = int(next(a for a in own if a.startswith('--skip=')).split('=')[1])
    _child(sys.argv[sys.argv.index('--') + 1:], skip)
    return
  parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
  parser.add_argument('--config', required=True)
  parser.add_argument('--workdir', required=True)
  parser.add_argument('--modes', required=True,
                      help='comma-separated, in pipeline order')
  parser.add_argument('--steps', type=int, default=300,
                      help='num_train_steps of every training section')
  parser.add_argument('--skip', type=int, default=20,
                      help='steps not timed (compilation, warm-up)')
  parser.add_argument('--processes', type=int, default=1)
  parser.add_argument('--stop_check_every', default='',
                      help='comma-separated values to run each training '
                      'mode with (default: the config\'s)')
  parser.add_argument('--override', action='append', default=[],
                      help='more --config.x=y flags for every run')
  parser.add_argument('--json', default=None)
  args = parser.parse_args()
  modes = args.modes.split(',')
  sections = {SECTIONS[m] for m in modes if m in SECTIONS}
  extra = [f'--config.{s}.num_train_steps={args.steps}'
           for s in sorted(sections)] + list(args.override)
  everies = ([int(v) for v in args.stop_check_every.split(',')]
             if args.stop_check_every else [None])
  results = []
  for mode in modes:
    for index, every in enumerate(everies if mode in SECTIONS else [None]):
      if index:  # train the same steps again
        _reset(args.workdir, SECTIONS[mode])
      result = _run_mode(args, mode, extra, args.processes, every)
      if result is None:
        print(f'{mode}: done (not a training mode)', flush=True)
        continue
      _print(result)
      results.append(result)
  if args.json:
    with open(args.json, 'w') as f:
      json.dump(results, f, indent=1)


def _reset(workdir: str, section: str) -> None:
  """Removes a stage's folder (checkpoints, identity) so that its steps run
  again."""
  import shutil  # pylint: disable=g-import-not-at-top
  sys.path.insert(0, ROOT)
  from slotformer_jax.workdir.paths import Paths  # pylint: disable=g-import-not-at-top
  paths = Paths.of(workdir)
  shutil.rmtree(paths.dynamics(section) if section in (
      'slotformer', 'slot_lstm') else paths.model(section))

if __name__ == '__main__':
  main()
