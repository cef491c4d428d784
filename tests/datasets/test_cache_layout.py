"""The folders of the embedded datasets, pinned: a data dir made by an
earlier version stays usable.

Readers compute where a dataset lives from its generation parameters (each
dataset module of datasets/); the generators write there. The expected paths
below were computed with the code before the reading side moved out of the
converters (issue 35), for the data sections of every shipped config: they pin the
cache layout. A change here makes every existing data dir regenerate; do it
only with a generator version bump. The version folder of the TFDS
families went from 1.0.0 to 2.0.0 with the chunked record layout
(data/chunked.py, issue 36): the slugs are unchanged, an old 1.0.0 folder is
left alone and a chunked one generated next to it.
"""

from __future__ import annotations

import pytest

from pipeline_helpers import load_config
from slotformer_jax.datasets import clevrer_like
from slotformer_jax.datasets import synthetic_contact as contact
from slotformer_jax.datasets import synthetic_phyre as phyre_like
from slotformer_jax.datasets import synthetic

EXPECTED = {
    'synthetic:': 'synthetic_obj3d/r32x32_t24_o2-3_s0_n1000-50-100_aa2_862a7904/2.0.0',
    'synthetic:tiny': 'synthetic_obj3d/r32x32_t12_o2-3_s0_n24-8-8_aa2_c145f7fe/2.0.0',
    'synthetic:steve': 'synthetic_obj3d/r64x64_t24_o2-3_s0_n500-50-100_aa2_26dcd35b/2.0.0',
    'synthetic:steve_tiny': 'synthetic_obj3d/r32x32_t8_o2-3_s0_n8-4-4_aa2_8a22adeb/2.0.0',
    'synthetic_contact:': 'synthetic_contact/r32x32_t24_obs8_d1-2_s0_n1000-400-100-200_bd3d97a8/2.0.0',
    'synthetic_contact:tiny': 'synthetic_contact/r32x32_t24_obs8_d1-2_s0_n16-16-8-8_1ac36642/2.0.0',
    'synthetic_contact:side': 'synthetic_contact/r32x32_t24_obs8_d1-2_s1_n1000-400-100-200_9ba7bed3/2.0.0',
    'synthetic_contact:bank': 'synthetic_contact/r32x32_t24_obs8_d1-2_s2_n1000-400-100-200_ae46dbf9/2.0.0',
    'synthetic_phyre:': 'synthetic_phyre/r32x32_f2_t5_k1_3x25_c200_fold0_s0_35de6daa_v600-0_p0.2/2.0.0',
    'synthetic_phyre::labels': 'synthetic_phyre/r32x32_f2_t5_k1_3x25_c200_fold0_s0_35de6daa/labels.npz',
    'synthetic_phyre:tiny': 'synthetic_phyre/r32x32_f2_t5_k1_3x5_c30_fold0_s0_235dab60_v16-0_p0.2/2.0.0',
    'synthetic_phyre:tiny:labels': 'synthetic_phyre/r32x32_f2_t5_k1_3x5_c30_fold0_s0_235dab60/labels.npz',
    'synthetic_phyre:ramp': 'synthetic_phyre/r32x32_f2_t5_k1_1x100_c200_fold0_s0_e5c829b6_v2400-0_p0.2/2.0.0',
    'synthetic_phyre:ramp:labels': 'synthetic_phyre/r32x32_f2_t5_k1_1x100_c200_fold0_s0_e5c829b6/labels.npz',
    'synthetic_phyre:ramp_layouts': 'synthetic_phyre/r32x32_f2_t5_k1_1x100_c200_fold0_s0_e5c829b6_v2400-0_p0.2_l300/2.0.0',
    'synthetic_phyre:ramp_layouts:labels': 'synthetic_phyre/r32x32_f2_t5_k1_1x100_c200_fold0_s0_e5c829b6/labels.npz',
    'synthetic_vqa:': 'clevrer_like/r32x32_t24+16_o2-4+1_s0_3af381d0',
    'synthetic_vqa:tiny': 'clevrer_like/r32x32_t12+8_o2-4+1_s0_78196cf0',
    'synthetic_vqa:long_savi': 'clevrer_like/r32x32_t24+16_o2-4+1_s0_3af381d0',
    'synthetic_vqa:big': 'clevrer_like/r32x32_t24+16_o2-4+1_s0_3a199181',
    'synthetic_vqa:deflect': 'clevrer_like/r32x32_t24+16_o2-4+1_s0_544895a5',
    # Not shipped: a later fold of the tiny config (the fold is in the slug).
    'synthetic_phyre:tiny:fold1': 'synthetic_phyre/r32x32_f2_t5_k1_3x5_c30_fold1_s0_96805d9b_v16-0_p0.2/2.0.0',
    'synthetic_phyre:tiny:fold1:labels': 'synthetic_phyre/r32x32_f2_t5_k1_3x5_c30_fold1_s0_96805d9b/labels.npz',
}


def _folders(key: str) -> dict[str, str]:
  """{key: folder relative to the data dir} of one config variant."""
  name, variant = key.split(':')[:2]
  data = load_config(name, variant).data
  if key.endswith(':fold1'):
    data.fold = 1
  if data.name == 'synthetic':
    return {key: synthetic.dataset_dir(
        synthetic.config_from_data_config(data), '.')}
  if data.name == 'synthetic_contact':
    return {key: contact.dataset_dir(
        contact.config_from_data_config(data), '.')}
  if data.name == 'synthetic_phyre':
    return {key: phyre_like.video_dataset_dir(data, '.'),
            f'{key}:labels': phyre_like.labels_path(
                phyre_like.config_from_data_config(data), '.')}
  return {key: clevrer_like.dataset_dir(
      clevrer_like.config_from_data_config(data), '.')}


@pytest.mark.parametrize('key', [k for k in EXPECTED
                                 if not k.endswith(':labels')])
def test_the_folders_of_the_shipped_configs_are_unchanged(key):
  for name, folder in _folders(key).items():
    assert str(folder) == EXPECTED[name], name
