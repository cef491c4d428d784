"""Reads PyTorch `.pth` files into NumPy arrays without importing torch.

`torch.save` (PyTorch >= 1.6) writes a zip archive: `<name>/data.pkl` is a
pickle of the saved object in which every tensor is a call of
`torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)` and
every storage a persistent id `('storage', torch.FloatStorage, key, device,
numel)` whose bytes are the member `<name>/data/<key>`.

The unpickler here executes nothing from the file: the few torch globals a
checkpoint of tensors needs are mapped to NumPy functions defined in this
module, `collections.OrderedDict` to itself, and every other global (an
optimizer's or scheduler's bookkeeping) becomes an inert `Opaque` record
that is never called. A state dict holding such a record is refused.

The old non-zip format (PyTorch < 1.6) needs torch itself:
`pip install -e .[torch]` and `read_checkpoint(path, reader='torch')`.
"""

from __future__ import annotations

import collections
import pickle
import zipfile
from typing import Any

import numpy as np

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


class _StorageType:
  """Stands for `torch.<X>Storage` in a persistent id."""

  def __init__(self, name: str):
    self.name = name
    dtype = _STORAGE_DTYPES[name]
    if dtype == 'bfloat16':
      import ml_dtypes  # pylint: disable=g-import-not-at-top  (a jax dependency)
      dtype = ml_dtypes.bfloat16
    self.dtype = np.dtype(dtype)


def _rebuild_tensor(storage: np.ndarray, storage_offset: int, size, stride,
                    *unused) -> np.ndarray:
  """`torch._utils._rebuild_tensor_v2` on a flat NumPy storage."""
  del unused  # requires_grad, backward hooks, metadata
  size, stride = tuple(size), tuple(stride)
  if not size:
    return np.array(storage[storage_offset])
  itemsize = storage.dtype.itemsize
  view = np.lib.stride_tricks.as_strided(
      storage[storage_offset:], shape=size,
      strides=tuple(s * itemsize for s in stride), writeable=False)
  return np.array(view, order='C')  # own, contiguous memory


def _rebuild_parameter(data, requires_grad, backward_hooks, *unused):
  del requires_grad, backward_hooks, unused
  return data


class _Unpickler(pickle.Unpickler):
  """See the module docstring: maps globals, never imports from the file."""

  def __init__(self, file, archive: zipfile.ZipFile, prefix: str,
               byteorder: str):
    super().__init__(file)
    self._archive = archive
    self._prefix = prefix
    self._byteorder = '<' if byteorder == 'little' else '>'
    self._storages: dict[str, np.ndarray] = {}

  def find_class(self, module: str, name: str) -> Any:
    if module == 'collections' and name == 'OrderedDict':
      return collections.OrderedDict
    if module == 'torch._utils' and name == '_rebuild_tensor_v2':
      return _rebuild_tensor
    if module == 'torch._utils' and name == '_rebuild_parameter':
      return _rebuild_parameter
    if module == 'torch' and name in _STORAGE_DTYPES:
      return _StorageType(name)
    return Opaque(f'{module}.{name}')

  def persistent_load(self, pid: Any) -> Any:
    if not (isinstance(pid, tuple) and pid and pid[0] == 'storage'):
      raise pickle.UnpicklingError(f'unsupported persistent id {pid!r}')
    storage_type, key = pid[1], str(pid[2])
    if not isinstance(storage_type, _StorageType):
      raise pickle.UnpicklingError(
          f'storage {key} has an unsupported type {storage_type!r}; read '
          "this file with reader='torch' (pip install -e .[torch])")
    if key not in self._storages:
      data = self._archive.read(f'{self._prefix}/data/{key}')
      dtype = storage_type.dtype.newbyteorder(self._byteorder)
      self._storages[key] = np.frombuffer(data, dtype=dtype).astype(
          storage_type.dtype.newbyteorder('='))
    return self._storages[key]


def _read_zip(path: str) -> Any:
  with zipfile.ZipFile(path) as archive:
    pickles = [n for n in archive.namelist() if n.endswith('/data.pkl')]
    if len(pickles) != 1:
      raise ValueError(f'{path}: not a torch.save archive (found '
                       f'{len(pickles)} data.pkl members)')
    prefix = pickles[0][:-len('/data.pkl')]
    byteorder = 'little'
    if f'{prefix}/byteorder' in archive.namelist():
      byteorder = archive.read(f'{prefix}/byteorder').decode().strip()
    with archive.open(pickles[0]) as file:
      return _Unpickler(file, archive, prefix, byteorder).load()


def _read_with_torch(path: str) -> Any:
  try:
    import torch  # pylint: disable=g-import-not-at-top
  except ImportError as error:
    raise ImportError(
        f'{path} is in the pre-1.6 torch format, which needs torch to read: '
        'pip install -e .[torch]') from error
  loaded = torch.load(path, map_location='cpu', weights_only=True)

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


def read_checkpoint(path: str, reader: str = 'auto') -> Any:
  """The object `torch.save` wrote to `path`, tensors as NumPy arrays.

  Args:
    path: a `.pth` file.
    reader: 'numpy' (no torch needed; zip format), 'torch' (needs torch),
      'auto' (numpy for zip files, torch otherwise).
  """
  if reader not in ('auto', 'numpy', 'torch'):
    raise ValueError(f"reader must be 'auto', 'numpy' or 'torch', got "
                     f'{reader!r}')
  if reader == 'torch' or (reader == 'auto' and not zipfile.is_zipfile(path)):
    return _read_with_torch(path)
  if not zipfile.is_zipfile(path):
    raise ValueError(f'{path} is not a zip-format torch file')
  return _read_zip(path)


def read_state_dict(path: str, reader: str = 'auto') -> dict[str, np.ndarray]:
  """The model weights in `path`: its 'state_dict' entry (the authors'
  checkpoints), or the file itself when it is a bare state dict."""
  loaded = read_checkpoint(path, reader)
  if isinstance(loaded, dict) and 'state_dict' in loaded:
    loaded = loaded['state_dict']
  if not isinstance(loaded, dict):
    raise ValueError(f'{path} holds a {type(loaded).__name__}, not a state '
                     'dict or {"state_dict": ...}')
  not_arrays = {key: value for key, value in loaded.items()
                if not isinstance(value, np.ndarray)}
  if not_arrays:
    raise ValueError(
        f'{path}: these state dict entries are not tensors the reader can '
        'build: ' + ', '.join(f'{k} ({v!r})' for k, v in not_arrays.items()))
  return dict(loaded)
