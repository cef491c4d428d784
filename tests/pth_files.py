"""Writes `torch.save`-format files without torch, byte by byte, for tests
of the reader on files torch would never write (negative strides, sizes
past the storage, members that inflate to a GiB...).

The pickle is emitted opcode by opcode (protocol 2, as torch.save writes
it), so any value can go anywhere: `Global` and `Reduce` stand for the
globals and calls a checkpoint holds, `PersistentId` for a storage
reference.
"""

from __future__ import annotations

import dataclasses
import io
import pickle
import struct
import zlib
import zipfile
from typing import Any

import numpy as np


@dataclasses.dataclass(frozen=True)
class Global:
  module: str
  name: str


@dataclasses.dataclass(frozen=True)
class Reduce:
  """`callable(*args)` in the pickle (GLOBAL ... TUPLE REDUCE)."""
  callable: Any
  args: tuple


@dataclasses.dataclass(frozen=True)
class PersistentId:
  pid: tuple


@dataclasses.dataclass(frozen=True)
class Build:
  """`obj` then `state` then BUILD: the pickle sets `state` on `obj` (how
  torch.save writes a state dict's `_metadata` attribute)."""
  obj: Any
  state: Any


REBUILD_TENSOR = Global('torch._utils', '_rebuild_tensor_v2')
ORDERED_DICT = Global('collections', 'OrderedDict')

# numpy dtype name -> torch storage class (the reader's table, written
# out again here so that a wrong entry there does not agree with itself).
STORAGE_CLASSES = {
    'float64': 'DoubleStorage', 'float32': 'FloatStorage',
    'float16': 'HalfStorage', 'int64': 'LongStorage', 'int32': 'IntStorage',
    'int16': 'ShortStorage', 'int8': 'CharStorage', 'uint8': 'ByteStorage',
    'bool': 'BoolStorage',
}


def tensor(storage_key: str, storage_class: str, storage_numel: Any,
           offset: Any, size: Any, stride: Any) -> Reduce:
  """`_rebuild_tensor_v2(storage, offset, size, stride, False, {})`."""
  storage = PersistentId(('storage', Global('torch', storage_class),
                          storage_key, 'cpu', storage_numel))
  return Reduce(REBUILD_TENSOR, (storage, offset, size, stride, False,
                                 Reduce(ORDERED_DICT, ())))


def encode_int(value: int) -> bytes:
  if 0 <= value < 256:
    return b'K' + bytes([value])
  if 0 <= value < 65536:
    return b'M' + struct.pack('<H', value)
  if -2**31 <= value < 2**31:
    return b'J' + struct.pack('<i', value)
  data = pickle.encode_long(value)
  if len(data) < 256:
    return b'\x8a' + bytes([len(data)]) + data
  return b'\x8b' + struct.pack('<I', len(data)) + data  # LONG4


def _emit(value: Any, out: io.BytesIO) -> None:
  if value is None:
    out.write(b'N')
  elif value is True or value is False:
    out.write(b'\x88' if value else b'\x89')
  elif isinstance(value, int):
    out.write(encode_int(value))
  elif isinstance(value, float):
    out.write(b'G' + struct.pack('>d', value))
  elif isinstance(value, str):
    data = value.encode('utf-8', 'surrogatepass')
    out.write(b'X' + struct.pack('<I', len(data)) + data)
  elif isinstance(value, bytes):
    out.write(b'C' + bytes([len(value)]) + value if len(value) < 256
              else b'B' + struct.pack('<I', len(value)) + value)
  elif isinstance(value, Global):
    out.write(f'c{value.module}\n{value.name}\n'.encode())
  elif isinstance(value, Reduce):
    _emit(value.callable, out)
    _emit(tuple(value.args), out)
    out.write(b'R')
  elif isinstance(value, PersistentId):
    _emit(tuple(value.pid), out)
    out.write(b'Q')
  elif isinstance(value, Build):
    _emit(value.obj, out)
    _emit(value.state, out)
    out.write(b'b')
  elif isinstance(value, tuple):
    out.write(b'(')
    for item in value:
      _emit(item, out)
    out.write(b't')
  elif isinstance(value, list):
    out.write(b']')
    if value:
      out.write(b'(')
      for item in value:
        _emit(item, out)
      out.write(b'e')
  elif isinstance(value, dict):
    out.write(b'}')
    if value:
      out.write(b'(')
      for key, item in value.items():
        _emit(key, out)
        _emit(item, out)
      out.write(b'u')
  else:
    raise TypeError(f'cannot emit {type(value).__name__}')


def dumps(value: Any) -> bytes:
  """Protocol-2 pickle of `value` (see the module docstring)."""
  out = io.BytesIO()
  out.write(b'\x80\x02')
  _emit(value, out)
  out.write(b'.')
  return out.getvalue()


def archive_bytes(pickle_bytes: bytes, members: dict[str, bytes],
                  prefix: str = 'archive', compress: tuple[str, ...] = (),
                  byteorder: str | None = 'little') -> bytes:
  """A torch.save zip: `<prefix>/data.pkl`, `<prefix>/data/<key>` for each
  member (`key -> bytes`), `byteorder`, `version`; members named in
  `compress` are deflated (torch stores them)."""
  out = io.BytesIO()
  with zipfile.ZipFile(out, 'w') as archive:
    archive.writestr(f'{prefix}/data.pkl', pickle_bytes)
    if byteorder is not None:
      archive.writestr(f'{prefix}/byteorder', byteorder)
    for key, data in members.items():
      archive.writestr(
          f'{prefix}/data/{key}', data,
          compress_type=(zipfile.ZIP_DEFLATED if key in compress
                         else zipfile.ZIP_STORED))
    archive.writestr(f'{prefix}/version', '3\n')
  return out.getvalue()


def state_dict_file(path, tensors: dict[str, tuple[np.ndarray, int, tuple,
                                                   tuple]],
                    wrap: bool = True) -> None:
  """Writes `{'state_dict': {name: tensor}}` (or the bare dict), one storage
  per entry: `name -> (flat storage array, offset, size, stride)`, with the
  storage's true element count in its record."""
  entries, members = {}, {}
  for index, (name, (flat, offset, size, stride)) in enumerate(
      tensors.items()):
    flat = np.ascontiguousarray(flat).reshape(-1)
    key = str(index)
    members[key] = flat.astype(flat.dtype.newbyteorder('<')).tobytes()
    entries[name] = tensor(key, STORAGE_CLASSES[flat.dtype.name], flat.size,
                           offset, tuple(size), tuple(stride))
  body = Reduce(ORDERED_DICT, (list((k, v) for k, v in entries.items()),))
  obj = {'state_dict': body} if wrap else body
  with open(path, 'wb') as f:
    f.write(archive_bytes(dumps(obj), members))


@dataclasses.dataclass(frozen=True)
class RawMember:
  """A zip member given as its stored payload: `payload` is the bytes in the
  archive (deflated when `method` is ZIP_DEFLATED), `size` and `crc` what
  the headers say about the inflated bytes, true or not."""
  name: str
  payload: bytes
  size: int
  crc: int
  method: int = zipfile.ZIP_STORED


def stored(name: str, data: bytes) -> RawMember:
  return RawMember(name, data, len(data), zlib.crc32(data))


def raw_zip(members: list[RawMember]) -> bytes:
  """A zip archive (no zip64) with exactly the headers `members` give, so a
  member can inflate to more than its header says."""
  out = io.BytesIO()
  directory = io.BytesIO()
  for member in members:
    name = member.name.encode()
    offset = out.tell()
    fields = struct.pack('<HHHHHIIIHH', 20, 0, member.method, 0, 0x21,
                         member.crc, len(member.payload), member.size,
                         len(name), 0)
    out.write(b'PK\x03\x04' + fields + name + member.payload)
    directory.write(b'PK\x01\x02' + struct.pack('<H', 20) + fields
                    + struct.pack('<HHHII', 0, 0, 0, 0, offset) + name)
  start = out.tell()
  out.write(directory.getvalue())
  out.write(b'PK\x05\x06' + struct.pack('<HHHHIIH', 0, 0, len(members),
                                        len(members), len(directory.getvalue()),
                                        start, 0))
  return out.getvalue()


_ZERO_BLOCK = 1 << 20


def deflated_zeros(size: int) -> tuple[bytes, int]:
  """(raw deflate stream, crc32) of `size` zero bytes, without holding them:
  after a full flush the compressor starts afresh, so each MiB of zeros is
  the same compressed block."""
  compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
  block = compressor.compress(bytes(_ZERO_BLOCK)) + compressor.flush(
      zlib.Z_FULL_FLUSH)
  whole, rest = divmod(size, _ZERO_BLOCK)
  tail = zlib.compressobj(9, zlib.DEFLATED, -15)
  stream = block * whole + tail.compress(bytes(rest)) + tail.flush()
  crc, zeros = 0, bytes(_ZERO_BLOCK)
  for _ in range(whole):
    crc = zlib.crc32(zeros, crc)
  return stream, zlib.crc32(bytes(rest), crc)


def zeros_member(name: str, size: int, stated_size: int | None = None,
                 stated_crc: int | None = None) -> RawMember:
  """A deflated member of `size` zeros whose headers state `stated_size`
  and `stated_crc` (the true ones by default)."""
  stream, crc = deflated_zeros(size)
  return RawMember(name, stream, size if stated_size is None else stated_size,
                   crc if stated_crc is None else stated_crc,
                   zipfile.ZIP_DEFLATED)
