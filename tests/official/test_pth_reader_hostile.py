"""The torch-free .pth reader on hostile and mistaken files (issue 27).

Files are written byte by byte (tests/pth_files.py). The cases that crashed
the process before the reader checked tensor headers run the reader in a
child process (tests/pth_fuzz.py), so that a segmentation fault fails the
test instead of killing pytest; the child also traces the reader's memory
(tracemalloc counts NumPy's buffers) under a 3 GiB address-space limit.
"""

from __future__ import annotations

import collections
import importlib.util
import io
import json
import os
import pickle
import pickletools
import struct
import subprocess
import sys
import tarfile
import time
import tracemalloc
import zipfile

import numpy as np
import pytest

import pth_files as pf
from slotformer_jax.official import pth_reader

TESTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROOT = os.path.dirname(TESTS)
FIXTURE = os.path.join(TESTS, 'data', 'official_tiny.pth')
_MIB = 1 << 20


def _child_env() -> dict[str, str]:
  # This checkout's package, whatever the venv has installed.
  return {**os.environ, 'PYTHONPATH': os.pathsep.join(
      [ROOT, os.environ.get('PYTHONPATH', '')]).rstrip(os.pathsep)}


def read_in_child(path, max_bytes: int | None = None) -> dict:
  """The reader's outcome on `path`, read in a child process."""
  command = [sys.executable, os.path.join(TESTS, 'pth_fuzz.py'), 'read',
             str(path)] + ([] if max_bytes is None else [str(max_bytes)])
  done = subprocess.run(command, capture_output=True, text=True, timeout=300,
                        env=_child_env(), check=False)
  assert done.returncode == 0, (
      f'the reader process died with status {done.returncode}: '
      f'{done.stderr[-2000:]}')
  return json.loads(done.stdout.splitlines()[-1])


def assert_refused(outcome: dict, path, *fragments: str) -> str:
  assert outcome['outcome'] == 'error', f'read it: {outcome}'
  assert outcome['own'], f'{outcome["type"]}, not CheckpointError: {outcome}'
  message = outcome['message']
  assert '\n' not in message and str(path) in message, message
  for fragment in fragments:
    assert fragment in message, message
  return message


def _floats(n: int) -> np.ndarray:
  return np.arange(n, dtype=np.float32)


# ---------------------------------------------------------------------------
# One test per defect of the issue: a crash, memory of the process returned
# as weights, an allocation past any bound.

def test_size_past_the_storage_is_refused(tmp_path):
  path = tmp_path / 'big_size.pth'
  pf.state_dict_file(path, {'w': (_floats(1), 0, (2**20,), (1,))})
  assert_refused(read_in_child(path), path, "tensor 'state_dict/w'",
                 'reaches element 1048575',
                 "its storage '0' of 1 float32 element")


def test_negative_stride_is_refused(tmp_path):
  path = tmp_path / 'negative_stride.pth'
  pf.state_dict_file(path, {'w': (_floats(4), 3, (4,), (-100000000,))})
  assert_refused(read_in_child(path), path, "tensor 'state_dict/w'",
                 'stride (-100000000,)', 'not an int >= 0')


def test_offset_past_the_end_returns_no_memory(tmp_path):
  path = tmp_path / 'offset.pth'
  pf.state_dict_file(path, {'w': (_floats(4), 1000, (4,), (1,))})
  assert_refused(read_in_child(path), path, "tensor 'state_dict/w'",
                 'storage offset 1000 is past the end',
                 "storage '0' of 4 float32 elements")


def test_huge_shape_with_stride_0_is_refused_before_allocating(tmp_path):
  path = tmp_path / 'expanded.pth'
  pf.state_dict_file(path, {'w': (_floats(1), 0, (2**40,), (0,))})
  outcome = read_in_child(path)
  assert_refused(outcome, path, "tensor 'state_dict/w' of size "
                 '(1099511627776,)', 'needs 4398046511104 bytes')
  assert outcome['peak'] < 2 * _MIB, outcome


@pytest.mark.parametrize('record', ['says 1 float', 'agrees'])
def test_member_inflating_to_a_gib_is_never_inflated(tmp_path, record):
  """A 1 MiB zip whose storage member inflates to 1 GiB: refused before a
  byte of it is inflated, whether the tensor record contradicts the member
  (1 float) or agrees with it (2**28 floats: more than the file can hold)."""
  numel = 1 if record == 'says 1 float' else 2**28
  body = pf.Reduce(pf.ORDERED_DICT, ([(
      'w', pf.tensor('0', 'FloatStorage', numel, 0, (numel,), (1,)))],))
  path = tmp_path / 'bomb.pth'
  path.write_bytes(pf.raw_zip([
      pf.stored('archive/data.pkl', pf.dumps({'state_dict': body})),
      pf.stored('archive/byteorder', b'little'),
      pf.zeros_member('archive/data/0', 1 << 30)]))
  assert path.stat().st_size < 2 * _MIB
  outcome = read_in_child(path)
  if numel == 1:
    assert_refused(outcome, path, "tensor 'state_dict/w'",
                   "member 'archive/data/0' holds 1073741824 bytes, but its "
                   'record says 1 float32 (4 bytes)')
  else:
    assert_refused(outcome, path, "member 'archive/data/0' needs 1073741824 "
                   'bytes', '(4 x the file size + 256 MiB)')
  assert outcome['peak'] < 8 * _MIB, outcome


def test_memo_index_bomb_is_refused(tmp_path):
  """Seven pickle bytes that make CPython's unpickler allocate and clear a
  32 GiB memo (LONG_BINPUT 2**31 - 1)."""
  path = tmp_path / 'memo.pth'
  path.write_bytes(pf.archive_bytes(
      b'\x80\x02N' + b'r' + struct.pack('<I', 2**31 - 1) + b'.', {}))
  outcome = read_in_child(path)
  assert_refused(outcome, path, 'memo index 2147483647 at opcode 3')
  assert outcome['peak'] < 2 * _MIB, outcome


def test_deep_nesting_and_cycles_are_refused(tmp_path):
  deep = tmp_path / 'deep.pth'
  levels = 100_000
  deep.write_bytes(pf.archive_bytes(
      b'\x80\x02' + b'](' * levels + b'}' + b'e' * levels + b'.', {}))
  assert_refused(read_in_child(deep), deep,
                 'containers nested deeper than 64 levels')
  cycle = tmp_path / 'cycle.pth'
  # A dict holding itself under 'state_dict'.
  cycle.write_bytes(pf.archive_bytes(
      b'\x80\x02}q\x00X\n\x00\x00\x00state_dicth\x00s.', {}))
  assert_refused(read_in_child(cycle), cycle, "'state_dict' contains itself")


def test_storage_length_must_match_its_record(tmp_path):
  """The member is 12 float32 (48 bytes); records of 13 and 11 elements."""
  for numel in (13, 11):
    body = {'w': pf.tensor('0', 'FloatStorage', numel, 0, (3, 3), (3, 1))}
    path = tmp_path / f'numel{numel}.pth'
    path.write_bytes(pf.archive_bytes(pf.dumps(body),
                                      {'0': _floats(12).tobytes()}))
    assert_refused(read_in_child(path), path, "tensor 'w'",
                   "member 'archive/data/0' holds 48 bytes, but its record "
                   f'says {numel} float32 ({4 * numel} bytes)')


def test_members_are_read_only_as_their_headers_say(tmp_path):
  """A member whose headers state 48 bytes but whose stream inflates to
  64 MiB stops at 48 bytes, and its CRC (of the 64 MiB) refuses it; a
  bzip2 member (which zipfile inflates without an output bound) is
  refused unread."""
  body = pf.dumps({'w': pf.tensor('0', 'FloatStorage', 12, 0, (12,), (1,))})
  lying = tmp_path / 'lying.pth'
  lying.write_bytes(pf.raw_zip([
      pf.stored('archive/data.pkl', body),
      pf.zeros_member('archive/data/0', 64 * _MIB, stated_size=48)]))
  outcome = read_in_child(lying)
  assert_refused(outcome, lying, "member 'archive/data/0' cannot be read",
                 'Bad CRC-32')
  assert outcome['peak'] < 2 * _MIB, outcome
  bzip2 = tmp_path / 'bzip2.pth'
  bzip2.write_bytes(pf.raw_zip([
      pf.stored('archive/data.pkl', body),
      pf.RawMember('archive/data/0', b'BZh9', 48, 0, zipfile.ZIP_BZIP2)]))
  assert_refused(read_in_child(bzip2), bzip2,
                 "member 'archive/data/0' is compressed with method 12")


def test_unknown_storage_type_is_one_line(tmp_path):
  path = tmp_path / 'complex.pth'
  body = {'state_dict': {'w': pf.tensor('0', 'ComplexFloatStorage', 2, 0,
                                        (2,), (1,))}}
  path.write_bytes(pf.archive_bytes(pf.dumps(body), {'0': bytes(16)}))
  assert_refused(read_in_child(path), path, "tensor 'state_dict/w'",
                 "storage '0' has the type 'torch.ComplexFloatStorage', "
                 'which the reader does not know')


# ---------------------------------------------------------------------------
# Files that are no zip-format checkpoint: one line saying what they are.

def _legacy_pickle() -> bytes:
  """The first bytes `torch.save(..., _use_new_zipfile_serialization=False)`
  writes: the magic number, the protocol version, the system info (a file
  torch 2.13 wrote starts with these same bytes)."""
  return (pickle.dumps(0x1950a86a20f9469cfc6c, protocol=2)
          + pickle.dumps(1001, protocol=2)
          + pickle.dumps({'protocol_version': 1001, 'little_endian': True,
                          'type_sizes': {'short': 2, 'int': 4, 'long': 4}},
                         protocol=2)
          + pickle.dumps({'state_dict': {}}, protocol=2))


def _legacy_tar() -> bytes:
  out = io.BytesIO()
  with tarfile.open(fileobj=out, mode='w', format=tarfile.PAX_FORMAT) as tar:
    for name in ('sys_info', 'storages', 'tensors', 'pickle'):
      info = tarfile.TarInfo(name)
      info.size = 1
      tar.addfile(info, io.BytesIO(b'\x00'))
  return out.getvalue()


_NOT_CHECKPOINTS = {
    'empty': (lambda: b'', 'not a PyTorch checkpoint (an empty file)'),
    'random bytes': (
        lambda: b'\x13' + np.random.default_rng(0).bytes(4095),
        'not a PyTorch checkpoint (neither a zip archive nor a pre-1.6 torch '
        "file; it starts with b'\\x13"),
    'truncated zip': (
        lambda: open(FIXTURE, 'rb').read()[:1500],  # pylint: disable=consider-using-with
        'not a PyTorch checkpoint (a truncated or damaged zip archive'),
    'plain pickle': (
        lambda: pickle.dumps({'state_dict': {'w': [1.0, 2.0]}}, protocol=4),
        'not a PyTorch checkpoint (a plain pickle, not the zip archive '
        'torch.save writes)'),
    'zip without data.pkl': (
        lambda: pf.raw_zip([pf.stored('weights/w.npy', b'x')]),
        'not a PyTorch checkpoint (a zip archive with 0 */data.pkl members'),
    'gzip': (lambda: b'\x1f\x8b\x08\x00' + bytes(20),
             'not a PyTorch checkpoint (a gzip file: decompress it first)'),
}


@pytest.mark.parametrize('kind', sorted(_NOT_CHECKPOINTS))
def test_what_a_non_checkpoint_is_is_said_in_one_line(tmp_path, kind):
  make, expected = _NOT_CHECKPOINTS[kind]
  path = tmp_path / 'model.pth'
  path.write_bytes(make())
  with pytest.raises(pth_reader.CheckpointError) as caught:
    pth_reader.read_state_dict(str(path))
  assert str(caught.value) == f'{path}: {expected}' or (
      str(caught.value).startswith(f'{path}: {expected}')), caught.value
  assert '\n' not in str(caught.value)


def test_a_folder_or_a_missing_file_is_said_in_one_line(tmp_path):
  with pytest.raises(pth_reader.CheckpointError,
                     match='not a PyTorch checkpoint \\(a directory'):
    pth_reader.read_state_dict(str(tmp_path))
  with pytest.raises(pth_reader.CheckpointError, match='no such file'):
    pth_reader.read_state_dict(str(tmp_path / 'missing.pth'))


@pytest.mark.parametrize('make', [_legacy_pickle, _legacy_tar],
                         ids=['pickle', 'tar'])
def test_a_pre_1_6_checkpoint_names_the_torch_extra(tmp_path, make):
  path = tmp_path / 'old.pth'
  path.write_bytes(make())
  readers = ['numpy'] + (['auto'] if importlib.util.find_spec('torch') is None
                         else [])
  for reader in readers:
    with pytest.raises(pth_reader.CheckpointError) as caught:
      pth_reader.read_checkpoint(str(path), reader=reader)
    assert str(caught.value) == (
        f"{path}: a pre-1.6 checkpoint: install the torch extra (pip install "
        "-e '.[torch]') or re-save it with torch >= 1.6")


class _Evil:

  def __reduce__(self):
    return (os.system, ('touch should_not_exist',))


def _evil_file(path) -> None:
  with zipfile.ZipFile(path, 'w') as archive:
    archive.writestr('archive/data.pkl', pickle.dumps(
        {'state_dict': {'encoder.0.0.weight': _Evil()}}, protocol=2))


def test_a_refused_global_is_one_line_naming_key_and_global(tmp_path):
  path = tmp_path / 'evil.pth'
  _evil_file(path)
  with pytest.raises(pth_reader.CheckpointError) as caught:
    pth_reader.read_state_dict(str(path))
  message = str(caught.value)
  assert "'encoder.0.0.weight' (a 'posix.system' object, refused" in message
  assert '\n' not in message and str(path) in message


@pytest.mark.parametrize('case', ['refused global', 'folder'])
def test_the_converter_prints_reader_errors_as_one_line(tmp_path, case):
  """`python -m slotformer_jax.official.convert` on a bad --checkpoint:
  exit 1, one `error:` line naming the file, no traceback, nothing
  written."""
  if case == 'refused global':
    checkpoint, named = tmp_path / 'evil.pth', "'encoder.0.0.weight'"
    _evil_file(checkpoint)
  else:
    checkpoint, named = tmp_path, 'a directory'
  workdir = tmp_path / 'run'
  done = subprocess.run(
      [sys.executable, '-m', 'slotformer_jax.official.convert',
       f'--config={os.path.join(ROOT, "configs", "obj3d.py")}',
       f'--workdir={workdir}', f'--checkpoint={checkpoint}'],
      capture_output=True, text=True, timeout=300, env=_child_env(),
      cwd=tmp_path, check=False)
  assert done.returncode == 1, done.stderr[-3000:]
  assert 'Traceback' not in done.stderr, done.stderr[-3000:]
  errors = [line for line in done.stderr.splitlines()
            if line.startswith('error: ')]
  assert len(errors) == 1, done.stderr[-3000:]
  assert str(checkpoint) in errors[0] and named in errors[0], errors[0]
  assert not workdir.exists()


# ---------------------------------------------------------------------------
# Memory: everything the reader holds is charged to its limit first.

def _binput(i: int) -> bytes:
  return b'r' + struct.pack('<I', i)


# Pickles of `n` small objects, each shape costing the reader the most per
# opcode that we found (a list of empty sets: ~390 bytes per opcode).
_SHAPES = {
    'empty dicts': lambda n: b'](' + b'}' * n + b'e',
    'empty sets': lambda n: b'](' + b'\x8f' * n + b'e',
    'memoized dicts': lambda n: b'](' + b''.join(
        b'}' + _binput(i) for i in range(n)) + b'e',
    'int -> dict': lambda n: b'}(' + b''.join(
        b'J' + struct.pack('<i', i) + b'}' for i in range(n)) + b'u',
    'floats': lambda n: b'](' + b''.join(
        b'G' + struct.pack('>d', i) for i in range(n)) + b'e',
    'one-tuples': lambda n: b'](' + b'N\x85' * n + b'e',
    'unknown calls': lambda n: b'](cfoo\nbar\n' + _binput(0) + b'h\x00)R' * (
        n // 3) + b'e',
}


# Two shapes in the default suite, every shape with -m slow (2-3 s each).
@pytest.mark.parametrize('shape', [
    shape if shape in ('empty dicts', 'unknown calls') else pytest.param(
        shape, marks=pytest.mark.slow) for shape in sorted(_SHAPES)])
def test_pickle_objects_stay_in_the_budget(tmp_path, shape):
  """Python objects cost the reader at most BYTES_PER_OPCODE per opcode
  (plus the pickle bytes, held twice): a pickle within the limit is read
  under it, a larger one refused under it, before it is unpickled."""
  limit = 32 * _MIB
  for n, fits in ((20_000, True), (100_000, False)):
    data = b'\x80\x04' + _SHAPES[shape](n) + b'.'
    opcodes = sum(1 for _ in pickletools.genops(data))
    path = tmp_path / f'{n}.pth'
    path.write_bytes(pf.archive_bytes(data, {}))
    tracemalloc.start()
    try:
      if fits:
        pth_reader.read_checkpoint(
            str(path), limits=pth_reader.Limits(max_bytes=limit))
      else:
        with pytest.raises(pth_reader.CheckpointError,
                           match='the Python objects of more than'):
          pth_reader.read_checkpoint(
              str(path), limits=pth_reader.Limits(max_bytes=limit))
      peak = tracemalloc.get_traced_memory()[1]
    finally:
      tracemalloc.stop()
    assert peak < limit, (shape, n, peak)
    if fits:
      charged = 2 * len(data) + opcodes * pth_reader.BYTES_PER_OPCODE
      assert peak < charged + _MIB, (shape, peak / opcodes)


# ---------------------------------------------------------------------------
# The fuzz test.

def test_fuzzed_checkpoints_are_read_right_or_refused(tmp_path):
  """400 seeded mutations of tests/data/official_tiny.pth (pickle ints:
  sizes, strides, offsets, storage counts; ints turned into other types;
  deleted and doubled opcodes; memo indices; member lengths and names;
  byteorder; deflated members inflating to 16 MiB, honest or lying
  headers; truncations; bit flips; nesting; random views of random
  storages) read in one child process under a 4 MiB limit: each must
  equal the independent reference (tests/pth_fuzz.py) bit for bit or be
  refused by both, as one CheckpointError line naming the file, tracing at
  most the limit + 2 MiB; the child must not die."""
  cases = 400
  done = subprocess.run(
      [sys.executable, os.path.join(TESTS, 'pth_fuzz.py'), 'fuzz', '0',
       str(cases), str(tmp_path)],
      capture_output=True, text=True, timeout=600, env=_child_env(),
      check=False)
  verdicts = [json.loads(line) for line in done.stdout.splitlines()]
  assert done.returncode == 0 and len(verdicts) == cases, (
      f'the fuzz process died with status {done.returncode} after '
      f'{len(verdicts)} cases (the next: case {len(verdicts)}): '
      f'{done.stderr[-2000:]}')
  problems = [v for v in verdicts if 'problem' in v]
  assert not problems, problems[:5]
  outcomes = collections.Counter(
      (v['what'].split()[0], v['reference'] == 'read') for v in verdicts)
  # Not vacuous: both outcomes happen, for the value-checking mutations too.
  for kind in ('int', 'view', 'bomb', 'lie'):
    assert outcomes[(kind, True)] and outcomes[(kind, False)], (
        outcomes)
  kinds = {kind for kind, _ in outcomes}
  assert kinds >= {'int', 'view', 'type', 'delete', 'duplicate', 'memo',
                   'length', 'name', 'byteorder', 'bomb', 'lie', 'truncate',
                   'flip', 'depth'}, kinds


def test_huge_ints_in_the_header_are_named_not_printed(tmp_path):
  """Python refuses to print an int of more than 4300 digits; a header
  full of them is still refused in one line."""
  huge = 2**20000 + 1
  for name, (numel, offset, size, stride) in {
      'numel': (huge, 0, (2,), (1,)),
      'offset': (4, huge, (2,), (1,)),
      'size': (4, 0, (huge, 0), (1, 1)),
      'stride': (4, 0, (2, 3), (huge, 1)),
  }.items():
    path = tmp_path / f'{name}.pth'
    path.write_bytes(pf.archive_bytes(
        pf.dumps({'w': pf.tensor('0', 'FloatStorage', numel, offset, size,
                                 stride)}), {'0': bytes(16)}))
    with pytest.raises(pth_reader.CheckpointError) as caught:
      pth_reader.read_checkpoint(str(path))
    assert '<20001-bit int>' in str(caught.value), caught.value


def test_a_zip_directory_is_charged_before_zipfile_reads_it(tmp_path):
  """60000 empty members: zipfile would build ~30 MB of ZipInfo objects."""
  path = tmp_path / 'members.pth'
  path.write_bytes(pf.raw_zip([pf.stored(f'archive/x{i}', b'')
                               for i in range(60000)]))
  tracemalloc.start()
  try:
    with pytest.raises(pth_reader.CheckpointError,
                       match='the zip directory .as ZipInfo objects. needs'):
      pth_reader.read_checkpoint(
          str(path), limits=pth_reader.Limits(max_bytes=8 * _MIB))
    peak = tracemalloc.get_traced_memory()[1]
  finally:
    tracemalloc.stop()
  assert peak < 8 * _MIB, peak


# ---------------------------------------------------------------------------
# Attributes the pickle sets on a state dict (BUILD), and names that reach
# the terminal.

def _build_file(path, state, items=None, storage=bytes(16)) -> None:
  """{'state_dict': OrderedDict(items)} with BUILD `state` on the
  OrderedDict, as torch.save writes `_metadata`; storage '0' holds 4
  floats."""
  items = items if items is not None else [
      ('w', pf.tensor('0', 'FloatStorage', 4, 0, (2, 2), (2, 1)))]
  body = pf.Build(pf.Reduce(pf.ORDERED_DICT, (items,)), state)
  path.write_bytes(pf.archive_bytes(pf.dumps({'state_dict': body}),
                                    {'0': storage}))


def test_a_state_dict_s_metadata_is_kept_and_its_values_checked(tmp_path):
  """torch.save's own `_metadata` attribute reads as torch.load reads it
  (a plain OrderedDict with the attribute); tensors hidden in attributes
  are checked like every other one. Before, the walk looked only at the
  items: a state dict whose only tensor sat in an attribute came back as an
  empty state dict, the tensor unchecked (here past its storage)."""
  path = tmp_path / 'metadata.pth'
  _build_file(path, {'_metadata': {'': {'version': 1}}},
              storage=np.arange(4, dtype='<f4').tobytes())
  state_dict = pth_reader.read_checkpoint(str(path))['state_dict']
  assert type(state_dict) is collections.OrderedDict  # not the reader's own
  assert state_dict._metadata == {'': {'version': 1}}
  np.testing.assert_array_equal(state_dict['w'], [[0, 1], [2, 3]])
  path = tmp_path / 'hidden.pth'
  _build_file(path, {'_hidden': pf.tensor('0', 'FloatStorage', 4, 3, (2, 2),
                                          (2, 1))}, items=[])
  with pytest.raises(pth_reader.CheckpointError,
                     match=r"tensor 'state_dict/<attribute _hidden>'.*past "
                     'the end'):
    pth_reader.read_state_dict(str(path))


@pytest.mark.parametrize('state, needle', [
    # An attribute that shadows a method: the caller's `dict(state_dict)`
    # would call the pickle's object (a traceback before).
    ({'keys': pf.Global('os', 'system')}, "attribute 'keys'"),
    ({'__class__': 1}, "attribute '__class__'"),
    # Attributes set through setattr (a (state, slotstate) pair).
    ((None, {'_x': 1}), 'a tuple state'),
    ([1, 2], 'a list state'),
])
def test_a_build_that_is_not_torch_s_metadata_is_refused(tmp_path, state,
                                                         needle):
  path = tmp_path / 'build.pth'
  _build_file(path, state)
  outcome = read_in_child(path)
  assert_refused(outcome, path, needle)


def test_a_build_into_the_reader_s_functions_is_refused(tmp_path):
  """The pickle may name torch's rebuild functions; a BUILD into one set
  attributes on the reader's own function before (kept for every later
  file of the process). Now each read gets fresh inert callables."""
  path = tmp_path / 'function.pth'
  body = {'state_dict': pf.Reduce(pf.ORDERED_DICT, ([],)),
          'f': pf.Build(pf.REBUILD_TENSOR, (None, {'__defaults__': (1,)}))}
  path.write_bytes(pf.archive_bytes(pf.dumps(body), {}))
  outcome = read_in_child(path)
  assert_refused(outcome, path, 'BUILD on a Call')


# What a hostile key or member name holds: a screen clear, a window title,
# and a forged second line.
_HOSTILE_NAME = '\x1b[2J\x1b]0;owned\x07\nerror: forged line\r'


def _no_raw_control(text: str) -> None:
  raw = [c for c in text if not c.isprintable() and c != '\n']
  assert not raw, (raw, text)
  forged = [line for line in text.splitlines() if 'forged' in line
            and line.startswith('error: forged')]
  assert not forged, text


def test_names_from_the_file_are_escaped_in_the_reader_s_messages(
    tmp_path):
  # A member name, in the message of a pickle that does not load.
  path = tmp_path / 'member.pth'
  path.write_bytes(pf.archive_bytes(b'\x80\x02X', {}, prefix=_HOSTILE_NAME[
      :-1].replace('\n', ' ')))
  outcome = read_in_child(path)
  assert outcome['outcome'] == 'error' and outcome['own'], outcome
  _no_raw_control(outcome['message'])
  # A key, in a refusal of its value.
  path = tmp_path / 'key.pth'
  body = pf.Reduce(pf.ORDERED_DICT, ([(_HOSTILE_NAME, 3)],))
  path.write_bytes(pf.archive_bytes(pf.dumps({'state_dict': body}), {}))
  with pytest.raises(pth_reader.CheckpointError) as caught:
    pth_reader.read_state_dict(str(path))
  _no_raw_control(str(caught.value))
  assert '\n' not in str(caught.value)


def test_the_converter_escapes_keys_it_does_not_know(tmp_path):
  """A state dict whose keys no official family knows: the converter lists
  some keys in its `error:` line. Before, they were printed raw: this one
  cleared the screen, retitled the terminal and printed a second,
  forged `error:` line."""
  path = tmp_path / 'keys.pth'
  pf.state_dict_file(path, {_HOSTILE_NAME: (np.zeros(4, np.float32), 0,
                                            (4,), (1,))})
  workdir = tmp_path / 'run'
  done = subprocess.run(
      [sys.executable, '-m', 'slotformer_jax.official.convert',
       f'--config={os.path.join(ROOT, "configs", "obj3d.py")}',
       f'--workdir={workdir}', f'--checkpoint={path}'],
      capture_output=True, text=True, timeout=300, env=_child_env(),
      cwd=tmp_path, check=False)
  assert done.returncode == 1, done.stderr[-3000:]
  _no_raw_control(done.stderr)
  errors = [line for line in done.stderr.splitlines()
            if line.startswith('error:')]
  assert len(errors) == 1 and 'no official model family' in errors[0], (
      done.stderr[-3000:])
  assert '\\x1b[2J' in errors[0], errors[0]
  assert not workdir.exists()


# ---------------------------------------------------------------------------
# Keys whose hashes a file can steer (issue 53).

_P = 2**61 - 1  # ints that differ by a multiple of it hash alike


def _with_side(side) -> bytes:
  body = pf.Reduce(pf.ORDERED_DICT, ([('w', pf.tensor(
      '0', 'FloatStorage', 2, 0, (2,), (1,)))],))
  return pf.archive_bytes(pf.dumps({'state_dict': body, 'side': side}),
                          {'0': bytes(8)})


@pytest.mark.parametrize('keys, needle', [
    ([(i + 1) * _P for i in range(20_000)], 'the int 2305843009213693951'),
    ([-(i + 1) * _P for i in range(3)], 'the int -2305843009213693951'),
    ([2**64, 1], 'the int 18446744073709551616'),
    ([(1, 2), (3, 4)], 'a tuple'),
    ([0.5, 1.5], 'a float'),
], ids=['20000_colliding_ints', 'negative', 'int_2_64', 'tuples', 'floats'])
def test_dict_keys_whose_hash_a_file_can_steer_are_refused_at_once(
    tmp_path, keys, needle):
  """Before: int keys that are multiples of 2**61 - 1 (all one hash value)
  took time quadratic in their number to unpickle (docs/reliability.md);
  now the first is refused."""
  path = tmp_path / 'side.pth'
  path.write_bytes(_with_side({key: 0 for key in keys}))
  started = time.perf_counter()
  with pytest.raises(pth_reader.CheckpointError) as caught:
    pth_reader.read_checkpoint(str(path))
  took = time.perf_counter() - started
  message = str(caught.value)
  assert str(path) in message and '\n' not in message
  assert f'a dict key or set member is {needle}' in message, message
  assert took < 1.0, took


def test_set_members_are_checked_as_keys(tmp_path):
  for opcodes, needle in (
      # EMPTY_SET MARK <ints> ADDITEMS; MARK <ints> FROZENSET
      (b'\x8f(' + pf.encode_int(2 * _P) + pf.encode_int(3 * _P) + b'\x90',
       'the int 4611686018427387902'),
      (b'(' + pf.encode_int(2 * _P) + b'\x91', 'the int 4611686018427387902'),
      (b'((\x88\x89Nt\x91', 'a tuple')):  # frozenset({(True, False, None)})
    path = tmp_path / 'set.pth'
    pickle_bytes = b'\x80\x04' + opcodes + b'.'
    path.write_bytes(pf.archive_bytes(pickle_bytes, {}))
    with pytest.raises(pth_reader.CheckpointError, match=needle):
      pth_reader.read_checkpoint(str(path))


def test_small_int_and_text_keys_are_read_as_before(tmp_path):
  """An optimizer state's int keys (0..n-1), text, bytes and None."""
  keys = [0, 1, -1, -2, _P - 1, -(_P - 1), 'a', b'b', None]
  path = tmp_path / 'keys.pth'
  path.write_bytes(_with_side({key: 7 for key in keys}))
  loaded = pth_reader.read_checkpoint(str(path))
  assert list(loaded['side']) == keys
  fixture = pth_reader.read_checkpoint(FIXTURE)
  assert sorted(fixture['opt_state_dict']['state']) == [0, 1]
