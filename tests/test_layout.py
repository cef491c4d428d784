"""The house's import rules, checked on the real import graph (no import runs).

The graph is every `import` / `from ... import` statement of the package,
function-local ones included (a lazy import still ties two modules). Rules:

* no import circle, between any number of modules;
* data flows one way: every module sits on a floor (`FLOORS`, lowest first)
  and imports only modules on its own floor or below -- nothing runs back up;
* the boundaries (`BOUNDARIES`): who must never reach whom, even on the
  floors' terms (reading never writes; evaluation, inference, the tasks and
  the run bookkeeping never reach training code; ...).

`test_the_checker_catches_*` and `test_each_boundary_catches_a_violation`
run the same checks with a deliberate circle / upward import / forbidden
edge, so the rules cannot pass by seeing nothing.
"""

from __future__ import annotations

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / 'slotformer_jax'

# Lowest floor first. A module's floor is that of the longest prefix listed.
FLOORS = (
    # plumbing every floor may use
    ('slotformer_jax', 'slotformer_jax.errors', 'slotformer_jax.files',
     'slotformer_jax.frames', 'slotformer_jax.targets',
     # the package's import sets XLA's flags before jax starts (no jax)
     'slotformer_jax.runtime.xla_flags'),
    # run bookkeeping: paths, identities, settings, locks (plain files)
    ('slotformer_jax.workdir',),
    # run-time pieces shared by training, evaluation and the tasks
    ('slotformer_jax.runtime',),
    # reading (sources, chunks, checksums, slots, questions, the downloads'
    # decoders) and the input pipeline
    ('slotformer_jax.data',),
    # the planning task's simulator, which its embedded dataset's generator
    # uses too: with the task, on the floor below the datasets
    ('slotformer_jax.tasks.phyre_world',),
    # one module per dataset and their registry; what reads by their facts
    ('slotformer_jax.datasets', 'slotformer_jax.data.vqa_questions'),
    # the writing room (the data stage's and the prepare CLI's), above every
    # reader
    ('slotformer_jax.data.write', 'slotformer_jax.data.prepare'),
    ('slotformer_jax.modules',),
    ('slotformer_jax.config',),
    ('slotformer_jax.losses',),
    ('slotformer_jax.train',),
    ('slotformer_jax.inference',),
    # the models as the pipeline uses them (built, declared, loaded)
    ('slotformer_jax.dynamics', 'slotformer_jax.slot_models'),
    ('slotformer_jax.evaluation', 'slotformer_jax.tasks'),
    # one run: config, paths, mesh, slot model, loaded models
    ('slotformer_jax.run',),
    # a trained model as one Python object (frames in, slots and frames out)
    ('slotformer_jax.api',),
    ('slotformer_jax.stages',),
    ('slotformer_jax.official',),
    # the entry points: the pipeline, the official-weights converter
    ('slotformer_jax.main', 'slotformer_jax.official.convert',
     'slotformer_jax.predict'),
)
TRAINING = ('slotformer_jax.train', 'slotformer_jax.losses',
            'slotformer_jax.stages')

# (who, must never reach, why): `who` and `forbidden` are module prefixes;
# reaching is through any chain of imports.
BOUNDARIES = (
    ('slotformer_jax.data.sources', 'slotformer_jax.data.write',
     'reading never writes: opening data never makes it'),
    ('slotformer_jax.datasets', 'slotformer_jax.data.write',
     'a dataset says how it is made; only the writing room writes it'),
    ('slotformer_jax.evaluation', 'slotformer_jax.train',
     'evaluation uses the run-time pieces, never training code'),
    ('slotformer_jax.evaluation', 'slotformer_jax.data.write',
     'evaluation reads a dataset\'s rules (CLEVRER\'s clips), never a '
     'writer'),
    ('slotformer_jax.tasks', 'slotformer_jax.data.write',
     'a task simulates with run-time code, not a writer'),
    ('slotformer_jax.slot_models', 'slotformer_jax.evaluation',
     'a model draws its pictures with frames.py, not evaluation code'),
    ('slotformer_jax.train', 'slotformer_jax.workdir',
     'the trainer knows nothing of run identities (stages stamp them)'),
    ('slotformer_jax.official.convert', 'slotformer_jax.stages',
     'the converter writes where the run\'s paths say, not via a stage'),
    ('slotformer_jax.workdir', 'slotformer_jax.data',
     'run bookkeeping reads no data'),
    ('slotformer_jax.config', 'slotformer_jax.modules',
     'checking a config builds no model'),
    ('slotformer_jax.config', 'slotformer_jax.data',
     'checking a config opens no data (main hands it what it needs)'),
    ('slotformer_jax.inference', 'slotformer_jax.train',
     'inference loads parameters without training code'),
    ('slotformer_jax.tasks', 'slotformer_jax.train',
     'the downstream tasks are pure: no training code'),
    ('slotformer_jax.workdir', 'slotformer_jax.train',
     'run bookkeeping knows no training'),
    ('slotformer_jax.api', 'slotformer_jax.train',
     'the Python API loads trained models without training code'),
    ('slotformer_jax.api', 'slotformer_jax.stages',
     'the Python API computes what the stages compute, not through them'),
)


def modules_of(package: pathlib.Path) -> dict[str, pathlib.Path]:
  """{dotted module name: file} of every .py under `package`."""
  out = {}
  for path in package.rglob('*.py'):
    parts = path.relative_to(package.parent).with_suffix('').parts
    out['.'.join(parts[:-1] if parts[-1] == '__init__' else parts)] = path
  return out


def import_graph(package: pathlib.Path) -> dict[str, set[str]]:
  """{module: the package's modules it imports}. `from a import b` is an
  edge to `a.b` when that is a module, else to `a`; a parent package's
  `__init__` is not counted for importing one of its submodules."""
  files = modules_of(package)
  graph = {}
  for name, path in files.items():
    edges = set()
    is_package = path.name == '__init__.py'
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.Import):
        targets = [alias.name for alias in node.names]
      elif isinstance(node, ast.ImportFrom):
        if node.level:  # relative: resolve against this module's package
          base = name.split('.')
          base = base[:len(base) - node.level + (1 if is_package else 0)]
          module = '.'.join(base + ([node.module] if node.module else []))
        else:
          module = node.module or ''
        targets = [f'{module}.{alias.name}' if f'{module}.{alias.name}' in
                   files else module for alias in node.names]
      else:
        continue
      edges.update(t for t in targets if t in files and t != name)
    graph[name] = edges
  return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
  """Every strongly connected group of 2+ modules (Tarjan), sorted."""
  index, low, stack, on_stack, out = {}, {}, [], set(), []

  def visit(node):
    index[node] = low[node] = len(index)
    stack.append(node)
    on_stack.add(node)
    for other in sorted(graph.get(node, ())):
      if other not in index:
        visit(other)
        low[node] = min(low[node], low[other])
      elif other in on_stack:
        low[node] = min(low[node], index[other])
    if low[node] == index[node]:
      group = []
      while True:
        member = stack.pop()
        on_stack.discard(member)
        group.append(member)
        if member == node:
          break
      if len(group) > 1:
        out.append(sorted(group))

  for node in sorted(graph):
    if node not in index:
      visit(node)
  return sorted(out)


def floor(module: str, floors=FLOORS) -> int:
  best, level = -1, None
  for i, prefixes in enumerate(floors):
    for prefix in prefixes:
      if (module == prefix or module.startswith(prefix + '.')) and len(
          prefix) > best:
        best, level = len(prefix), i
  if level is None:
    raise AssertionError(f'{module} is on no floor: add it to FLOORS')
  return level


def upward_imports(graph: dict[str, set[str]], floors=FLOORS
                   ) -> list[tuple[str, str]]:
  return sorted((a, b) for a, edges in graph.items() for b in edges
                if floor(b, floors) > floor(a, floors))


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
  seen, todo = set(), [start]
  while todo:
    name = todo.pop()
    if name not in seen:
      seen.add(name)
      todo += graph.get(name, ())
  return seen


def boundary_violations(graph: dict[str, set[str]],
                        boundaries=BOUNDARIES) -> list[tuple[str, str, str]]:
  """(module, forbidden module it reaches, why) for every boundary crossed."""
  out = []
  for who, forbidden, why in boundaries:
    for name in sorted(graph):
      if _under(name, (who,)):
        out += [(name, other, why) for other in sorted(reachable(graph, name))
                if _under(other, (forbidden,))]
  return out


# Packages that import every module of theirs by name at run time
# (importlib): the edges the statements do not show.
IMPORTS_EVERY_MODULE = ('slotformer_jax.datasets',)


def with_package_imports(graph: dict[str, set[str]]) -> dict[str, set[str]]:
  """`graph` with an edge from each of IMPORTS_EVERY_MODULE to each of its
  direct modules."""
  for package in IMPORTS_EVERY_MODULE:
    graph[package] |= {name for name in graph
                       if name.rsplit('.', 1)[0] == package}
  return graph


GRAPH = with_package_imports(import_graph(PACKAGE))


def test_no_import_circle():
  assert circles(GRAPH) == []


def test_no_import_runs_back_up():
  assert upward_imports(GRAPH) == []


def test_no_boundary_is_crossed():
  assert boundary_violations(GRAPH) == []


def test_each_boundary_catches_a_violation():
  """One edge added per boundary, from a module of `who` straight to one of
  `forbidden`: the check names it."""
  for who, forbidden, why in BOUNDARIES:
    source = next(n for n in sorted(GRAPH) if _under(n, (who,)))
    target = next(n for n in sorted(GRAPH) if _under(n, (forbidden,)))
    graph = {name: set(edges) for name, edges in GRAPH.items()}
    graph[source].add(target)
    assert (source, target, why) in boundary_violations(graph), (who,
                                                                 forbidden)


def dataset_modules(graph: dict[str, set[str]]) -> set[str]:
  """Every module of datasets/ but the interface (base.py) and the
  registry."""
  return {name for name in graph if _under(name, ('slotformer_jax.datasets',))
          and name not in ('slotformer_jax.datasets',
                           'slotformer_jax.datasets.base')}


def test_the_writing_room_names_no_dataset():
  """data/write/ writes whatever a dataset module describes: it reaches the
  interface (datasets/base.py), never one dataset's module."""
  assert forbidden_reaches(GRAPH, ('slotformer_jax.data.write',),
                           tuple(dataset_modules(GRAPH))) == []


def test_stages_and_tasks_write_files_atomically():
  """Results, readout parameters and selections go through files.py (a
  crash or a full disk leaves the old file or none, never a torn one that a
  rerun would trust): no open() for writing, no json.dump to a file."""
  offenders = []
  for name, path in modules_of(PACKAGE).items():
    if not name.startswith(('slotformer_jax.stages', 'slotformer_jax.tasks')):
      continue
    for node in ast.walk(ast.parse(path.read_text())):
      if not isinstance(node, ast.Call):
        continue
      func = ast.unparse(node.func)
      modes = [ast.literal_eval(a) for a in node.args[1:2]
               if isinstance(a, ast.Constant)] + [
                   ast.literal_eval(k.value) for k in node.keywords
                   if k.arg == 'mode' and isinstance(k.value, ast.Constant)]
      if func == 'open' and any(set(m) & set('wax+') for m in modes):
        offenders.append(f'{name}:{node.lineno} open(..., {modes[0]!r})')
      if func == 'json.dump':
        offenders.append(f'{name}:{node.lineno} json.dump')
  assert offenders == []


def test_the_graph_sees_imports():
  # Guards the checks above against passing because they see nothing.
  assert 'slotformer_jax.train.steps' in reachable(
      GRAPH, 'slotformer_jax.stages.dynamics')
  assert 'slotformer_jax.slot_models.steve' in GRAPH[
      'slotformer_jax.slot_models']
  assert 'slotformer_jax.runtime.sharding' in reachable(
      GRAPH, 'slotformer_jax.evaluation.evaluate')
  assert {'slotformer_jax.datasets.synthetic',
          'slotformer_jax.datasets.clevrer'} <= GRAPH['slotformer_jax.datasets']
  assert 'slotformer_jax.data.write.generate' in reachable(
      GRAPH, 'slotformer_jax.stages.data')
  assert len(GRAPH) > 80


def _fake_package(root: pathlib.Path, files: dict[str, str]) -> pathlib.Path:
  for name, text in files.items():
    path = root / 'pkg' / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
  return root / 'pkg'


def test_the_checker_catches_a_circle(tmp_path):
  package = _fake_package(tmp_path, {
      '__init__.py': '',
      'a.py': 'from pkg import b\n',
      'b.py': 'def f():\n  from pkg.sub import c  # lazy, still an edge\n',
      'sub/__init__.py': '',
      'sub/c.py': 'import pkg.a\n',
  })
  assert circles(import_graph(package)) == [['pkg.a', 'pkg.b', 'pkg.sub.c']]


def test_the_checker_catches_an_upward_import(tmp_path):
  package = _fake_package(tmp_path, {
      '__init__.py': '', 'low.py': 'from pkg import high\n', 'high.py': '',
  })
  floors = (('pkg', 'pkg.low'), ('pkg.high',))
  assert upward_imports(import_graph(package), floors) == [
      ('pkg.low', 'pkg.high')]
  # The real package, with one import added that runs back up, fails too.
  graph = {name: set(edges) for name, edges in GRAPH.items()}
  graph['slotformer_jax.train.trainer'].add('slotformer_jax.inference')
  assert upward_imports(graph) == [('slotformer_jax.train.trainer',
                                    'slotformer_jax.inference')]


# --------------------------------------------------------------------------
# Reading never writes; the rules a run uses live outside the writers
# --------------------------------------------------------------------------

# What reading must never reach: the writing room (the converters' shared
# steps, the generators' Output, the record and checksum writers, the
# prepare CLI) and the lock.
WRITING = ('slotformer_jax.data.write', 'slotformer_jax.data.prepare',
           'slotformer_jax.workdir.lock')
# Where a run opens data: the sources, every dataset module (a dataset holds
# its converter or generator, which make examples and write only through the
# Output the data stage hands them), the VQA questions and vocabulary.
READERS = ('slotformer_jax.data.sources', 'slotformer_jax.datasets',
           'slotformer_jax.data.vqa_questions')
# Calls that write files; a reader's own modules make none.
WRITE_CALLS = ('write_json_atomic', 'write_atomic', 'append_line_atomic',
               'record_checksums', 'np.save', 'np.savez', 'json.dump',
               'shutil.rmtree', 'os.replace', 'os.rename', 'mkdir',
               'download_and_prepare', 'FileLock')


def _under(module: str, prefixes) -> bool:
  return any(module == p or module.startswith(p + '.') for p in prefixes)


def forbidden_reaches(graph: dict[str, set[str]], starts, forbidden
                      ) -> list[tuple[str, str]]:
  """(module, what it reaches) for every module under `starts` that reaches
  a module under `forbidden`."""
  return sorted((name, other) for name in graph if _under(name, starts)
                for other in reachable(graph, name)
                if _under(other, forbidden))


def readers_and_what_they_reach(graph: dict[str, set[str]]) -> set[str]:
  """The readers, every dataset module and every module of data/, datasets/
  and the PHYRE-like world they reach (outside the writing room)."""
  return {m for r in (*READERS, *dataset_modules(graph))
          for m in reachable(graph, r)
          if _under(m, ('slotformer_jax.data', 'slotformer_jax.datasets',
                        'slotformer_jax.tasks.phyre_world'))
          and not _under(m, WRITING)}


def write_calls(files: dict[str, pathlib.Path], names) -> list[str]:
  """'module:line call' of every writing call (WRITE_CALLS, by name or
  method) in the modules `names`, and of open() with a writing mode."""
  found = []
  for name in sorted(names):
    for node in ast.walk(ast.parse(files[name].read_text())):
      if not isinstance(node, ast.Call):
        continue
      func = ast.unparse(node.func)
      modes = [a.value for a in node.args[1:2] if isinstance(a, ast.Constant)]
      if func == 'open' and any(set(str(m)) & set('wax+') for m in modes):
        found.append(f'{name}:{node.lineno} {func}')
      elif func in WRITE_CALLS or func.rsplit('.', 1)[-1] in WRITE_CALLS:
        found.append(f'{name}:{node.lineno} {func}')
  return found


def test_reading_reaches_no_writer():
  """data/sources.py, the dataset modules and what they reach import nothing
  of the writing room and no lock (`data.integrity` only verifies)."""
  assert forbidden_reaches(GRAPH, readers_and_what_they_reach(GRAPH),
                           WRITING) == []


def test_the_reading_modules_write_nothing():
  """Nor do they write a file themselves: a generator writes through the
  Output it is handed (data/write/generate.py)."""
  reached = readers_and_what_they_reach(GRAPH)
  assert {'slotformer_jax.data.integrity', 'slotformer_jax.datasets.clevrer',
          'slotformer_jax.datasets.clevrer_like',
          'slotformer_jax.data.vqa'} <= reached
  assert write_calls(modules_of(PACKAGE), reached) == []


def test_tasks_and_evaluation_reach_no_writer():
  """The run-time rules they use (the PHYRE-like world, CLEVRER's clips)
  are with the planning task and the dataset modules, not with the
  writers."""
  converters = ('slotformer_jax.data.write',)
  assert forbidden_reaches(GRAPH, ('slotformer_jax.tasks',), converters) == []
  assert forbidden_reaches(GRAPH, ('slotformer_jax.evaluation',),
                           converters) == []


def test_the_checker_catches_reading_that_writes():
  graph = {name: set(edges) for name, edges in GRAPH.items()}
  graph['slotformer_jax.datasets.synthetic'].add(
      'slotformer_jax.data.write.generate')
  graph['slotformer_jax.data.integrity'].add(
      'slotformer_jax.data.write.records')
  graph['slotformer_jax.data.vqa'].add('slotformer_jax.workdir.lock')
  caught = forbidden_reaches(graph, readers_and_what_they_reach(graph),
                             WRITING)
  for reader, writer in [
      ('slotformer_jax.datasets', 'slotformer_jax.data.write.generate'),
      ('slotformer_jax.data.sources', 'slotformer_jax.data.write.records'),
      ('slotformer_jax.datasets.synthetic',
       'slotformer_jax.data.write.generate'),
      ('slotformer_jax.data.vqa_questions', 'slotformer_jax.workdir.lock')]:
    assert (reader, writer) in caught
  # A dataset module's own write call is found too.
  files = modules_of(PACKAGE)
  assert write_calls(files, readers_and_what_they_reach(GRAPH)) == []
  assert any(c.startswith('slotformer_jax.data.write.generate:')
             for c in write_calls(files, {'slotformer_jax.data.write.generate'}))


def test_the_checker_catches_the_writing_room_naming_a_dataset():
  graph = {name: set(edges) for name, edges in GRAPH.items()}
  graph['slotformer_jax.data.write.convert'].add(
      'slotformer_jax.datasets.clevrer')
  assert ('slotformer_jax.data.write.convert',
          'slotformer_jax.datasets.clevrer') in forbidden_reaches(
              graph, ('slotformer_jax.data.write',),
              tuple(dataset_modules(graph)))


def test_the_checker_catches_a_write_call(tmp_path):
  package = _fake_package(tmp_path, {
      '__init__.py': '',
      'reader.py': ('import json\n'
                    'def f(path, data):\n'
                    '  with open(path, "w") as out:\n'
                    '    json.dump(data, out)\n'),
      'cache.py': ('from pkg.files import write_json_atomic\n'
                   'def g(path):\n'
                   '  write_json_atomic(path, {})\n'
                   '  path.parent.mkdir(parents=True)\n'),
      'clean.py': 'def h(path):\n  return open(path).read()\n',
  })
  files = modules_of(package)
  assert write_calls(files, files) == [
      'pkg.cache:3 write_json_atomic', 'pkg.cache:4 path.parent.mkdir',
      'pkg.reader:3 open', 'pkg.reader:4 json.dump']


def test_the_checker_catches_a_task_or_evaluation_reaching_a_writer():
  graph = {name: set(edges) for name, edges in GRAPH.items()}
  graph['slotformer_jax.tasks.phyre_planning'].add(
      'slotformer_jax.data.write.generate')
  graph['slotformer_jax.datasets.clevrer'].add(
      'slotformer_jax.data.write.convert')
  writers = ('slotformer_jax.data.write',)
  assert ('slotformer_jax.tasks.phyre_planning',
          'slotformer_jax.data.write.generate') in forbidden_reaches(
              graph, ('slotformer_jax.tasks',), writers)
  caught = forbidden_reaches(graph, ('slotformer_jax.evaluation',), writers)
  assert ('slotformer_jax.evaluation.evaluate',
          'slotformer_jax.data.write.convert') in caught
