"""configs/movi.py against SAVi's MOVi configs: each variant resolves and
passes the checks of its whole run, and its fields hold the values of
google-research/slot-attention-video's `savi/configs/movi/*.py` (the table
below, read from those files at ba8f15e; the field each comes from is
configs/movi.py's SAVI_FIELDS)."""

import importlib.util
import os

import pytest

from slotformer_jax import slot_models
from slotformer_jax.config import checks as config_checks

ROOT = os.path.join(os.path.dirname(__file__), '..', '..')
MOVI = os.path.join(ROOT, 'configs', 'movi.py')


def _module():
  spec = importlib.util.spec_from_file_location('movi_config', MOVI)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


# Values every SAVi MOVi config shares (savi_conditional_small.py).
COMMON = {
    'savi.batch_size': 64,                        # batch_size
    'savi.learning_rate': 2e-4,                   # learning_rate
    'savi.grad_clip': 0.05,                       # max_grad_norm
    'savi.clip_length': 6,                        # temporal_random_strided_window(length=6)
    'evaluation.chunk_length': 6,                 # eval_slice_size
    'savi.initial_slots': 'boxes',                # conditioning_key, center_of_mass=False
    'savi.slot_size': 128,                        # initializer.embedding_transform.output_size
    'savi.encoder.mlp_size': 64,                  # pos_emb.output_transform.hidden_size
    'savi.slot_attention.num_iterations': 1,      # corrector.num_iterations
    'savi.slot_attention.mlp_size': None,         # corrector: no mlp_size, no MLP
    'savi.predictor.kind': 'transformer',         # predictor: TransformerBlock
    'savi.predictor.num_layers': 1,
    'savi.predictor.num_heads': 4,                # predictor.num_heads
    'savi.predictor.pre_norm': False,             # TransformerBlock's default
    'savi.decoder.broadcast_resolution': (8, 8),  # decoder.resolution
    'savi.decoder.features': (64, 64, 64, 64),    # decoder.backbone.features
    'savi.decoder.kernel_size': 5,                # decoder.backbone.kernel_size
}
# What each file sets besides (warm-up: warmup_steps=2500 of num_train_steps).
SAVI = {
    'savis': {  # savi_conditional_small.py
        'data.name': 'movi_a', 'data.resolution': (64, 64),
        'savi.targets': ('flow',), 'savi.num_train_steps': 100_000,
        'savi.warmup_fraction': 2_500 / 100_000,
        'savi.encoder.kind': 'cnn', 'savi.encoder.features': (32,) * 4,
        'savi.encoder.kernel_size': 5, 'savi.encoder.strides': (1, 1, 1, 1),
        'savi.encoder.output_size': 32,
        'savi.encoder.transformer.num_layers': 0,
        'savi.slot_attention.qkv_size': 128, 'savi.predictor.qkv_size': 128,
        'savi.predictor.mlp_size': 256,
        'savi.random_resized_crop.enabled': False},
    'savim': {  # savi_conditional_medium.py
        'data.name': 'movi_a', 'data.resolution': (128, 128),
        'savi.targets': ('flow',), 'savi.num_train_steps': 100_000,
        'savi.warmup_fraction': 2_500 / 100_000,
        'savi.encoder.kind': 'cnn', 'savi.encoder.features': (64,) * 4,
        'savi.encoder.kernel_size': 5, 'savi.encoder.strides': (2, 1, 1, 1),
        'savi.encoder.output_size': 64,
        'savi.encoder.transformer.num_layers': 0,
        'savi.slot_attention.qkv_size': 128, 'savi.predictor.qkv_size': 128,
        'savi.predictor.mlp_size': 256,
        'savi.random_resized_crop.enabled': False},
    'savil': {  # savi_conditional_large.py
        'data.name': 'movi_a', 'data.resolution': (128, 128),
        'savi.targets': ('flow',), 'savi.num_train_steps': 500_000,
        'savi.warmup_fraction': 2_500 / 500_000,
        'savi.encoder.kind': 'resnet34', 'savi.encoder.output_size': 512,
        'savi.encoder.transformer.num_layers': 0,
        'savi.slot_attention.qkv_size': 128, 'savi.predictor.qkv_size': 128,
        'savi.predictor.mlp_size': 256,
        'savi.random_resized_crop.enabled': False},
    'savipp': {  # savi++_conditional.py
        'data.name': 'movi_e', 'data.resolution': (128, 128),
        'savi.targets': ('flow', 'depth'), 'savi.num_train_steps': 500_000,
        'savi.warmup_fraction': 2_500 / 500_000,
        'savi.encoder.kind': 'resnet34', 'savi.encoder.output_size': 512,
        'savi.encoder.transformer.num_layers': 4,
        'savi.encoder.transformer.num_heads': 4,
        'savi.encoder.transformer.qkv_size': 64,
        'savi.encoder.transformer.mlp_size': 1024,
        'savi.slot_attention.qkv_size': 256, 'savi.predictor.qkv_size': 256,
        'savi.predictor.mlp_size': 1024,
        'savi.random_resized_crop.enabled': True,
        'savi.random_resized_crop.min_object_covered': 0.75},
}
# MOVi-E's max_instances 23 (+ 1 background slot); A's 10, SAVi's note.
SLOTS = {'savis': 11, 'savim': 11, 'savil': 11, 'savipp': 24}


def _get(config, field):
  value = config
  for key in field.split('.'):
    value = value[key]
  return tuple(value) if isinstance(value, (list, tuple)) else value


@pytest.mark.parametrize('model', sorted(SAVI))
def test_each_model_holds_savis_values(model):
  config = _module().get_config(model)
  expected = {**COMMON, **SAVI[model], 'savi.num_slots': SLOTS[model]}
  wrong = {field: (_get(config, field), value)
           for field, value in expected.items()
           if _get(config, field) != value}
  assert not wrong, wrong


def test_every_value_from_savi_names_its_field():
  """The docstring's promise: each field the table checks has SAVi's
  field named in SAVI_FIELDS (and only fields the config has)."""
  module = _module()
  checked = set(COMMON) | {f for values in SAVI.values() for f in values}
  checked -= {'data.name', 'savi.predictor.kind', 'savi.predictor.num_layers'}
  assert checked <= set(module.SAVI_FIELDS), checked - set(module.SAVI_FIELDS)
  config = module.get_config('savipp')
  for field in module.SAVI_FIELDS:
    _get(config, field)  # exists


def test_words_combine_and_the_old_names_still_resolve():
  module = _module()
  assert module.get_config('savim_c').data.name == 'movi_c'
  assert module.get_config('savim_c').data.resolution == (128, 128)
  assert module.get_config('savipp_a').data.max_instances == 10
  for letter, slots in (('a', 11), ('d', 24)):
    config = module.get_config(letter)
    assert config.savi.targets == ('rgb',)  # SlotFormer's target
    assert config.savi.initial_slots == 'boxes'
    assert config.savi.num_slots == slots
    assert 'psnr' in config.evaluation.metrics
  assert module.get_config('a_uncond').savi.initial_slots == 'learned'
  assert module.get_config('savipp_uncond').savi.initial_slots == 'learned'
  # Without RGB targets the frame metrics are not asked for.
  assert 'psnr' not in module.get_config('savis').evaluation.metrics
  for bad in ('f', 'savis_savim', 'a_b', 'savix', 'a_conditional'):
    with pytest.raises(ValueError, match='unknown MOVi variant'):
      module.get_config(bad)


@pytest.mark.parametrize('variant', _module().VARIANTS)
def test_every_variant_passes_the_checks_of_its_whole_run(variant):
  from slotformer_jax import stages  # pylint: disable=g-import-not-at-top
  from slotformer_jax.run import Run  # pylint: disable=g-import-not-at-top
  config = config_checks.load_config_file(f'{MOVI}:{variant}')
  assert config_checks.check_field_kinds(config) == []
  assert config_checks.check_field_shapes(config) == []
  assert slot_models.get(config).check_config(frozenset()) == []
  run = Run.create(config, '/nonexistent/run')
  stages.check(run, stages.selected_stages(run, 'all'), num_devices=1,
               num_processes=1)
