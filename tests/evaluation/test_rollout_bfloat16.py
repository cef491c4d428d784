"""The rollout evaluation with config.compute_dtype='bfloat16'.

It failed to trace before (the decoder's bound float32 parameters met
bfloat16 slots in the accelerator kernel form, which `lax.platform_dependent`
traces on CPU too); now every convolution of the decode computes in
bfloat16 and the metrics stay close to float32's.
"""

import jax
import numpy as np
import pytest

from slotformer_jax import dynamics as dynamics_lib
from slotformer_jax import slot_models
from slotformer_jax.evaluation import evaluate
from slotformer_jax.runtime import sharding
from slotformer_jax.stages import dynamics
from slotformer_jax.stages import stage1
from tests.pipeline_helpers import load_config

SLOTFORMER = 'slotformer'  # the dynamics model's registered name


def _inputs(config):
  """Random SAVi and SlotFormer parameters and one evaluation batch."""
  slot_model = slot_models.get(config)
  mesh = sharding.make_mesh()
  part = slot_model.part('savi')
  slot_params = {'savi': stage1.part_stage(
      part, '/unused', mesh, None, seed=0).init_params(jax.random.key(0))}
  dyn_stage = dynamics.dynamics_stage(
      config.slotformer, SLOTFORMER, '/unused', mesh, slot_model,
      slot_params, None, seed=1, compute_dtype=config.compute_dtype)
  dynamics_params = {SLOTFORMER: dyn_stage.init_params(jax.random.key(1))}
  rng = np.random.default_rng(0)
  length = config.slotformer.burn_in + config.evaluation.rollout_steps
  num_slots, slot_size = slot_model.slot_shape
  height, width = config.data.resolution
  batch = {'slots': rng.normal(size=(4, length, num_slots, slot_size)
                               ).astype(np.float32),
           'video': rng.integers(0, 256, (4, length, height, width, 3),
                                 np.uint8)}
  return mesh, slot_model, dynamics_params, slot_params, batch


@pytest.mark.slow  # 10 s; the bfloat16 step: train/test_precision.py
def test_bfloat16_rollout_evaluation_decodes_in_bfloat16():
  results, jaxprs = {}, {}
  for dtype in ('float32', 'bfloat16'):
    config = load_config('synthetic', 'tiny')
    config.compute_dtype = dtype
    mesh, slot_model, dynamics_params, slot_params, batch = _inputs(config)
    run = evaluate.make_rollout_evaluator(
        config.evaluation, mesh, ('psnr',),
        {SLOTFORMER: dynamics_lib.build(config.slotformer, SLOTFORMER)},
        slot_model, burn_in=config.slotformer.burn_in,
        num_true=config.data.max_instances + 1,
        compute_dtype=config.compute_dtype)
    jaxprs[dtype] = str(jax.make_jaxpr(run)(dynamics_params, slot_params,
                                            batch, None))
    results[dtype] = jax.tree.map(np.asarray, run(dynamics_params,
                                                  slot_params, batch, None))
  def conv_dtypes(jaxpr):
    """The result dtype of every convolution in a jaxpr's text."""
    return [line.split('=')[0].split(':')[1].split('[')[0]
            for line in jaxpr.splitlines() if '= conv_general_dilated[' in line]
  # Both kernel forms are traced (platform_dependent): all in bfloat16.
  assert conv_dtypes(jaxprs['bfloat16'])
  assert set(conv_dtypes(jaxprs['bfloat16'])) == {'bf16'}
  assert set(conv_dtypes(jaxprs['float32'])) == {'f32'}
  for method in results['float32']:
    low = results['bfloat16'][method]['psnr'][0]
    high = results['float32'][method]['psnr'][0]
    assert low.dtype == np.float32
    np.testing.assert_allclose(low, high, atol=0.5, err_msg=method)
