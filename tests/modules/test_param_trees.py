"""The parameter trees of the shipped configs' slot models, pinned.

Checkpoints (orbax restores by path) and the official-weight converters
(`official/savi.py`, `official/steve.py`) depend on every parameter's path
and shape, so a refactor of the modules must not move one. Each entry below
is the SHA-256 (first 16 hex digits) of the sorted lines
`<path> <shape> <dtype>` of one model's parameters, built by
`slotformer_jax.models` from a shipped config (or a variant no shipped
config sets, on synthetic:tiny). The values were recorded when SAVi and
STEVE became compositions of parts (issue 35) and checked then against the
trees, initial values and outputs of the flat modules before it.

If a change moves a parameter on purpose, existing checkpoints and the
converters need migrating: say so in the change, then print the new values
with `python tests/modules/test_param_trees.py` and update them here.
"""

import hashlib
import json
import os
import sys

import jax
import jax.numpy as jnp
import pytest

from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.slot_models import steve as steve_slots

_TESTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [_TESTS, os.path.dirname(_TESTS)]  # when run as a script
from pipeline_helpers import load_config  # pylint: disable=wrong-import-position

# (config, variant) -> the hash of its slot model (SAVi, or STEVE and its
# dVAE for slot_model='steve').
SHIPPED = {
    ('synthetic', ''): {'savi': 'e3c4235703e6c539'},
    ('synthetic', 'tiny'): {'savi': 'e3c4235703e6c539'},
    ('synthetic', 'steve'): {
        'steve': '78a4959be72892d5', 'dvae': '2abcb6313a8c76de'},
    ('synthetic', 'steve_tiny'): {
        'steve': '1f5e5824001401f1', 'dvae': '2abcb6313a8c76de'},
    ('synthetic_contact', ''): {'savi': 'e3c4235703e6c539'},
    ('synthetic_contact', 'tiny'): {'savi': 'e3c4235703e6c539'},
    ('synthetic_contact', 'side'): {'savi': 'e3c4235703e6c539'},
    ('synthetic_contact', 'bank'): {'savi': 'e3c4235703e6c539'},
    ('synthetic_phyre', ''): {'savi': 'c66f145684205fbb'},
    ('synthetic_phyre', 'tiny'): {'savi': 'c66f145684205fbb'},
    ('synthetic_phyre', 'ramp'): {'savi': 'c66f145684205fbb'},
    ('synthetic_phyre', 'ramp_layouts'): {'savi': 'c66f145684205fbb'},
    ('synthetic_vqa', ''): {'savi': 'c66f145684205fbb'},
    ('synthetic_vqa', 'tiny'): {'savi': 'c66f145684205fbb'},
    ('synthetic_vqa', 'long_savi'): {'savi': 'c66f145684205fbb'},
    ('synthetic_vqa', 'big'): {'savi': 'c66f145684205fbb'},
    ('synthetic_vqa', 'deflect'): {'savi': 'c66f145684205fbb'},
    ('clevrer', ''): {'savi': 'ca671b7552fe3c93'},
    ('clevrer_vqa', ''): {'savi': 'ca671b7552fe3c93'},
    ('obj3d', ''): {'savi': 'f44a9e8727cd0b8f'},
    ('phyre', ''): {'savi': '64c440e7c5d5e206'},
    ('phyre', 'planning'): {'savi': '64c440e7c5d5e206'},
    ('physion', ''): {'steve': 'a8adea6dd10b1dc9', 'dvae': 'defa1a448ee1deac'},
    ('physion_contact', ''): {
        'steve': 'a8adea6dd10b1dc9', 'dvae': 'defa1a448ee1deac'},
    # configs/movi.py follows SAVi's configs since issue 51: conditional
    # (the box MLP, no learned slots: A and D share a tree) and SAVi-S's
    # position MLP (64 hidden, 32 out), and a corrector without Slot
    # Attention's MLP (SAVi's `mlp_size` unset); no MOVi checkpoint existed.
    # The unconditional fixture is the fixture of before.
    ('movi', 'a'): {'savi': 'd37836aac6aed7f5'},
    ('movi', 'd'): {'savi': 'd37836aac6aed7f5'},
    ('movi', 'fixture'): {'savi': '72e3b856d88d436c'},
    ('movi', 'fixture_uncond'): {'savi': 'a9ebc59b8f4a1a73'},
    ('movi', 'savipp'): {'savi': '0b632f9955ce246b'},
}

# synthetic:tiny with the `config.savi` fields of choices no shipped config
# makes.
VARIANTS = {
    'boxes': (dict(initial_slots='boxes'), '83ec8e61c51d22df'),
    'points': (dict(initial_slots='points'), '104f2430f2de1c63'),
    'gaussian': (dict(initial_slots='gaussian'), '1789402eaa6a9711'),
    'transformer_lstm': (dict(predictor=dict(kind='transformer_lstm',
                                             lstm_size=32),
                              posterior_head='mlp'), 'b4478a9224ce91d1'),
    'residual_mlp': (dict(predictor=dict(kind='residual_mlp'),
                          posterior_head='linear', stochastic=True),
                     'e1afb2e2ddfcec1e'),
}


def tree_hash(params) -> str:
  lines = sorted(
      '/'.join(str(getattr(key, 'key', key)) for key in path)
      + f' {tuple(leaf.shape)} {leaf.dtype}'
      for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0])
  return hashlib.sha256('\n'.join(lines).encode()).hexdigest()[:16]


def _shapes(module, *args, **kwargs):
  rngs = {name: jax.random.key(0) for name in ('params', 'sample', 'dropout',
                                               'gumbel')}
  return jax.eval_shape(lambda: module.init(rngs, *args, **kwargs))['params']


_CACHE = {}


def model_trees(config) -> dict:
  """{'savi': shapes} or {'steve': shapes, 'dvae': shapes}: the parameter
  shapes of `config`'s models (built once for configs with the same model
  sections)."""
  sections = ('steve', 'dvae') if config.slot_model == 'steve' else ('savi',)
  key = json.dumps([config.slot_model, list(config.data.resolution)]
                   + [config[name].to_dict() for name in sections],
                   sort_keys=True, default=str)
  if key not in _CACHE:
    _CACHE[key] = _model_trees(config)
  return _CACHE[key]


def _model_trees(config) -> dict:
  resolution = tuple(config.data.resolution)
  clip = jnp.zeros((1, 2, *resolution, 3))
  if config.slot_model == 'steve':
    steve = steve_slots.build_steve(config.steve, resolution,
                               config.dvae.vocab_size)
    tokens = jnp.zeros((1, 2, steve.token_grid[0] * steve.token_grid[1]),
                       jnp.int32)
    dvae = steve_slots.build_dvae(config.dvae)
    return {'steve': _shapes(steve, clip, tokens),
            'dvae': _shapes(dvae, clip[:, 0], 1.0)}
  savi = config.savi
  extra = {}
  if savi.initial_slots in ('boxes', 'points'):
    extra['boxes'] = jnp.zeros((1, savi.num_slots - 1, 4))
  return {'savi': _shapes(savi_slots.build_savi(savi, resolution), clip,
                          **extra)}


def model_hashes(config) -> dict[str, str]:
  return {name: tree_hash(tree) for name, tree in model_trees(config).items()}


def _variant_config(updates):
  config = load_config('synthetic', 'tiny')
  config.savi.update(updates)
  return config


@pytest.mark.parametrize('name,variant', sorted(SHIPPED))
def test_shipped_config_parameter_trees_are_pinned(name, variant):
  assert model_hashes(load_config(name, variant)) == SHIPPED[name, variant]


def test_the_official_models_keep_the_flat_top_level_names():
  """What a failing hash above is most likely about, readably."""
  savi = model_trees(load_config('obj3d'))['savi']
  assert set(savi) == {'encoder', 'initial_slots', 'frame_step', 'decoder'}
  assert set(savi['frame_step']) == {'corrector', 'predictor',
                                     'posterior_head'}
  steve = model_trees(load_config('physion'))['steve']
  assert set(steve) == {'encoder', 'initial_slots', 'frame_step', 'decoder'}
  assert set(steve['frame_step']) == {'corrector', 'predictor'}
  assert 'position_embedding' in steve['decoder']  # the token decoder


@pytest.mark.parametrize('label', sorted(VARIANTS))
def test_savi_variant_parameter_trees_are_pinned(label):
  updates, expected = VARIANTS[label]
  assert model_hashes(_variant_config(updates)) == {'savi': expected}


if __name__ == '__main__':
  for key in SHIPPED:
    print(key, model_hashes(load_config(*key)))
  for label, (updates, _) in VARIANTS.items():
    print(label, model_hashes(_variant_config(updates)))
