"""TFRecord framing and CRC32C without TensorFlow (data/tfrecord.py)."""

import struct

import numpy as np
import pytest

from dataset_fixtures import write_tfrecords
from slotformer_jax.data import tfrecord


def reference_crc32c(data: bytes) -> int:
  """Bit by bit, from the definition (reflected 0x82f63b78)."""
  register = 0xFFFFFFFF
  for byte in data:
    register ^= byte
    for _ in range(8):
      register = (register >> 1) ^ (0x82F63B78 if register & 1 else 0)
  return register ^ 0xFFFFFFFF


def test_crc32c_known_values():
  # RFC 3720 (iSCSI) appendix B.4 and the usual check value.
  assert tfrecord.crc32c(b'123456789') == 0xE3069283
  assert tfrecord.crc32c(bytes(32)) == 0x8A9136AA
  assert tfrecord.crc32c(b'\xff' * 32) == 0x62A8AB43
  assert tfrecord.crc32c(bytes(range(32))) == 0x46DD794E
  assert tfrecord.crc32c(b'') == 0


@pytest.mark.parametrize('size', [1, 1023, 1024, 4095, 4096, 4097, 9000,
                                  3 * 1024 * 4 + 5])
def test_vectorised_crc32c_equals_the_definition(size):
  data = np.random.default_rng(size).integers(0, 256, size, np.uint8)
  assert tfrecord.crc32c(data.tobytes()) == reference_crc32c(data.tobytes())


def test_masked_crc_is_tensorflows():
  crc = tfrecord.crc32c(b'abc')
  rotated = ((crc >> 15) | (crc << 17)) & 0xFFFFFFFF
  assert tfrecord.masked_crc32c(b'abc') == (rotated + 0xA282EAD8) % 2**32


def test_round_trip_and_framing(tmp_path):
  records = [b'', b'a', bytes(range(256)) * 50]
  path = tmp_path / 'x.tfrecord'
  write_tfrecords(path, records)
  raw = path.read_bytes()
  # The framing by hand: length, its masked CRC, data, its masked CRC.
  (length,) = struct.unpack('<Q', raw[12 + 4:12 + 4 + 8])
  assert length == 1 and raw[12 + 4 + 12:12 + 4 + 13] == b'a'
  assert len(raw) == sum(16 + len(r) for r in records)
  spans = tfrecord.index_records(path)
  assert [s.length for s in spans] == [0, 1, 12800]
  assert list(tfrecord.iter_records(path)) == records


def test_truncated_and_damaged_files_name_the_file(tmp_path):
  path = tmp_path / 'x.tfrecord'
  write_tfrecords(path, [b'x' * 100, b'y' * 100])
  good = path.read_bytes()
  path.write_bytes(good[:-10])
  with pytest.raises(tfrecord.TFRecordError, match='x.tfrecord: truncated'):
    tfrecord.index_records(path)
  damaged = bytearray(good)
  damaged[3] ^= 1  # the first length
  path.write_bytes(bytes(damaged))
  with pytest.raises(tfrecord.TFRecordError, match='length checksum'):
    tfrecord.index_records(path)
  damaged = bytearray(good)
  damaged[50] ^= 1  # inside the first record's data
  path.write_bytes(bytes(damaged))
  span = tfrecord.index_records(path)[0]
  with pytest.raises(tfrecord.TFRecordError,
                     match='x.tfrecord: record 0: data checksum'):
    tfrecord.read_record(path, span)
  assert tfrecord.read_record(path, span, verify=False)[38] == ord('x') ^ 1
