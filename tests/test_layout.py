"""The house's import rules, checked by parsing the sources (no imports run).

Data flows one way: evaluation never imports training code (stages, the
trainer, the training step, the optimiser, the losses); `data/` run-time
readers never import the offline writers except the synthetic generator that
`sources` builds on first use; nothing imports `sources` from `data/convert`.
"""

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / 'slotformer_jax'
TRAINING = ('slotformer_jax.stages', 'slotformer_jax.train.trainer',
            'slotformer_jax.train.steps', 'slotformer_jax.train.optim',
            'slotformer_jax.train.state', 'slotformer_jax.losses')


def _imports(path: pathlib.Path) -> set[str]:
  """Every module `path` imports (`from a import b` counts as a and a.b)."""
  found = set()
  for node in ast.walk(ast.parse(path.read_text())):
    if isinstance(node, ast.Import):
      found.update(alias.name for alias in node.names)
    elif isinstance(node, ast.ImportFrom) and node.module:
      found.add(node.module)
      found.update(f'{node.module}.{alias.name}' for alias in node.names)
  return found


def _module(path: pathlib.Path) -> str:
  parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
  return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def _closure(start: str) -> set[str]:
  """Project modules reachable from `start` through imports."""
  files = {_module(p): p for p in PACKAGE.rglob('*.py')}
  seen, todo = set(), [start]
  while todo:
    name = todo.pop()
    if name in seen or name not in files:
      continue
    seen.add(name)
    todo += [m for m in _imports(files[name]) if m in files]
  return seen


def test_evaluation_imports_no_training_code():
  for path in (PACKAGE / 'evaluation').glob('*.py'):
    reached = _closure(_module(path))
    assert not reached & set(TRAINING), (path.name, reached & set(TRAINING))


def test_tasks_import_no_training_code():
  # The downstream tasks train their own readouts (tasks/readout.py) but read
  # SAVi and SlotFormer only through inference.py.
  for path in (PACKAGE / 'tasks').glob('*.py'):
    reached = _closure(_module(path))
    assert not reached & set(TRAINING), (path.name, reached & set(TRAINING))


def test_inference_and_workdir_import_no_training_code():
  for name in ('slotformer_jax.inference', 'slotformer_jax.workdir'):
    assert not _closure(name) & set(TRAINING), name


def test_no_import_cycle_between_sources_and_the_generator():
  for path in (PACKAGE / 'data' / 'convert').glob('*.py'):
    assert 'slotformer_jax.data.sources' not in _closure(_module(path)), path


def test_the_closure_sees_imports():
  # Guards the checks above against passing because they see nothing.
  assert 'slotformer_jax.train.steps' in _closure('slotformer_jax.stages')
  assert 'slotformer_jax.data.convert.synthetic' in _closure(
      'slotformer_jax.data.sources')
