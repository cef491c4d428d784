"""The registry and the spec every dataset module declares (datasets/)."""

from __future__ import annotations

import numpy as np
import pytest

from slotformer_jax import datasets
from slotformer_jax.data import prepare
from slotformer_jax.errors import ConfigError

CONVERTED = ('clevrer', 'movi_a', 'movi_b', 'movi_c', 'movi_d', 'movi_e',
             'movi_f', 'obj3d', 'phyre', 'physion', 'videos')
GENERATED = ('clevrer_like', 'synthetic', 'synthetic_contact',
             'synthetic_phyre')


def test_every_dataset_is_registered_by_its_module():
  assert sorted(n for n, d in datasets.DATASETS.items()
                if isinstance(d, datasets.Converted)) == list(CONVERTED)
  assert set(GENERATED) <= {n for n, d in datasets.DATASETS.items()
                            if isinstance(d, datasets.Generated)}
  # One MOVi module answers every variant.
  assert len({id(datasets.get(f'movi_{v}')) for v in 'abcdef'}) == 1
  with pytest.raises(ConfigError, match='Unknown dataset'):
    datasets.get('mnist')


@pytest.mark.parametrize('name', CONVERTED + GENERATED)
def test_the_spec_says_what_a_video_holds(name):
  dataset = datasets.get(name)
  video = dataset.features()['video']
  assert video.np_dtype == np.uint8 and len(video.shape) == 4
  assert video.shape[-1] == 3 and dataset.resolution == video.shape[1:3]
  if isinstance(dataset, datasets.Converted):
    # The spec is the default conversion's.
    options = dataset.options()
    assert dataset.resolution == options.resolution
    if dataset.frames is not None and hasattr(options, 'num_frames'):
      assert dataset.frames == options.num_frames


def test_the_facts_the_registries_used_to_repeat():
  orders = {name: datasets.get(name).official_channel_order
            for name in CONVERTED + GENERATED}
  # The official CLEVRER models read OpenCV's BGR frames, the OBJ3D, PHYRE
  # and Physion ones PIL's RGB; the others have no official models.
  assert {n for n, o in orders.items() if o == 'bgr'} == {'clevrer'}
  assert {n for n, o in orders.items() if o == 'rgb'} == {
      'obj3d', 'phyre', 'physion'}
  # CLEVRER alone offers clips beyond each video's first frames.
  assert {n: list(datasets.get(n).clip_rules) for n in CONVERTED + GENERATED
          if datasets.get(n).clip_rules} == {'clevrer': ['clevrer']}
  assert datasets.clip_rule('clevrer') is datasets.get('clevrer').clip_rules[
      'clevrer']
  # The prepare CLI's --dataset choices come from the registry.
  choices = next(a for a in prepare.build_parser()._actions  # pylint: disable=protected-access
                 if a.dest == 'dataset').choices
  assert sorted(choices) == ['clevrer', 'movi', 'obj3d', 'phyre', 'physion',
                             'videos']
  assert datasets.get('synthetic_phyre').task_data.keys() == {'planning'}
