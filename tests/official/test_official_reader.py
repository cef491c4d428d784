"""The torch-free .pth reader, on a real `torch.save` file (tests/data).

tests/data/official_tiny.pth was written once by `torch.save` (torch 2.13)
from official-style key names with values given by the formulas below; it
holds a transposed (non-contiguous) tensor, views into a shared storage
with an offset, float16/bfloat16/float64/int64/bool tensors, a 0-d tensor, an
nn.Parameter and an Adam + StepLR training state.
"""

import os
import pickle
import zipfile

import ml_dtypes
import numpy as np
import pytest

from slotformer_jax.official import pth_reader

FIXTURE = os.path.join(os.path.dirname(__file__), '..', 'data', 'official_tiny.pth')


def test_reads_the_state_dict_exactly():
  state = pth_reader.read_state_dict(FIXTURE, reader='numpy')
  base = np.arange(24, dtype=np.float32).reshape(4, 6) / 8
  expected = {
      'slot_attention.project_k.weight':
          np.arange(12, dtype=np.float32).reshape(3, 4) / 10,
      'slot_attention.gru.bias_hh': np.arange(9, dtype=np.float64) - 4,
      'decoder.0.0.weight': np.arange(6, dtype=np.float32).reshape(2, 3).T,
      'decoder.0.0.bias': base[1, 2:5],
      'decoder.4.weight': base[:, 1],
      'init_latents': np.arange(4, dtype=np.float16).reshape(1, 2, 2),
      'rollouter.enc_t_pe': np.ones((1, 2, 2), np.float32),
      'num_batches_tracked': np.array(7, np.int64),
      'mask': np.array([True, False, True]),
      'bf16': np.array([1.5, -2.0, 0.25], ml_dtypes.bfloat16),
  }
  assert list(state) == list(expected)  # order kept
  for key, value in expected.items():
    assert state[key].dtype == value.dtype, key
    assert state[key].shape == value.shape, key
    np.testing.assert_array_equal(state[key], value, err_msg=key)
  # Views into one storage are independent arrays.
  assert state['decoder.0.0.weight'].flags['C_CONTIGUOUS']


def test_reads_the_training_bookkeeping():
  checkpoint = pth_reader.read_checkpoint(FIXTURE)
  assert checkpoint['it'] == 12 and checkpoint['epoch'] == 1
  adam = checkpoint['opt_state_dict']['state'][0]
  assert adam['exp_avg'].shape == (2, 3)
  assert checkpoint['scheduler_state_dict']['step_size'] == 3


class _Evil:

  def __reduce__(self):
    return (os.system, ('touch should_not_exist',))


def _write_archive(path, obj):
  with zipfile.ZipFile(path, 'w') as archive:
    archive.writestr('archive/data.pkl', pickle.dumps(obj, protocol=2))


def test_never_runs_code_from_the_file(tmp_path, monkeypatch):
  monkeypatch.chdir(tmp_path)
  path = str(tmp_path / 'evil.pth')
  _write_archive(path, {'state_dict': {'encoder.0.0.weight': _Evil()}})
  with pytest.raises(ValueError, match=r'encoder\.0\.0\.weight.*posix\.system'
                     r'|encoder\.0\.0\.weight.*os\.system'):
    pth_reader.read_state_dict(path, reader='numpy')
  assert not os.path.exists(tmp_path / 'should_not_exist')


def test_bare_state_dict_and_bad_files(tmp_path):
  path = str(tmp_path / 'bare.pth')
  _write_archive(path, {'a': 1.0})
  with pytest.raises(ValueError, match='not tensors'):
    pth_reader.read_state_dict(path)
  not_zip = tmp_path / 'legacy.pth'
  not_zip.write_bytes(b'\x80\x02}q\x00.')
  with pytest.raises(pth_reader.CheckpointError,
                     match=r'not a PyTorch checkpoint \(a plain pickle'):
    pth_reader.read_checkpoint(str(not_zip), reader='numpy')
