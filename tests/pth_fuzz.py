"""Runs the .pth reader on hostile files in a child process, so that a crash
(a segmentation fault) fails a test instead of killing pytest.

  python tests/pth_fuzz.py read FILE [MAX_BYTES]
      one JSON line: the reader's outcome on FILE and its peak traced memory.
  python tests/pth_fuzz.py fuzz SEED CASES FOLDER
      CASES mutations of tests/data/official_tiny.pth; one JSON line per
      case, each comparing the reader with `reference_read` below.

`reference_read` is the oracle, written apart from the reader: pickle's
Python unpickler with recording stand-ins, the documented rules checked one
by one (dict keys and set members too, before they are hashed),
and every tensor value gathered by explicit indices (`np.indices`) that are
asserted to lie inside the storage bytes. A case passes when the reader
returns what the reference returns (bit for bit), or when both refuse and
the reader's refusal is its own one-line `CheckpointError` naming the file;
in every case the reader's peak traced memory (tracemalloc, which counts
NumPy's buffers) must stay under its byte limit plus 2 MiB.
"""

from __future__ import annotations

import collections
import io
import json
import math
import os
import pickle
import pickletools
import random
import struct
import sys
import tracemalloc
import zipfile
import zlib
from typing import Any

import ml_dtypes  # before tracing: the reader imports it lazily
import numpy as np

import pth_files

HERE = os.path.dirname(os.path.abspath(__file__))
FIXTURE = os.path.join(HERE, 'data', 'official_tiny.pth')
MEMORY_SLACK = 2 << 20   # what the reader may trace beyond its byte limit
AS_LIMIT = 3 << 30       # address space of the child (a backstop)
BYTES_PER_OPCODE = 512   # the reader's documented charges: per opcode,
DIRECTORY_FACTOR = 12    # per byte of the zip directory

_DTYPES = {
    'DoubleStorage': '<f8', 'FloatStorage': '<f4', 'HalfStorage': '<f2',
    'BFloat16Storage': 'bfloat16', 'LongStorage': '<i8', 'IntStorage': '<i4',
    'ShortStorage': '<i2', 'CharStorage': 'i1', 'ByteStorage': 'u1',
    'BoolStorage': 'bool',
}


class Refused(Exception):
  """The reference finds the file unreadable under the documented rules."""


# ----------------------------------------------------------------------------
# The reference reader.

class _TensorCall:
  def __init__(self, args):
    self.args = args


class _StorageRef:
  def __init__(self, key):
    self.key = key


class _StorageType:
  def __init__(self, name):
    self.name = name


class _Unknown:
  def __init__(self, name, args=()):
    self.name, self.args, self.state = name, args, None

  def __call__(self, *args):
    return _Unknown(self.name, args)

  def __setstate__(self, state):
    self.state = state


def _key_allowed(key) -> bool:
  """The documented rule for dict keys and set members: text, bytes, a
  bool, None, an int of magnitude below 2**61 - 1 (hashed to itself), or
  an object hashed by identity (the stand-ins here)."""
  if type(key) in (str, bytes, bool, type(None)):
    return True
  if type(key) is int:
    return abs(key) < 2**61 - 1
  return type(key).__hash__ is object.__hash__


def _keys_checked(load, keys):
  """`load` (an opcode of pickle's Python unpickler), after `keys(self)`
  (the keys it is about to hash) are checked."""
  def checked(self):
    if not all(_key_allowed(key) for key in keys(self)):
      raise Refused('a dict key or set member whose hash a file can steer')
    load(self)
  return checked


class _RecordingUnpickler(pickle._Unpickler):  # pylint: disable=protected-access
  """Records tensors and storages; one reference per storage key, with
  every persistent id that named it. pickle's Python unpickler, whose
  opcodes that hash keys are wrapped to check them first (the items since
  the last mark are `self.stack` there)."""

  dispatch = dict(pickle._Unpickler.dispatch)  # pylint: disable=protected-access
  for _opcode, _keys in ((pickle.SETITEM, lambda u: u.stack[-2:-1]),
                         (pickle.SETITEMS, lambda u: u.stack[::2]),
                         (pickle.DICT, lambda u: u.stack[::2]),
                         (pickle.ADDITEMS, lambda u: u.stack),
                         (pickle.FROZENSET, lambda u: u.stack)):
    dispatch[_opcode[0]] = _keys_checked(dispatch[_opcode[0]], _keys)
  del _opcode, _keys

  def __init__(self, file):
    super().__init__(file)
    self.refs: dict[str, _StorageRef] = {}
    self.pids: dict[str, list[tuple]] = collections.defaultdict(list)

  def find_class(self, module, name):
    if (module, name) == ('collections', 'OrderedDict'):
      return collections.OrderedDict
    if (module, name) == ('torch._utils', '_rebuild_tensor_v2'):
      return lambda *args: _TensorCall(args)
    if module == 'torch._utils' and name in ('_rebuild_parameter',
                                             '_rebuild_parameter_with_state'):
      return lambda data, *rest: data
    if module == 'torch' and name in _DTYPES:
      return _StorageType(name)
    return _Unknown(f'{module}.{name}')

  def persistent_load(self, pid):
    if not (type(pid) is tuple and len(pid) == 5 and type(pid[0]) is str
            and pid[0] == 'storage'):
      raise Refused('persistent id')
    key = pid[2]
    if not (type(key) is str or type(key) is int):
      raise Refused('storage key type')
    key = str(key)
    if not key or len(key) > 1000:
      raise Refused('storage key length')
    self.pids[key].append(pid)
    return self.refs.setdefault(key, _StorageRef(key))


def _np_dtype(type_name: str) -> np.dtype:
  if type_name == 'BFloat16Storage':
    return np.dtype(ml_dtypes.bfloat16)
  return np.dtype(_DTYPES[type_name])


def _exact_int(value) -> bool:
  return isinstance(value, int) and not isinstance(value, bool)


def reference_read(path: str, max_bytes: int) -> Any:
  """What the reader must return for `path`, or `Refused`."""
  try:
    archive = zipfile.ZipFile(path)
  except Exception as error:
    raise Refused(f'zip: {error!r}') from None
  with archive:
    try:
      names = archive.namelist()
    except Exception as error:
      raise Refused(repr(error)) from None
    pickles = [n for n in names if n.endswith('/data.pkl')]
    if len(pickles) != 1:
      raise Refused(f'{len(pickles)} data.pkl')
    prefix = pickles[0][:-len('/data.pkl')]

    def member(name, expected=None):
      if name not in names:
        raise Refused(f'no member {name}')
      info = archive.getinfo(name)
      if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise Refused('compression method')
      if expected is not None and info.file_size != expected:
        raise Refused(f'{name}: {info.file_size} bytes, not {expected}')
      try:
        return archive.read(name)
      except Exception as error:
        raise Refused(f'{name}: {error!r}') from None

    order = '<'
    if f'{prefix}/byteorder' in names:
      if archive.getinfo(f'{prefix}/byteorder').file_size > 16:
        raise Refused('byteorder size')
      text = member(f'{prefix}/byteorder').strip()
      if text not in (b'little', b'big'):
        raise Refused('byteorder')
      order = '<' if text == b'little' else '>'
    data = member(pickles[0])
    with open(path, 'rb') as f:  # zipfile's ZipInfo objects, ~10x
      used = DIRECTORY_FACTOR * zipfile._EndRecData(f)[zipfile._ECD_SIZE]  # pylint: disable=protected-access
    used += 2 * len(data)  # the reader holds it twice for a moment
    # Memo indices no pickler writes (the reader refuses them before the
    # unpickler would allocate a memo that long).
    count = 0
    try:
      for count, (op, arg, _) in enumerate(pickletools.genops(data), 1):
        if used + count * BYTES_PER_OPCODE > max_bytes:
          raise Refused('budget (pickle)')
        if op.name in ('PUT', 'BINPUT', 'LONG_BINPUT') and not 0 <= arg <= count:
          raise Refused('memo index')
    except Refused:
      raise
    except Exception as error:
      raise Refused(f'opcodes: {error!r}') from None
    used += count * BYTES_PER_OPCODE
    if used > max_bytes:
      raise Refused('budget (pickle)')
    unpickler = _RecordingUnpickler(io.BytesIO(data))
    try:
      loaded = unpickler.load()
    except Refused:
      raise
    except Exception as error:
      raise Refused(f'unpickle: {error!r}') from None

    # Depth (the longest path through containers) and cycles.
    heights = {}

    def height(obj, ancestors):
      if isinstance(obj, (dict, list, tuple, set, frozenset, _Unknown)):
        if id(obj) in ancestors:
          raise Refused('cycle')
        if len(ancestors) >= 64:
          raise Refused('depth')  # a path of more than 64 containers
        if id(obj) not in heights:
          items = (list(obj.keys()) + list(obj.values())
                   if isinstance(obj, dict) else
                   list(obj.args) + [obj.state] if isinstance(obj, _Unknown)
                   else list(obj))
          heights[id(obj)] = 1 + max(
              (height(v, ancestors | {id(obj)}) for v in items), default=0)
        return heights[id(obj)]
      return 0

    if height(loaded, frozenset()) > 64:
      raise Refused('depth')

    def storage_of(ref):
      """(key, type, numel) that every persistent id of the key agrees on."""
      described = set()
      for pid in unpickler.pids[ref.key]:
        if not isinstance(pid[1], _StorageType):
          raise Refused('storage type')
        if not _exact_int(pid[4]) or pid[4] < 0:
          raise Refused('numel')
        described.add((pid[1].name, pid[4]))
      if len(described) != 1:
        raise Refused('inconsistent storage records')
      (type_name, numel), = described
      return ref.key, type_name, numel

    plans = []     # (call, key, type, numel, offset, size, stride)
    bare = []      # storage refs reached as values

    def plan(obj, seen):
      if id(obj) in seen:
        return
      seen.add(id(obj))
      if isinstance(obj, _TensorCall):
        args = obj.args
        if not 4 <= len(args) <= 7 or not isinstance(args[0], _StorageRef):
          raise Refused('tensor args')
        key, type_name, numel = storage_of(args[0])
        offset, size, stride = args[1], args[2], args[3]
        if not _exact_int(offset) or offset < 0:
          raise Refused('offset')
        for dims in (size, stride):
          if type(dims) not in (tuple, list) or len(dims) > 32:
            raise Refused('dims')
          if not all(_exact_int(d) and d >= 0 for d in dims):
            raise Refused('dims')
        if len(size) != len(stride):
          raise Refused('ndim')
        plans.append((obj, key, type_name, numel, offset, tuple(size),
                      tuple(stride)))
        return
      if isinstance(obj, _StorageRef):
        bare.append(obj)
        return
      children = (list(obj.keys()) + list(obj.values())
                  if isinstance(obj, dict) else
                  list(obj.args) + [obj.state] if isinstance(obj, _Unknown)
                  else
                  list(obj) if isinstance(obj, (list, tuple, set, frozenset))
                  else [])
      for child in children:
        plan(child, seen)

    plan(loaded, set())
    storages: dict[str, tuple[str, int]] = {}   # key -> (type, numel)
    for key, type_name, numel in ([p[1:4] for p in plans]
                                  + [storage_of(r) for r in bare]):
      storages[key] = (type_name, numel)

    for _, key, type_name, numel, offset, size, stride in plans:
      itemsize = _np_dtype(type_name).itemsize
      if math.prod(max(n, 1) for n in size) * itemsize >= 2**62:
        raise Refused('extent')
      count = math.prod(size)
      if count:
        last = offset + sum((n - 1) * s for n, s in zip(size, stride))
        if offset >= numel or last >= numel:
          raise Refused('out of the storage')
    for key, (type_name, numel) in storages.items():
      used += numel * _np_dtype(type_name).itemsize
    for _, key, type_name, _, _, size, _ in plans:
      used += math.prod(size) * _np_dtype(type_name).itemsize
    for ref in bare:
      key, type_name, numel = storage_of(ref)
      used += numel * _np_dtype(type_name).itemsize
    if used > max_bytes:
      raise Refused('budget')

    flats = {}
    for key, (type_name, numel) in storages.items():
      dtype = _np_dtype(type_name)
      raw = member(f'{prefix}/data/{key}', numel * dtype.itemsize)
      if type_name == 'BoolStorage':
        flats[key] = np.frombuffer(raw, np.uint8) != 0
      else:
        flats[key] = np.frombuffer(raw, dtype.newbyteorder(order)).astype(
            dtype.newbyteorder('='))

    values = {}
    for call, key, type_name, numel, offset, size, stride in plans:
      flat = flats[key]
      assert len(flat) == numel
      index = np.full(size, offset, np.int64)
      for axis, grid in enumerate(np.indices(size, dtype=np.int64)):
        if size[axis] > 1:  # else the index along it is 0, whatever stride
          index = index + grid * stride[axis]
      if index.size:
        assert 0 <= index.min() and index.max() < len(flat), 'out of storage'
      values[id(call)] = np.array(flat[index])
    for ref in bare:
      values[id(ref)] = flats[storage_of(ref)[0]].copy()

  def rebuild(obj):
    if isinstance(obj, (_TensorCall, _StorageRef)):
      return values[id(obj)]
    if isinstance(obj, collections.OrderedDict):
      return collections.OrderedDict((rebuild(k), rebuild(v))
                                     for k, v in obj.items())
    if isinstance(obj, dict):
      return {rebuild(k): rebuild(v) for k, v in obj.items()}
    if isinstance(obj, list):
      return [rebuild(v) for v in obj]
    if isinstance(obj, tuple):
      return tuple(rebuild(v) for v in obj)
    if isinstance(obj, _Unknown):
      return ('unknown', obj.name, tuple(rebuild(v) for v in obj.args),
              rebuild(obj.state))
    return obj

  try:
    return rebuild(loaded)
  except TypeError as error:  # an array as a dict key
    raise Refused(repr(error)) from None


def same(a: Any, b: Any, path: str = '') -> str | None:
  """None when the reader's `a` equals the reference's `b`, else where not."""
  from slotformer_jax.official import pth_reader  # pylint: disable=g-import-not-at-top
  if isinstance(a, pth_reader.Opaque):
    a = ('unknown', a.name, tuple(a.args), a.state)
    return same(a, b, path)
  if isinstance(b, np.ndarray):
    if not isinstance(a, np.ndarray):
      return f'{path}: {type(a).__name__}, not an array'
    if a.dtype != b.dtype or a.shape != b.shape:
      return f'{path}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}'
    if a.tobytes() != b.tobytes():
      return f'{path}: values differ'
    return None
  if type(a) is not type(b):
    return f'{path}: {type(a).__name__} vs {type(b).__name__}'
  if isinstance(b, dict):
    if list(a) != list(b):
      return f'{path}: keys {list(a)[:5]} vs {list(b)[:5]}'
    for key in b:
      found = same(a[key], b[key], f'{path}/{key}')
      if found:
        return found
    return None
  if isinstance(b, (list, tuple)):
    if len(a) != len(b):
      return f'{path}: length {len(a)} vs {len(b)}'
    for i, (x, y) in enumerate(zip(a, b)):
      found = same(x, y, f'{path}/{i}')
      if found:
        return found
    return None
  if isinstance(b, float) and math.isnan(b):
    return None if isinstance(a, float) and math.isnan(a) else f'{path}: nan'
  return None if a == b else f'{path}: {_short(a)} vs {_short(b)}'


# ----------------------------------------------------------------------------
# The reader, watched.

def run_reader(path: str, max_bytes: int | None) -> dict[str, Any]:
  """The reader's outcome on `path`, with its peak traced memory."""
  from slotformer_jax.official import pth_reader  # pylint: disable=g-import-not-at-top
  # Without a limit the call is the one any version of the reader takes,
  # so the tests can show what a version before the checks did.
  extra = ({} if max_bytes is None else
           {'limits': pth_reader.Limits(max_bytes=max_bytes)})
  own = getattr(pth_reader, 'CheckpointError', ())
  tracemalloc.start()
  tracemalloc.reset_peak()
  try:
    value = pth_reader.read_checkpoint(path, reader='numpy', **extra)
    outcome = {'outcome': 'read', 'value': value}
  except BaseException as error:  # pylint: disable=broad-except
    outcome = {'outcome': 'error', 'type': type(error).__name__,
               'own': bool(own) and isinstance(error, own),
               'message': str(error)}
  outcome['peak'] = tracemalloc.get_traced_memory()[1]
  tracemalloc.stop()
  return outcome


# ----------------------------------------------------------------------------
# Mutations of the fixture.

_INT_OPS = ('BININT1', 'BININT2', 'BININT', 'LONG1')
_VALUES = (-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 23, 24, 25, 47, 48,
           255, 256, 4096, 2**16, 2**20, 2**24, 2**31 - 1, 2**31, 2**32,
           2**40, 2**62, 2**63 - 1, 2**63, 2**64, 2**100, 2**20000, -2**31,
           -2**63)


_encode_int = pth_files.encode_int


def _short(value: Any) -> str:
  """repr, except for ints Python refuses to print (> 4300 digits)."""
  if isinstance(value, int) and value.bit_length() > 256:
    return f'<{value.bit_length()}-bit int>'
  return repr(value)[:200]


def _ops(data: bytes) -> list[tuple[str, Any, int, int]]:
  """(name, arg, start, end) of every opcode."""
  ops = list(pickletools.genops(data))
  out = []
  for i, (op, arg, pos) in enumerate(ops):
    end = ops[i + 1][2] if i + 1 < len(ops) else len(data)
    out.append((op.name, arg, pos, end))
  return out


def _splice(data: bytes, edits: list[tuple[int, int, bytes]]) -> bytes:
  for start, end, new in sorted(edits, reverse=True):
    data = data[:start] + new + data[end:]
  return data


def _zip(members: list[tuple[str, bytes]], replace: dict[str, Any] = {}
         ) -> bytes:  # pylint: disable=dangerous-default-value
  """The members, stored, except those given as `pth_files.RawMember`s."""
  return pth_files.raw_zip([replace.get(name) or pth_files.stored(name, data)
                            for name, data in members])


def fixture_members() -> list[tuple[str, bytes]]:
  with zipfile.ZipFile(FIXTURE) as archive:
    return [(info.filename, archive.read(info))
            for info in archive.infolist()]


BOMB = 16 << 20  # inflated size of the fuzz's zip bombs (the limit: 4 MiB)


def mutate(rng: random.Random, members: list[tuple[str, bytes]]
           ) -> tuple[str, bytes]:
  """One mutated file: (what was done, its bytes)."""
  members = list(members)
  names = [m[0] for m in members]
  pkl = next(i for i, n in enumerate(names) if n.endswith('/data.pkl'))
  prefix = names[pkl][:-len('/data.pkl')]
  storage_indices = [i for i, n in enumerate(names) if '/data/' in n]
  data = members[pkl][1]
  ops = _ops(data)
  int_ops = [op for op in ops if op[0] in _INT_OPS]
  kind = rng.choice(['int'] * 6 + ['view'] * 4 + [
      'type', 'delete', 'duplicate', 'memo', 'length', 'name', 'byteorder',
      'bomb', 'lie', 'truncate', 'flip', 'depth'])

  def with_pickle(new_data):
    members[pkl] = (names[pkl], new_data)
    return _zip(members)

  if kind == 'view':
    return random_views(rng)
  if kind == 'int':
    chosen = rng.sample(int_ops, rng.choice([1, 1, 1, 2, 3]))
    edits, shown = [], []
    for _, old, start, end in chosen:
      value = (rng.choice(_VALUES) if rng.random() < 0.6 else
               old + rng.choice([-2, -1, 1, 2]) if rng.random() < 0.6 else
               rng.randrange(-2**rng.randrange(1, 70), 2**rng.randrange(1, 70)))
      edits.append((start, end, _encode_int(value)))
      shown.append(f'{start}:{_short(old)}->{_short(value)}')
    return f'int {" ".join(shown)}', with_pickle(_splice(data, edits))
  if kind == 'type':
    _, old, start, end = rng.choice(int_ops)
    new = rng.choice([b'N', b'\x88', b'\x89', b'G' + struct.pack('>d', 1.5),
                      b'X\x01\x00\x00\x00x', b')', b']', b'}'])
    return f'type {start}:{old}->{new!r}', with_pickle(
        _splice(data, [(start, end, new)]))
  if kind in ('delete', 'duplicate'):
    name, _, start, end = rng.choice(ops[1:])
    new = b'' if kind == 'delete' else data[start:end] * 2
    return f'{kind} {name}@{start}', with_pickle(
        _splice(data, [(start, end, new)]))
  if kind == 'memo':
    puts = [op for op in ops if op[0] == 'BINPUT']
    _, old, start, end = rng.choice(puts)
    index = rng.choice([2**28, 2**31 - 1, 2**32 - 1, len(ops) + 5, old])
    return f'memo {start}:{old}->{index}', with_pickle(
        _splice(data, [(start, end, b'r' + struct.pack('<I', index))]))
  if kind == 'length':
    i = rng.choice(storage_indices)
    name, blob = members[i]
    change = rng.choice([-len(blob), -1, -2, 1, 2, 8, 1000])
    blob = blob[:len(blob) + change] if change < 0 else blob + bytes(change)
    members[i] = (name, blob)
    return f'length {name} {change:+d}', _zip(members)
  if kind == 'name':
    action = rng.choice(['rename', 'drop', 'drop pickle', 'second pickle',
                         'prefix'])
    if action == 'rename':
      i = rng.choice(storage_indices)
      members[i] = (f'{prefix}/data/9{rng.randrange(100)}',) + members[i][1:]
    elif action == 'drop':
      del members[rng.choice(storage_indices)]
    elif action == 'drop pickle':
      del members[pkl]
    elif action == 'second pickle':
      members.append(('other/data.pkl',) + members[pkl][1:])
    else:
      members = [(n.replace(prefix, 'elsewhere', 1) if '/data/' in n else n,
                  d) for n, d in members]
    return f'name {action}', _zip(members)
  if kind == 'byteorder':
    order = rng.choice([b'big', b'middle', b'little\n', b'x' * 40, None])
    members = [m for m in members if not m[0].endswith('/byteorder')]
    if order is not None:
      members.append((f'{prefix}/byteorder', order))
    return f'byteorder {order!r}', _zip(members)
  if kind == 'bomb':
    name, blob = members[rng.choice(storage_indices)]
    size = rng.choice([len(blob), 2 * len(blob) + 1, BOMB])
    return (f'bomb {name} inflates to {size}',
            _zip(members, {name: pth_files.zeros_member(name, size)}))
  if kind == 'lie':
    # The headers say the member is as long as its record says, the stream
    # inflates to BOMB bytes; with the CRC of its first bytes the read is
    # consistent (zipfile stops at the stated size), without it a bad CRC.
    name, blob = members[rng.choice(storage_indices)]
    crc = zlib.crc32(bytes(len(blob))) if rng.random() < 0.5 else None
    return (f'lie {name} crc={"true" if crc is None else "of the prefix"}',
            _zip(members, {name: pth_files.zeros_member(
                name, BOMB, stated_size=len(blob), stated_crc=crc)}))
  if kind == 'truncate':
    blob = _zip(members)
    cut = rng.randrange(len(blob))
    return f'truncate at {cut}', blob[:cut]
  if kind == 'flip':
    blob = bytearray(_zip(members))
    where = []
    for _ in range(rng.choice([1, 1, 2, 4])):
      at = rng.randrange(len(blob))
      blob[at] ^= 1 << rng.randrange(8)
      where.append(at)
    return f'flip {where}', bytes(blob)
  if kind == 'depth':
    levels = rng.choice([10, 63, 64, 65, 200, 3000])
    # [[...[root]...]]: the root object nested in `levels` lists.
    body = data[2:-1]
    wrapped = b'\x80\x02' + b'](' * levels + body + b'e' * levels + b'.'
    return f'depth {levels}', with_pickle(wrapped)
  raise AssertionError(kind)


def random_views(rng: random.Random) -> tuple[str, bytes]:
  """A new file of 1 to 4 tensors, each a random view (offset, size,
  stride, about half of them inside the storage) of a storage of random
  bytes: the reader's values are checked element by element."""
  tensors, members, shown = {}, {}, []
  for index in range(rng.randrange(1, 5)):
    type_name = rng.choice(sorted(_DTYPES))
    itemsize = _np_dtype(type_name).itemsize
    numel = rng.randrange(0, 25)
    key = str(index)
    members[key] = bytes(rng.randrange(256) for _ in range(numel * itemsize))
    ndim = rng.randrange(0, 4)
    size = tuple(rng.randrange(0, 5) for _ in range(ndim))
    stride = tuple(rng.choice([0, 1, 1, 2, 3, 5]) for _ in range(ndim))
    offset = rng.randrange(0, numel + 2)
    if rng.random() < 0.1:  # a size-1 dim with an absurd stride is fine
      size, stride = size + (1,), stride + (2**62,)
    tensors[f't{index}'] = pth_files.tensor(key, type_name, numel, offset,
                                            size, stride)
    shown.append(f'{type_name}[{numel}]@{offset}{size}/{stride}')
  body = pth_files.Reduce(pth_files.ORDERED_DICT, (list(tensors.items()),))
  blob = pth_files.archive_bytes(pth_files.dumps({'state_dict': body}),
                                 members)
  return 'view ' + ' '.join(shown), blob


def fuzz(seed: int, cases: int, folder: str, max_bytes: int) -> None:
  rng = random.Random(seed)
  members = fixture_members()
  for case in range(cases):
    what, blob = mutate(rng, members)
    path = os.path.join(folder, f'case{case}.pth')
    with open(path, 'wb') as f:
      f.write(blob)
    try:
      expected, reason = reference_read(path, max_bytes), None
    except Refused as refusal:
      expected, reason = None, str(refusal)
    got = run_reader(path, max_bytes)
    verdict = {'case': case, 'what': what, 'peak': got['peak'],
               'reference': 'refused: ' + reason if reason else 'read'}
    if got['outcome'] == 'read':
      if reason is not None:
        verdict['problem'] = 'read a file the reference refuses'
      else:
        found = same(got['value'], expected)
        if found:
          verdict['problem'] = f'differs from the reference at {found}'
    else:
      verdict['message'] = got['message']
      if not got['own']:
        verdict['problem'] = f'raised {got["type"]}, not CheckpointError'
      elif '\n' in got['message'] or path not in got['message']:
        verdict['problem'] = 'the message is not one line naming the file'
      elif not got['message'].isprintable():
        verdict['problem'] = 'the message holds a raw control character'
      elif reason is None:
        verdict['problem'] = 'refused a file the reference reads'
    if got['peak'] > max_bytes + MEMORY_SLACK:
      verdict['problem'] = (f'traced {got["peak"]} bytes, past the limit '
                            f'{max_bytes}')
    print(json.dumps(verdict), flush=True)
    os.remove(path)


def _limit_memory() -> None:
  try:
    import resource  # pylint: disable=g-import-not-at-top
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))
  except (ImportError, ValueError, OSError):
    pass


def main(argv: list[str]) -> None:
  _limit_memory()
  if argv[1] == 'read':
    max_bytes = int(argv[3]) if len(argv) > 3 else None
    outcome = run_reader(argv[2], max_bytes)
    outcome.pop('value', None)
    print(json.dumps(outcome), flush=True)
  elif argv[1] == 'fuzz':
    fuzz(int(argv[2]), int(argv[3]), argv[4],
         int(argv[5]) if len(argv) > 5 else 4 << 20)
  else:
    raise SystemExit(__doc__)


if __name__ == '__main__':
  main(sys.argv)
