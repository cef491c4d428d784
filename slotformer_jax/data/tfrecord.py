"""TFRecord files without TensorFlow: the framing, with its CRC32C checks.

A TFRecord file is a sequence of records, each framed as::

    uint64 length            (little endian)
    uint32 masked_crc32c(the 8 length bytes)
    byte   data[length]
    uint32 masked_crc32c(data)

where ``masked_crc32c(x) = rotate_right(crc32c(x), 15) + 0xa282ead8`` (mod
2**32) and CRC32C is the Castagnoli CRC (reflected polynomial 0x82f63b78,
initial value and final xor 0xffffffff). The published TFDS datasets (e.g.
Kubric's MOVi) are such files of serialized ``tf.train.Example`` protos.

:func:`index_records` walks a file's headers only (a seek per record) and
checks each length checksum, so a truncated or mis-framed file is found
before any conversion; :func:`read_record` reads one record and checks its
data checksum. CRC32C is computed with numpy: the data is cut into rows of
``_ROW`` bytes whose CRCs advance in lockstep (one vectorised table lookup
per byte column), then the row CRCs are chained through the linear map of
``_ROW`` zero bytes. That is about 100 MB/s on one core, enough not to
dominate a conversion that also decodes PNGs; a pure-Python loop would be
~50x slower. :func:`encode_record` frames one record (the test fixtures
write MOVi-like downloads with it); nothing here writes a file.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import struct
from collections.abc import Iterable
from pathlib import Path

import numpy as np

_POLYNOMIAL = 0x82F63B78  # CRC32C (Castagnoli), reflected
_MASK_DELTA = 0xA282EAD8
_HEADER = struct.Struct('<QI')
_FOOTER = struct.Struct('<I')
# Bytes per row of the vectorised CRC: the per-byte numpy overhead is paid
# _ROW times, the Python-level chaining len(data) / _ROW times.
_ROW = 1024


class TFRecordError(ValueError):
  """A TFRecord file is truncated, mis-framed or fails a checksum."""


def _byte_table() -> np.ndarray:
  """uint32 [256]: the CRC register update of one byte (reflected)."""
  table = np.arange(256, dtype=np.uint32)
  for _ in range(8):
    table = np.where(table & 1, (table >> 1) ^ np.uint32(_POLYNOMIAL),
                     table >> 1).astype(np.uint32)
  return table


_TABLE = _byte_table()
_TABLE_LIST = [int(v) for v in _TABLE]


def _advance_rows(columns: np.ndarray, registers: np.ndarray) -> np.ndarray:
  """Runs the CRC register of every row over its bytes.

  Args:
    columns: uint32 [L, K]: byte j of row k at [j, k].
    registers: uint32 [K] initial registers.

  Returns:
    uint32 [K], the registers after the L bytes of each row.
  """
  crc = registers.astype(np.uint32)
  for column in columns:
    crc = _TABLE[(crc ^ column) & np.uint32(0xFF)] ^ (crc >> np.uint32(8))
  return crc


@functools.lru_cache(maxsize=None)
def _zeros_tables(length: int) -> tuple[tuple[int, ...], ...]:
  """The register map of ``length`` zero bytes, as 4 byte-indexed tables.

  The CRC register update is linear over GF(2), so running ``length`` zero
  bytes from register r equals the xor of the runs from each byte of r
  alone: ``table[i][b]`` is the run from ``b << (8 * i)``.
  """
  starts = (np.arange(256, dtype=np.uint32)[None, :]
            << (np.arange(4, dtype=np.uint32)[:, None] * np.uint32(8)))
  zeros = np.zeros((length, 1024), np.uint32)
  ends = _advance_rows(zeros, starts.reshape(-1)).reshape(4, 256)
  return tuple(tuple(int(v) for v in row) for row in ends)


def _update_small(register: int, data: bytes | memoryview) -> int:
  table = _TABLE_LIST
  for byte in bytes(data):
    register = table[(register ^ byte) & 0xFF] ^ (register >> 8)
  return register


def crc32c(data: bytes | bytearray | memoryview) -> int:
  """The CRC32C (Castagnoli) of ``data``: crc32c(b'123456789') = 0xe3069283."""
  view = memoryview(data).cast('B')
  register = 0xFFFFFFFF
  rows = len(view) // _ROW
  if rows >= 4:
    body = np.frombuffer(view[:rows * _ROW], np.uint8).reshape(rows, _ROW)
    columns = np.ascontiguousarray(body.T).astype(np.uint32)
    row_crcs = _advance_rows(columns, np.zeros(rows, np.uint32)).tolist()
    t0, t1, t2, t3 = _zeros_tables(_ROW)
    # register' = zeros_map(register) ^ (row run from 0): linearity again.
    for row_crc in row_crcs:
      register = (t0[register & 0xFF] ^ t1[(register >> 8) & 0xFF]
                  ^ t2[(register >> 16) & 0xFF] ^ t3[register >> 24]
                  ^ row_crc)
    view = view[rows * _ROW:]
  return _update_small(register, view) ^ 0xFFFFFFFF


def masked_crc32c(data: bytes | bytearray | memoryview) -> int:
  """TFRecord's masked CRC32C of ``data``."""
  crc = crc32c(data)
  return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


@dataclasses.dataclass(frozen=True)
class RecordSpan:
  """Where one record's data lies in its file.

  Attributes:
    index: position of the record in the file (0-based).
    offset: byte offset of the data (after the 12-byte header).
    length: data bytes.
  """

  index: int
  offset: int
  length: int


# One record is one example (a MOVi video is a few MB); a length field can
# claim anything up to 2**64.
MAX_RECORD_BYTES = 1 << 30


def index_records(path: str | os.PathLike[str], *,
                  max_record_bytes: int = MAX_RECORD_BYTES
                  ) -> list[RecordSpan]:
  """The records of a TFRecord file, from its headers only; a record may
  hold at most `max_record_bytes`.

  Raises:
    TFRecordError: the file ends inside a record, or a length checksum
      fails (a damaged or truncated download), naming the file and record.
  """
  path = Path(path)
  size = path.stat().st_size
  spans = []
  with open(path, 'rb') as f:
    position = 0
    while position < size:
      header = f.read(_HEADER.size)
      index = len(spans)
      if len(header) < _HEADER.size:
        raise TFRecordError(
            f'{path}: truncated: {size - position} stray bytes after record '
            f'{index - 1} (a partial download?)')
      length, length_crc = _HEADER.unpack(header)
      if masked_crc32c(header[:8]) != length_crc:
        raise TFRecordError(f'{path}: record {index} at byte {position}: '
                            'length checksum mismatch (damaged file)')
      if length > max_record_bytes:
        raise TFRecordError(
            f'{path}: record {index} at byte {position} claims {length} '
            f'bytes, more than the {max_record_bytes} a record may have '
            '(a damaged file?)')
      end = position + _HEADER.size + length + _FOOTER.size
      if end > size:
        raise TFRecordError(
            f'{path}: truncated: record {index} needs bytes up to {end}, the '
            f'file has {size} (a partial download?)')
      spans.append(RecordSpan(index=index, offset=position + _HEADER.size,
                              length=length))
      position = end
      f.seek(position)
  return spans


def read_record(path: str | os.PathLike[str], span: RecordSpan, *,
                verify: bool = True) -> bytes:
  """The data of one record (its checksum checked unless ``verify=False``).

  Raises:
    TFRecordError: short read or data checksum mismatch.
  """
  with open(path, 'rb') as f:
    f.seek(span.offset)
    payload = f.read(span.length + _FOOTER.size)
  if len(payload) != span.length + _FOOTER.size:
    raise TFRecordError(f'{path}: truncated inside record {span.index}')
  data = payload[:span.length]
  if verify:
    (expected,) = _FOOTER.unpack(payload[span.length:])
    if masked_crc32c(data) != expected:
      raise TFRecordError(f'{path}: record {span.index}: data checksum '
                          'mismatch (damaged file)')
  return data


def iter_records(path: str | os.PathLike[str], *,
                 verify: bool = True) -> Iterable[bytes]:
  """Every record of a file, in order."""
  for span in index_records(path):
    yield read_record(path, span, verify=verify)


def encode_record(data: bytes) -> bytes:
  """One record's bytes in the TFRecord framing."""
  length = struct.pack('<Q', len(data))
  return (length + _FOOTER.pack(masked_crc32c(length)) + data
          + _FOOTER.pack(masked_crc32c(data)))

