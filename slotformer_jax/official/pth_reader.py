"""Reads PyTorch `.pth` files into NumPy arrays without importing torch, and
refuses hostile ones.

`torch.save` (PyTorch >= 1.6) writes a zip archive: `<name>/data.pkl` is a
pickle of the saved object in which every tensor is a call of
`torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)` and
every storage a persistent id `('storage', torch.FloatStorage, key, device,
numel)` whose bytes are the member `<name>/data/<key>`.

A checkpoint is a file users download from other people, so nothing in it is
trusted:

* The unpickler executes nothing from the file: the few torch globals a
  checkpoint of tensors needs are mapped to recorders defined here,
  `collections.OrderedDict` to itself, and every other global (an
  optimizer's or scheduler's bookkeeping) becomes an inert `Opaque` record
  that is never called. A state dict holding such a record is refused.
* Every dict key and set member is checked before it is hashed (pickle's
  pure-Python unpickler, whose dict opcodes can be replaced): a str, bytes,
  bool, None, an int below 2**61 - 1 in magnitude (its hash is itself) or
  one of the reader's records (hashed by identity). A tuple, float or
  larger int is refused: a file can give thousands of them one hash value
  (multiples of 2**61 - 1 all hash alike), and inserting n of them takes
  n**2 steps (docs/reliability.md, "The `.pth` reader's dict keys"); no
  checkpoint has such keys (optimizer states use small ints).
* Before the pickle runs, its opcodes are scanned (`pickletools`, pure
  Python): every length it declares must be present in the data, memo
  indices must be ones a pickler could have written, and the opcode count is
  bounded, so the C unpickler never allocates by a length it read.
* Tensors are recorded while unpickling and built only after the whole
  object has been checked: nesting depth bounded, no cycles, every tensor's
  dtype known, size and stride non-negative ints, its storage offset and its
  last element inside the storage, the storage record consistent, and its
  zip member exactly `numel * itemsize` bytes, stored or deflated. The bytes
  all of this needs (pickle, storages, built tensors) are summed and checked
  against `Limits.max_bytes` before any member is read; a member is then
  read in chunks up to the size its header gives, never inflated past it.

Every refusal is a `CheckpointError` (a `UserError`) whose one-line message
names the file and the tensor (its key path, e.g.
'state_dict/encoder.0.weight') or the member.

The old non-zip format (PyTorch < 1.6) needs torch itself:
`pip install -e '.[torch]'` (read with `reader='torch'` or 'auto').
"""

from __future__ import annotations

import collections
import dataclasses
import io
import math
import os
import pickle
import pickletools
import sys
import zipfile
from typing import Any

import numpy as np

from slotformer_jax.errors import UserError

# torch storage class -> numpy dtype ('bfloat16': ml_dtypes', loaded lazily).
_STORAGE_DTYPES = {
    'DoubleStorage': np.float64,
    'FloatStorage': np.float32,
    'HalfStorage': np.float16,
    'BFloat16Storage': 'bfloat16',
    'LongStorage': np.int64,
    'IntStorage': np.int32,
    'ShortStorage': np.int16,
    'CharStorage': np.int8,
    'ByteStorage': np.uint8,
    'BoolStorage': np.bool_,
}

# The first pickle of a pre-1.6 (non-zip) torch.save file is this number.
_LEGACY_MAGIC = 0x1950a86a20f9469cfc6c
# Member names of the even older tar format.
_LEGACY_TAR_MEMBERS = (b'sys_info', b'pickle', b'storages', b'tensors')

_MIB = 1 << 20
# What the reader charges per pickle opcode for the Python objects the
# unpickler makes (at most one per opcode) and what `_walk` keeps for each:
# the most measured is ~390 bytes (a list of empty sets), see
# tests/official/test_pth_reader_hostile.py::test_pickle_objects_stay_in_the_budget.
BYTES_PER_OPCODE = 512
# zipfile makes a ZipInfo per central-directory entry: ~10x the entry's
# bytes (measured with 1-character names, Python 3.11).
DIRECTORY_FACTOR = 12


@dataclasses.dataclass(frozen=True)
class Limits:
  """What the reader will allocate for one file.

  Attributes:
    max_bytes: pickle + storage + built tensor bytes together; None: four
      times the file's size plus `slack_bytes` (a checkpoint needs about
      twice its size: its storages, then the arrays built from them).
    slack_bytes: see `max_bytes`.
    max_pickle_bytes: size of `data.pkl` (the authors' are tens of KB).
    max_pickle_ops: opcodes in `data.pkl`, which bounds the objects it makes.
    max_depth: nesting of containers in the saved object.
    max_ndim: dimensions of one tensor (NumPy 1.x's limit).
  """

  max_bytes: int | None = None
  slack_bytes: int = 256 * _MIB
  max_pickle_bytes: int = 32 * _MIB
  max_pickle_ops: int = 1_000_000
  max_depth: int = 64
  max_ndim: int = 32

  def budget(self, file_size: int) -> int:
    if self.max_bytes is not None:
      return int(self.max_bytes)
    return 4 * file_size + self.slack_bytes


class CheckpointError(UserError, ValueError):
  """A file the reader cannot or will not read: the message (one line) names
  the file and the tensor or member at fault."""


def _one_line(text: Any, limit: int = 300) -> str:
  text = ' '.join(str(text).split())
  return text if len(text) <= limit else text[:limit] + '...'


def _fmt(value: Any, limit: int = 120) -> str:
  """A value from the file, for a message: an int of any size (Python
  refuses to print one of more than 4300 digits), a tuple or list of them
  (the first 8), a short repr of a string or float, else its type."""
  def one(item: Any) -> str:
    if isinstance(item, int) and not isinstance(item, bool):
      return (repr(item) if item.bit_length() <= 128
              else f'<{item.bit_length()}-bit int>')
    if isinstance(item, (bool, float, type(None))):
      return repr(item)
    if isinstance(item, (str, bytes)):
      return _shown(item[:60], 80)
    return f'<{type(item).__name__}>'

  if type(value) in (tuple, list):  # pylint: disable=unidiomatic-typecheck
    items = [one(item) for item in value[:8]]
    if len(value) > 8:
      items.append(f'... {len(value)} in all')
    brackets = '()' if type(value) is tuple else '[]'  # pylint: disable=unidiomatic-typecheck
    text = brackets[0] + ', '.join(items) + (
        ',' if len(value) == 1 and brackets == '()' else '') + brackets[1]
  else:
    text = one(value)
  return _one_line(text, limit)


def _shown(text: str, limit: int = 160) -> str:
  """A name from the file, quoted: no control characters reach the
  terminal, no line is longer than `limit`."""
  shown = repr(text)
  return shown if len(shown) <= limit else shown[:limit] + "...'"


class Opaque:
  """A global the reader does not know, and anything built from it.

  Records the name and the arguments it was given; never runs code.
  """

  def __init__(self, name: str, args: tuple = ()):
    self.name = name
    self.args = args
    self.state = None

  def __call__(self, *args, **kwargs):
    return Opaque(self.name, args)

  def __setstate__(self, state):
    self.state = state

  def __repr__(self):
    return f'Opaque({self.name})'


class _Inert:
  """Base of the reader's own records: a pickle cannot BUILD into them."""

  __slots__ = ()

  def __setstate__(self, state):
    raise pickle.UnpicklingError(
        f'BUILD on a {type(self).__name__.lstrip("_")}')


class _StorageClass(_Inert):
  """Stands for `torch.<X>Storage` in a persistent id."""

  __slots__ = ('name',)

  def __init__(self, name: str):
    self.name = name


class _StorageRecord(_Inert):
  """One storage key of the archive and every persistent id naming it."""

  __slots__ = ('key', 'pids')

  def __init__(self, key: str):
    self.key = key
    self.pids: list[tuple] = []


class _TensorRecord(_Inert):
  """The arguments of one `_rebuild_tensor_v2` call, checked later."""

  __slots__ = ('args',)

  def __init__(self, args: tuple):
    self.args = args


class _Call(_Inert):
  """A torch function the pickle may call, as a fresh object per read: a
  BUILD into it is refused (a module-level function would take attributes,
  even `__defaults__`, and keep them for the next file)."""

  __slots__ = ('function',)

  def __init__(self, function):
    self.function = function

  def __call__(self, *args):
    return self.function(*args)


def _rebuild_tensor(*args) -> _TensorRecord:
  return _TensorRecord(args)


def _rebuild_parameter(data, *unused):
  del unused  # requires_grad, backward hooks, state
  return data


class _StateDict(collections.OrderedDict):
  """`collections.OrderedDict` as the pickle builds it. torch.save pickles a
  state dict's `_metadata` attribute as a BUILD on it; here a BUILD only
  records its state, which `_walk` checks (names that shadow no method,
  values walked like every other child) and `_replace_records` turns into
  the attributes of a plain OrderedDict. Nothing from the file is ever set
  on an object the reader or its caller then uses."""

  __slots__ = ('builds', 'attributes')

  def __init__(self, *args):
    super().__init__(*args)
    self.builds = []
    self.attributes = {}  # set by `_walk` once checked

  def __setstate__(self, state):
    if type(self) is not _StateDict:  # BUILD on the class itself
      raise pickle.UnpicklingError('BUILD on the OrderedDict class')
    self.builds.append(state)


class _NewStateDict(_Inert):
  """What `collections.OrderedDict` is to the pickle: a fresh callable per
  read that makes `_StateDict`s."""

  __slots__ = ()

  def __call__(self, *args):
    return _StateDict(*args)


# Ints in (-_HASH_MODULUS, _HASH_MODULUS) hash to themselves (but -1 -> -2).
_HASH_MODULUS = sys.hash_info.modulus


class _KeyRefused(pickle.UnpicklingError):
  """A dict key or set member whose hash a file could steer."""


def _check_key(key: Any) -> None:
  kind = type(key)
  if kind in (str, bytes, bool, type(None)) or (
      kind is int and -_HASH_MODULUS < key < _HASH_MODULUS) or (
          kind.__hash__ is object.__hash__):
    return
  what = f'the int {_fmt(key)}' if kind is int else f'a {kind.__name__}'
  raise _KeyRefused(
      f'a dict key or set member is {what}; checkpoints have text or small '
      'int keys only (keys like it can be made to share one hash value, '
      'which makes reading them take quadratic time)')


def _pop_items(unpickler: pickle._Unpickler) -> list:  # pylint: disable=protected-access
  items = unpickler.pop_mark()
  for key in items[::2]:
    _check_key(key)
  return items


class _Unpickler(pickle._Unpickler):  # pylint: disable=protected-access
  """See the module docstring: maps globals, never imports from the file,
  reads no storage, checks every key before it is hashed.

  pickle's pure-Python unpickler (the C one fills dicts without a hook):
  about 1 us per opcode, 1 s at `Limits.max_pickle_ops`.
  """

  dispatch = dict(pickle._Unpickler.dispatch)  # pylint: disable=protected-access

  def _setitem(self):
    value = self.stack.pop()
    key = self.stack.pop()
    _check_key(key)
    self.stack[-1][key] = value

  def _setitems(self):
    items = _pop_items(self)
    target = self.stack[-1]
    for i in range(0, len(items), 2):
      target[items[i]] = items[i + 1]

  def _dict(self):
    items = _pop_items(self)
    self.append({items[i]: items[i + 1] for i in range(0, len(items), 2)})

  def _additems(self):
    items = self.pop_mark()
    for item in items:
      _check_key(item)
    target = self.stack[-1]
    if isinstance(target, set):
      target.update(items)
    else:
      for item in items:
        target.add(item)

  def _frozenset(self):
    items = self.pop_mark()
    for item in items:
      _check_key(item)
    self.append(frozenset(items))

  dispatch[pickle.SETITEM[0]] = _setitem
  dispatch[pickle.SETITEMS[0]] = _setitems
  dispatch[pickle.DICT[0]] = _dict
  dispatch[pickle.ADDITEMS[0]] = _additems
  dispatch[pickle.FROZENSET[0]] = _frozenset

  def __init__(self, file):
    super().__init__(file)
    self.storages: dict[str, _StorageRecord] = {}

  def find_class(self, module: str, name: str) -> Any:
    if module == 'collections' and name == 'OrderedDict':
      return _NewStateDict()
    if module == 'torch._utils' and name == '_rebuild_tensor_v2':
      return _Call(_rebuild_tensor)
    if module == 'torch._utils' and name in ('_rebuild_parameter',
                                             '_rebuild_parameter_with_state'):
      return _Call(_rebuild_parameter)
    if module == 'torch' and name in _STORAGE_DTYPES:
      return _StorageClass(name)
    return Opaque(f'{module}.{name}')

  def persistent_load(self, pid: Any) -> Any:
    if not (type(pid) is tuple and len(pid) == 5  # pylint: disable=unidiomatic-typecheck
            and type(pid[0]) is str and pid[0] == 'storage'):
      raise pickle.UnpicklingError(
          'a persistent id other than (storage, type, key, device, numel)')
    key = pid[2]
    if type(key) is int:  # pylint: disable=unidiomatic-typecheck
      key = str(key)
    if type(key) is not str or not key or len(key) > 1000:  # pylint: disable=unidiomatic-typecheck
      raise pickle.UnpicklingError('a storage key that is not a short string')
    record = self.storages.setdefault(key, _StorageRecord(key))
    record.pids.append(pid)
    return record


# Opcodes that store into the memo at the index given as argument.
_MEMO_PUTS = ('PUT', 'BINPUT', 'LONG_BINPUT')


def _scan_pickle(data: bytes, where: str, limits: Limits,
                 budget: _Budget) -> None:
  """Walks the opcodes without running them (see the module docstring) and
  charges `budget` for the objects they will make."""
  most = min(limits.max_pickle_ops,
             max(budget.limit - budget.used, 0) // BYTES_PER_OPCODE)
  count = 0
  try:
    for opcode, arg, _ in pickletools.genops(data):
      count += 1
      if count > most:
        if count > limits.max_pickle_ops:
          raise CheckpointError(
              f'{where}: more than {limits.max_pickle_ops} pickle opcodes')
        budget.charge(count * BYTES_PER_OPCODE,
                      f'the Python objects of more than {count - 1} opcodes')
      # A pickler numbers its memo from 0, one entry per object at most; a
      # larger index would make the unpickler allocate a memo that large.
      if opcode.name in _MEMO_PUTS and not (
          isinstance(arg, int) and 0 <= arg <= count):
        raise CheckpointError(
            f'{where}: memo index {_fmt(arg)} at opcode {count}, '
            'which no pickler writes')
  except CheckpointError:
    raise
  except Exception as error:  # pylint: disable=broad-except
    # pickletools raises ValueError for a length past the data, an unknown
    # opcode, a bad argument; the file is damaged or crafted either way.
    raise CheckpointError(f'{where}: not a valid pickle ('
                          f'{type(error).__name__}: {_one_line(error)})'
                          ) from None
  budget.charge(count * BYTES_PER_OPCODE,
                f'the Python objects of {count} pickle opcodes')


def _unpickle(data: bytes, where: str, limits: Limits,
              budget: _Budget) -> tuple[Any, _Unpickler]:
  _scan_pickle(data, where, limits, budget)
  unpickler = _Unpickler(io.BytesIO(data))
  try:
    return unpickler.load(), unpickler
  except CheckpointError:
    raise
  except _KeyRefused as error:
    raise CheckpointError(f'{where}: {error}') from None
  except Exception as error:  # pylint: disable=broad-except
    # A crafted pickle can make the unpickler raise nearly anything (a call
    # of OrderedDict with the wrong arguments, a BUILD into a record...).
    raise CheckpointError(f'{where}: the pickle does not load ('
                          f'{type(error).__name__}: {_one_line(error)})'
                          ) from None


# Path components of `_walk` that are not dict keys or indices.
_KEY, _ITEM = object(), object()
_CONTAINERS = (dict, collections.OrderedDict, _StateDict, list, tuple, set,
               frozenset)
_DICTS = (dict, collections.OrderedDict, _StateDict)


def _component(part: Any) -> str:
  if part is _KEY:
    return '<key>'
  if part is _ITEM:
    return '<item>'
  if isinstance(part, str):
    return part
  if isinstance(part, (int, float)) and not isinstance(part, bool):
    return repr(part)
  if isinstance(part, _OpaquePart):
    return f'<{part.name}>' + ('.state' if part.index is None
                               else f'[{part.index}]')
  if isinstance(part, _Attribute):
    return f'<attribute {part.name}>'
  return f'<{type(part).__name__}>'


@dataclasses.dataclass(frozen=True)
class _Attribute:
  name: str


def _attributes(obj: _StateDict, path: str, node: Any) -> dict[str, Any]:
  """The attributes the BUILDs of a `_StateDict` give it, checked: each
  BUILD's state a dict of names that are no dunder and shadow nothing an
  OrderedDict has (torch.save writes `{'_metadata': ...}`).

  Raises:
    CheckpointError: any other state.
  """
  out = {}
  for state in obj.builds:
    if type(state) is not dict:  # pylint: disable=unidiomatic-typecheck
      raise CheckpointError(
          f'{path}: the OrderedDict at {_shown(_path(node)[:200] or "the top")}'
          f' is given a {type(state).__name__} state by the pickle, not the '
          'dict of attributes torch.save writes')
    for name in state:
      if (type(name) is not str or name.startswith('__')  # pylint: disable=unidiomatic-typecheck
          or hasattr(collections.OrderedDict, name)):
        raise CheckpointError(
            f'{path}: the OrderedDict at '
            f'{_shown(_path(node)[:200] or "the top")} is given the '
            f'attribute {_fmt(name)} by the pickle, which would shadow one '
            'of its own (torch.save writes only _metadata)')
    out.update(state)
  return out


@dataclasses.dataclass(frozen=True)
class _OpaquePart:
  name: str
  index: int | None


def _path(node: tuple | None) -> str:
  """The key path of a `_walk` node: (parent node, component) links."""
  parts = []
  while node is not None:
    node, part = node
    parts.append(_component(part))
  return '/'.join(reversed(parts))


def _push_children(obj: Any, node: Any, depth: int, stack: list) -> None:
  """Pushes `obj`'s children so that they pop in their own order. Each
  entry holds (child, path node, depth, parent id): about 150 bytes, which
  `BYTES_PER_OPCODE` covers (a child is at least one opcode)."""
  parent = id(obj)
  kind = type(obj)
  if kind in _DICTS:
    if kind is _StateDict:
      for name, value in reversed(obj.attributes.items()):
        stack.append((value, (node, _Attribute(name)), depth, parent))
    for key, value in reversed(list(kind.items(obj))):
      stack.append((value, (node, key), depth, parent))
      stack.append((key, (node, _KEY), depth, parent))
  elif kind in (list, tuple):
    for index in range(len(obj) - 1, -1, -1):
      stack.append((obj[index], (node, index), depth, parent))
  elif kind in (set, frozenset):
    stack.extend((value, (node, _ITEM), depth, parent) for value in obj)
  else:  # Opaque
    stack.append((obj.state, (node, _OpaquePart(obj.name, None)), depth,
                  parent))
    for index in range(len(obj.args) - 1, -1, -1):
      stack.append((obj.args[index], (node, _OpaquePart(obj.name, index)),
                    depth, parent))


def _walk(root: Any, path: str, limits: Limits
          ) -> tuple[dict[int, tuple[_TensorRecord, str]],
                     dict[int, tuple[_StorageRecord, str]]]:
  """Every tensor and bare storage reachable from `root`, with the key path
  it is first reached by; refuses cycles and deep nesting (the longest path
  through containers, shared ones included). Iterative: a crafted pickle
  can nest deeper than Python's recursion limit."""
  tensors: dict[int, tuple[_TensorRecord, str]] = {}
  storages: dict[int, tuple[_StorageRecord, str]] = {}
  heights: dict[int, int] = {}   # finished containers: longest path down
  running: dict[int, int] = {}   # open containers: tallest child so far
  ancestors: set[int] = set()
  # (object, path node, depth, parent id), and (..., True) when leaving.
  stack: list[tuple] = [(root, None, 0, None)]

  def too_deep(node):
    return CheckpointError(
        f'{path}: containers nested deeper than {limits.max_depth} levels '
        f'(at {_shown(_path(node)[:200] or "the top")})')

  while stack:
    entry = stack.pop()
    obj, node, depth, parent = entry[:4]
    if len(entry) == 5:  # leaving a container
      ancestors.discard(id(obj))
      height = 1 + running.pop(id(obj))
      if height > limits.max_depth:
        raise too_deep(node)
      heights[id(obj)] = height
      if parent is not None:
        running[parent] = max(running[parent], height)
      continue
    if isinstance(obj, _TensorRecord):
      if id(obj) not in tensors:
        tensors[id(obj)] = (obj, _path(node))
      continue
    if isinstance(obj, _StorageRecord):
      if id(obj) not in storages:
        storages[id(obj)] = (obj, _path(node))
      continue
    if type(obj) not in _CONTAINERS and type(obj) is not Opaque:
      continue
    if id(obj) in ancestors:
      raise CheckpointError(f'{path}: {_shown(_path(node)[:200])} contains '
                            'itself (a cycle no checkpoint has)')
    if id(obj) in heights:  # shared, already walked
      if parent is not None:
        running[parent] = max(running[parent], heights[id(obj)])
      continue
    if depth >= limits.max_depth:
      raise too_deep(node)
    if type(obj) is _StateDict:  # pylint: disable=unidiomatic-typecheck
      obj.attributes = _attributes(obj, path, node)
    ancestors.add(id(obj))
    running[id(obj)] = 0
    stack.append((obj, node, depth, parent, True))
    _push_children(obj, node, depth + 1, stack)
  return tensors, storages


def _is_int(value: Any) -> bool:
  return type(value) is int  # pylint: disable=unidiomatic-typecheck  (no bool)


@dataclasses.dataclass(frozen=True)
class _Storage:
  key: str
  type_name: str
  dtype: np.dtype
  numel: int

  @property
  def nbytes(self) -> int:
    return self.numel * self.dtype.itemsize

  def describe(self) -> str:
    return (f'storage {_shown(self.key)} of {_fmt(self.numel)} {self.dtype.name} '
            f'element{"" if self.numel == 1 else "s"}')


@dataclasses.dataclass(frozen=True)
class _Tensor:
  """A checked tensor: `storage[offset + sum_i index_i * stride_i]`."""
  record_id: int
  path: str
  storage: _Storage
  offset: int
  size: tuple[int, ...]
  stride: tuple[int, ...]

  @property
  def numel(self) -> int:
    return math.prod(self.size)

  @property
  def nbytes(self) -> int:
    return self.numel * self.storage.dtype.itemsize


def _dtype(type_name: str) -> np.dtype:
  dtype = _STORAGE_DTYPES[type_name]
  if dtype == 'bfloat16':
    import ml_dtypes  # pylint: disable=g-import-not-at-top  (a jax dependency)
    dtype = ml_dtypes.bfloat16
  return np.dtype(dtype)


def _check_storage(record: _StorageRecord, what: str) -> _Storage:
  """The storage every persistent id of `record` describes, or an error."""
  described = set()
  for pid in record.pids:
    storage_class, numel = pid[1], pid[4]
    if not isinstance(storage_class, _StorageClass):
      name = (storage_class.name if isinstance(storage_class, Opaque)
              else type(storage_class).__name__)
      raise CheckpointError(
          f'{what}: storage {_shown(record.key)} has the type '
          f'{_shown(name)}, which the reader does not know (it reads '
          f'{", ".join(sorted(_STORAGE_DTYPES))}); read this file with '
          "reader='torch' (pip install -e '.[torch]')")
    if not _is_int(numel) or numel < 0:
      raise CheckpointError(
          f'{what}: storage {_shown(record.key)} has the element count '
          f'{_fmt(numel)}, not an int >= 0')
    described.add((storage_class.name, numel))
  if len(described) != 1:
    raise CheckpointError(
        f'{what}: storage {_shown(record.key)} is described '
        f'{len(described)} ways ('
        + '; '.join(sorted(f'{t} x {_fmt(n)}' for t, n in described))[:200]
        + ')')
  (type_name, numel), = described
  return _Storage(record.key, type_name, _dtype(type_name), numel)


def _check_dims(values: Any, name: str, what: str,
                limits: Limits) -> tuple[int, ...]:
  if type(values) not in (tuple, list):  # pylint: disable=unidiomatic-typecheck
    raise CheckpointError(f'{what}: its {name} is a {type(values).__name__}, '
                          'not a tuple of ints')
  if len(values) > limits.max_ndim:
    raise CheckpointError(f'{what}: its {name} has {len(values)} dimensions, '
                          f'more than {limits.max_ndim}')
  for dim, value in enumerate(values):
    if not _is_int(value) or value < 0:
      raise CheckpointError(
          f'{what}: its {name} {_fmt(values)} has '
          f'{_fmt(value)} in dimension {dim}, not an int >= 0'
          + (' (torch writes no negative stride)'
             if name == 'stride' and _is_int(value) else ''))
  return tuple(values)


def _check_tensor(record: _TensorRecord, tensor_path: str, path: str,
                  limits: Limits) -> _Tensor:
  """The tensor `record` describes, with every index inside its storage."""
  what = f'{path}: tensor {_shown(tensor_path)}'
  args = record.args
  if not 4 <= len(args) <= 7:
    raise CheckpointError(f'{what}: _rebuild_tensor_v2 called with '
                          f'{len(args)} arguments, not 4 to 7')
  storage_record, offset = args[0], args[1]
  if not isinstance(storage_record, _StorageRecord):
    raise CheckpointError(f'{what}: its storage is a '
                          f'{type(storage_record).__name__}, not a storage '
                          'of the archive')
  storage = _check_storage(storage_record, what)
  if not _is_int(offset) or offset < 0:
    raise CheckpointError(f'{what}: its storage offset '
                          f'{_fmt(offset)} is not an int >= 0')
  size = _check_dims(args[2], 'size', what, limits)
  stride = _check_dims(args[3], 'stride', what, limits)
  if len(size) != len(stride):
    raise CheckpointError(f'{what}: size {_fmt(size)} and stride {_fmt(stride)} have '
                          'different lengths')
  itemsize = storage.dtype.itemsize
  # NumPy multiplies every dimension, zeros last, in 63 bits.
  extent = math.prod(max(n, 1) for n in size)
  if extent * itemsize >= 2**62:
    raise CheckpointError(f'{what}: size {_fmt(size)} is larger '
                          'than any array')
  tensor = _Tensor(id(record), tensor_path, storage, offset, size, stride)
  if tensor.numel == 0:
    return tensor  # no element to read: any offset (as torch.load allows)
  last = offset + sum((n - 1) * s for n, s in zip(size, stride))
  if offset >= storage.numel:
    raise CheckpointError(f'{what}: storage offset {_fmt(offset)} is past the end '
                          f'of its {storage.describe()}')
  if last >= storage.numel:
    raise CheckpointError(
        f'{what}: size {_fmt(size)} with stride {_fmt(stride)} from '
        f'offset {_fmt(offset)} reaches element {_fmt(last)}, past the end of its '
        f'{storage.describe()}')
  return tensor


class _Budget:
  """Bytes the reader will hold, charged before anything is allocated."""

  def __init__(self, path: str, limits: Limits, file_size: int):
    self.path = path
    self.limit = limits.budget(file_size)
    self.explain = ('the limit given' if limits.max_bytes is not None else
                    f'4 x the file size + {limits.slack_bytes // _MIB} MiB')
    self.used = 0

  def charge(self, nbytes: int, what: str) -> None:
    self.used += nbytes
    if self.used > self.limit:
      raise CheckpointError(
          f'{self.path}: {what} needs {_fmt(nbytes)} bytes, which takes the '
          f'reader past {self.limit} bytes ({self.explain})'
          + ('; a file this small cannot hold that much data (pass '
             'pth_reader.Limits(max_bytes=...) if you trust it)'
             if self.explain != 'the limit given' else ''))


def _directory_size(path: str) -> int:
  """Bytes of the zip's central directory, from the end record zipfile will
  read (zipfile turns each entry into a ZipInfo before anything can be
  checked, so the directory is charged first)."""
  try:
    with open(path, 'rb') as f:
      end = zipfile._EndRecData(f)  # pylint: disable=protected-access  (zipfile's own reading)
  except OSError:
    end = None
  if end is None:
    raise CheckpointError(f'{path}: not a PyTorch checkpoint (a damaged zip '
                          'archive: no end-of-archive record)')
  return int(end[zipfile._ECD_SIZE])  # pylint: disable=protected-access


def _member(archive: zipfile.ZipFile, name: str,
            what: str) -> zipfile.ZipInfo:
  try:
    info = archive.getinfo(name)
  except KeyError:
    raise CheckpointError(f'{what}: the archive has no member '
                          f'{_shown(name)}') from None
  if info.flag_bits & 0x1:
    raise CheckpointError(f'{what}: member {_shown(name)} is encrypted')
  if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
    # zipfile inflates bzip2 / lzma chunks without an output bound;
    # torch.save stores every member.
    raise CheckpointError(
        f'{what}: member {_shown(name)} is compressed with method '
        f'{info.compress_type}; torch.save stores members (deflate is also '
        'read)')
  return info


def _read_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo,
                 what: str) -> bytearray:
  """The member's bytes, exactly `info.file_size` of them, read in chunks
  (zipfile never inflates more than a chunk at a time for deflate) and
  checked against the CRC the archive records."""
  size = info.file_size
  data = bytearray(size)
  view = memoryview(data)
  position = 0
  try:
    with archive.open(info) as member:
      while position < size:
        chunk = member.read(min(16 * _MIB, size - position))
        if not chunk:
          raise CheckpointError(
              f'{what}: member {_shown(info.filename)} ends after '
              f'{position} of its {size} bytes (a truncated file)')
        view[position:position + len(chunk)] = chunk
        position += len(chunk)
      member.read(1)  # at the end: zipfile checks the CRC here if not yet
  except CheckpointError:
    raise
  except Exception as error:  # pylint: disable=broad-except
    # BadZipFile (bad CRC, header mismatch), EOFError (truncated), zlib
    # errors: a damaged or crafted archive.
    raise CheckpointError(
        f'{what}: member {_shown(info.filename)} cannot be read '
        f'({type(error).__name__}: {_one_line(error)})') from None
  return data


def _build(tensor: _Tensor, flat: np.ndarray) -> np.ndarray:
  """A C-contiguous copy of the checked tensor; `flat` is its storage."""
  dtype = tensor.storage.dtype
  if tensor.numel == 0:
    return np.zeros(tensor.size, dtype)
  # Sizes of 0 or 1 never step: their stride is irrelevant (and may be
  # large), so it is not handed to NumPy.
  strides = tuple(s * flat.itemsize if n > 1 else 0
                  for n, s in zip(tensor.size, tensor.stride))
  view = np.lib.stride_tricks.as_strided(
      flat[tensor.offset:], shape=tensor.size, strides=strides,
      writeable=False)
  return np.array(view, dtype=dtype, order='C')


def _storage_array(data: bytearray, storage: _Storage,
                   byteorder: str) -> np.ndarray:
  if storage.dtype == np.bool_:
    # Any byte but 0 is true (NumPy would keep other bytes as they are).
    return np.frombuffer(data, np.uint8) != 0
  return np.frombuffer(data, storage.dtype.newbyteorder(byteorder))


def _read_zip(path: str, limits: Limits) -> Any:
  budget = _Budget(path, limits, os.path.getsize(path))
  budget.charge(DIRECTORY_FACTOR * _directory_size(path),
                'the zip directory (as ZipInfo objects)')
  try:
    archive = zipfile.ZipFile(path)
  except Exception as error:  # pylint: disable=broad-except
    raise CheckpointError(
        f'{path}: not a PyTorch checkpoint (a damaged zip archive: '
        f'{type(error).__name__}: {_one_line(error)})') from None
  with archive:
    pickles = [n for n in archive.namelist() if n.endswith('/data.pkl')]
    if len(pickles) != 1:
      raise CheckpointError(
          f'{path}: not a PyTorch checkpoint (a zip archive with '
          f'{len(pickles)} */data.pkl members, not 1)')
    prefix = pickles[0][:-len('/data.pkl')]
    byteorder = '<'
    if f'{prefix}/byteorder' in archive.NameToInfo:
      info = _member(archive, f'{prefix}/byteorder', path)
      if info.file_size > 16:
        raise CheckpointError(f'{path}: its byteorder member holds '
                              f'{info.file_size} bytes')
      text = bytes(_read_member(archive, info, path)).strip()
      if text not in (b'little', b'big'):
        raise CheckpointError(f'{path}: byteorder {_shown(text)}, not '
                              'little or big')
      byteorder = '<' if text == b'little' else '>'

    info = _member(archive, pickles[0], path)
    if info.file_size > limits.max_pickle_bytes:
      raise CheckpointError(
          f'{path}: {_shown(pickles[0])} holds {info.file_size} bytes, more '
          f'than {limits.max_pickle_bytes} (a checkpoint pickle holds no '
          'tensor data)')
    # Held twice for a moment: as read, then as the unpickler's bytes.
    budget.charge(2 * info.file_size, f'member {_shown(pickles[0])}')
    where = f'{path}: {_shown(pickles[0])}'
    loaded, unpickler = _unpickle(bytes(_read_member(archive, info, path)),
                                  where, limits, budget)
    del unpickler  # its storage records are reached through `loaded`
    records, bare_storages = _walk(loaded, path, limits)

    # Everything is checked and charged before the first storage is read.
    tensors = [_check_tensor(record, tensor_path, path, limits)
               for record, tensor_path in records.values()]
    storages: dict[str, tuple[_Storage, str, zipfile.ZipInfo]] = {}
    bare = {}
    uses = [(t.storage, f'tensor {_shown(t.path)}') for t in tensors]
    for record, storage_path in bare_storages.values():
      what = f'storage at {_shown(storage_path)}'
      bare[id(record)] = _check_storage(record, f'{path}: {what}')
      uses.append((bare[id(record)], what))
    for storage, what in uses:
      if storage.key in storages:
        continue
      name = f'{prefix}/data/{storage.key}'
      info = _member(archive, name, f'{path}: {what}')
      if info.file_size != storage.nbytes:
        raise CheckpointError(
            f'{path}: {what}: member {_shown(name)} holds {info.file_size} '
            f'bytes, but its record says {_fmt(storage.numel)} '
            f'{storage.dtype.name} ({_fmt(storage.nbytes)} bytes)')
      budget.charge(storage.nbytes, f'member {_shown(name)}')
      storages[storage.key] = (storage, what, info)
    for tensor in tensors:
      budget.charge(tensor.nbytes, f'tensor {_shown(tensor.path)} of size '
                    f'{_fmt(tensor.size)} ({tensor.storage.dtype.name})')
    for storage in bare.values():
      budget.charge(storage.nbytes, f'storage {_shown(storage.key)}')

    built: dict[int, np.ndarray] = {}
    by_storage = collections.defaultdict(list)
    for tensor in tensors:
      by_storage[tensor.storage.key].append(tensor)
    for key, (storage, what, info) in storages.items():
      flat = _storage_array(_read_member(archive, info, f'{path}: {what}'),
                            storage, byteorder)
      for tensor in by_storage[key]:
        built[tensor.record_id] = _build(tensor, flat)
      for record_id, bare_storage in bare.items():
        if bare_storage.key == key:
          built[record_id] = np.array(flat, dtype=storage.dtype)
      del flat
  return _replace_records(loaded, built, path)


def _replace_records(root: Any, built: dict[int, np.ndarray],
                     path: str) -> Any:
  """`root` with every tensor / storage record replaced by its array. A
  container with no record below it is returned as it is (not copied);
  shared objects stay shared. Recursive: `_walk` bounded the depth."""
  done: dict[int, Any] = {}

  def rebuild(obj: Any) -> Any:
    if isinstance(obj, (_TensorRecord, _StorageRecord)):
      return built[id(obj)]
    kind = type(obj)
    if kind not in _CONTAINERS and kind is not Opaque:
      return obj
    if id(obj) in done:
      return done[id(obj)]
    try:
      if kind is _StateDict:
        # Always a plain OrderedDict: the reader's class never leaves it.
        new = collections.OrderedDict(
            (rebuild(k), rebuild(v)) for k, v in kind.items(obj))
        new.__dict__.update({name: rebuild(value)
                             for name, value in obj.attributes.items()})
      elif kind in (dict, collections.OrderedDict):
        items = [(rebuild(k), rebuild(v)) for k, v in kind.items(obj)]
        same = all(k is a and v is b
                   for (k, v), (a, b) in zip(items, kind.items(obj)))
        new = obj if same else kind(items)
      elif kind is Opaque:
        args = tuple(rebuild(value) for value in obj.args)
        state = rebuild(obj.state)
        if (state is obj.state
            and all(a is b for a, b in zip(args, obj.args))):
          new = obj
        else:
          new = Opaque(obj.name, args)
          new.state = state
      else:  # list, tuple, set, frozenset
        values = [rebuild(value) for value in obj]
        new = (obj if all(a is b for a, b in zip(values, obj))
               else kind(values))
    except TypeError as error:  # an array as a dict key or set member
      raise CheckpointError(f'{path}: a tensor used as a dict key or set '
                            f'member ({_one_line(error)})') from None
    done[id(obj)] = new
    return new

  return rebuild(root)


def _first_pickle_value(head: bytes) -> tuple[bool, Any]:
  """(whether `head` starts with a complete pickle, the last argument seen)
  without running it."""
  last, count = None, 0
  try:
    for opcode, arg, _ in pickletools.genops(head):
      if opcode.name == 'STOP':
        return count > 0 and opcode.name != 'PROTO', last
      count += opcode.name != 'PROTO'
      if arg is not None and opcode.name != 'PROTO':
        last = arg
  except Exception:  # pylint: disable=broad-except  (not a pickle)
    return False, None
  return False, None


# Leading bytes of files people mistake for checkpoints.
_KNOWN_FORMATS = (
    (b'\x1f\x8b', 'a gzip file: decompress it first'),
    (b'\xfd7zXZ\x00', 'an xz file: decompress it first'),
    (b'BZh', 'a bzip2 file: decompress it first'),
    (b'\x89HDF\r\n\x1a\n', 'an HDF5 file (Keras / h5py), not torch.save'),
    (b'\x93NUMPY', 'a NumPy .npy file'),
)


def _not_a_zip(path: str) -> str:
  """'legacy' for a pre-1.6 torch.save file, else raises the one-line error
  saying what the file is instead."""
  def refuse(what: str) -> CheckpointError:
    return CheckpointError(f'{path}: not a PyTorch checkpoint ({what})')

  if os.path.isdir(path):
    raise refuse('a directory; pass the .pth file')
  if not os.path.exists(path):
    raise CheckpointError(f'{path}: no such file')
  with open(path, 'rb') as f:
    head = f.read(4096)
  if not head:
    raise refuse('an empty file')
  if head.startswith(b'PK\x03\x04') or head.startswith(b'PK\x05\x06'):
    raise refuse('a truncated or damaged zip archive: no end-of-archive '
                 'record')
  complete, value = _first_pickle_value(head)
  if complete and value == _LEGACY_MAGIC:
    return 'legacy'
  if (head[257:262] == b'ustar'
      and head[:100].rstrip(b'\0').split(b'/')[-1] in _LEGACY_TAR_MEMBERS):
    return 'legacy'
  if complete or (head[:1] == b'\x80' and head[1:2] in
                  tuple(bytes([p]) for p in range(2, 6))):
    raise refuse('a plain pickle, not the zip archive torch.save writes')
  for magic, what in _KNOWN_FORMATS:
    if head.startswith(magic):
      raise refuse(what)
  if len(head) > 10 and head[8:10] == b'{"':
    raise refuse('a safetensors file, not torch.save')
  raise refuse(f'neither a zip archive nor a pre-1.6 torch file; it starts '
               f'with {head[:12]!r}')


def _legacy_error(path: str) -> CheckpointError:
  return CheckpointError(
      f"{path}: a pre-1.6 checkpoint: install the torch extra (pip install "
      "-e '.[torch]') or re-save it with torch >= 1.6")


def _read_with_torch(path: str) -> Any:
  try:
    import torch  # pylint: disable=g-import-not-at-top
  except ImportError:
    raise CheckpointError(
        f"{path}: reader='torch' needs torch: pip install -e '.[torch]'"
    ) from None
  try:
    loaded = torch.load(path, map_location='cpu', weights_only=True)
  except Exception as error:  # pylint: disable=broad-except
    raise CheckpointError(
        f'{path}: torch.load refused it ({type(error).__name__}: '
        f'{_one_line(error)})') from None

  def to_numpy(value):
    if isinstance(value, torch.Tensor):
      return value.detach().cpu().float().numpy() if (
          value.dtype == torch.bfloat16) else value.detach().cpu().numpy()
    if isinstance(value, dict):
      return type(value)((k, to_numpy(v)) for k, v in value.items())
    if isinstance(value, (list, tuple)):
      return type(value)(to_numpy(v) for v in value)
    return value

  return to_numpy(loaded)


def _torch_installed() -> bool:
  import importlib.util  # pylint: disable=g-import-not-at-top
  return importlib.util.find_spec('torch') is not None


def read_checkpoint(path: str, reader: str = 'auto',
                    limits: Limits | None = None) -> Any:
  """The object `torch.save` wrote to `path`, tensors as NumPy arrays.

  Args:
    path: a `.pth` file.
    reader: 'numpy' (no torch needed; zip format), 'torch' (needs torch),
      'auto' (numpy for zip files, torch for pre-1.6 files).
    limits: what the numpy reader may allocate (default `Limits()`).

  Raises:
    CheckpointError: the file is missing, is no checkpoint, or is one the
      reader refuses (see the module docstring); one line.
  """
  if reader not in ('auto', 'numpy', 'torch'):
    raise ValueError(f"reader must be 'auto', 'numpy' or 'torch', got "
                     f'{reader!r}')
  path = os.fspath(path)
  if reader == 'torch':
    return _read_with_torch(path)
  if not os.path.isfile(path) or not zipfile.is_zipfile(path):
    _not_a_zip(path)  # raises unless a pre-1.6 file
    if reader == 'auto' and _torch_installed():
      return _read_with_torch(path)
    raise _legacy_error(path)
  return _read_zip(path, limits or Limits())


def read_state_dict(path: str, reader: str = 'auto',
                    limits: Limits | None = None) -> dict[str, np.ndarray]:
  """The model weights in `path`: its 'state_dict' entry (the authors'
  checkpoints), or the file itself when it is a bare state dict.

  Raises:
    CheckpointError: as `read_checkpoint`, or an entry that is not a tensor
      (an unknown global is refused here, by name).
  """
  loaded = read_checkpoint(path, reader, limits)
  if isinstance(loaded, dict) and 'state_dict' in loaded:
    loaded = loaded['state_dict']
  if not isinstance(loaded, dict):
    raise CheckpointError(
        f'{path} holds a {type(loaded).__name__}, not a state dict or '
        '{"state_dict": ...}')
  not_keys = [key for key in loaded if not isinstance(key, str)]
  if not_keys:
    raise CheckpointError(
        f'{path}: state dict keys that are not strings: '
        + ', '.join(_fmt(k) for k in not_keys[:5]))
  not_arrays = {key: value for key, value in loaded.items()
                if not isinstance(value, np.ndarray)}
  if not_arrays:
    shown = [f'{_shown(k)} (a {_shown(v.name)} object, refused: the reader '
             'runs no code from the file)' if isinstance(v, Opaque) else
             f'{_shown(k)} ({type(v).__name__})'
             for k, v in list(not_arrays.items())[:5]]
    more = len(not_arrays) - len(shown)
    raise CheckpointError(
        f'{path}: state dict entries that are not tensors: '
        + ', '.join(shown) + (f' and {more} more' if more else ''))
  return dict(loaded)
