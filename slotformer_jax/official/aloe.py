"""The authors' Aloe for CLEVRER VQA -> this project's `Aloe` (config.vqa).

The official `CLEVRERAloe` (pairlab/SlotFormer, slotformer/clevrer_vqa/
models/; configs `aloe_clevrer_params-rollout.py` / `aloe_clevrer_params.py`
differ only in the slots they read) has state-dict keys
`transformer_model.<name>`; its token layout, flags, padding mask and heads
are the same as here. What the weights cannot tell is required of the
config: one learned position per token (`vqa.positions='token'`) and
PyTorch's LayerNorm epsilon (`vqa.layer_norm_epsilon=1e-5`), both set by
configs/clevrer_vqa.py. The key mapping and the part-by-part comparison:
docs/official_weights.md, "Aloe".
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax.data import vqa_questions
from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.errors import ConfigError
from slotformer_jax.errors import MissingInputError
from slotformer_jax.modules import aloe as aloe_module
from slotformer_jax.official import layers
from slotformer_jax.official.common import PYTORCH_LN_EPSILON
from slotformer_jax.official.common import ConversionError
from slotformer_jax.official.common import Converted
from slotformer_jax.official.common import assemble
from slotformer_jax.official.common import require
from slotformer_jax.official.layers import StateDictMapper
from slotformer_jax.tasks import vqa as vqa_task

# The pipeline stage a converted Aloe belongs to (vqa/<inputs>_s<seed>/).
ALOE_STAGE = 'vqa'
PREFIX = 'transformer_model.'

# Official fixed flag -> the constant modules/aloe.py concatenates instead.
FLAGS = {
    'text_token': aloe_module.TEXT_FLAG,
    'vision_token': aloe_module.VISION_FLAG,
    'cls_token': aloe_module.OPEN_QUESTION_FLAG,
    'mc_question_token': aloe_module.MC_QUESTION_FLAG,
    'mc_choice_token': aloe_module.MC_CHOICE_FLAG,
}


def is_aloe(keys: set[str]) -> bool:
  """CLEVRERAloe: the Transformer model's two answer heads."""
  return any(k.startswith((f'{PREFIX}cls_answer_mlp.',
                           f'{PREFIX}mc_answer_mlp.')) for k in keys)


def vocabulary(config: ml_collections.ConfigDict) -> vqa_data.Vocabulary:
  """The vocabulary the pipeline will use (data/vqa_questions.py): its sizes
  are the embedding's and the open head's.

  Raises:
    ConversionError: none is configured (names `vqa.vocab_file`).
  """
  try:
    return vqa_questions.vocabulary(config)
  except (ConfigError, MissingInputError) as error:  # none configured
    if config.data.name == 'clevrer_like':
      raise  # its vocabulary comes with the data: the error says how
    raise ConversionError(
        'an official Aloe\'s word and answer ids are those of the vocabulary '
        'it was trained with: set --config.vqa.vocab_file to the official '
        'clevrer_vqa/datasets/cache/CLEVRER_vocab.json (or '
        'vqa.questions_root, CLEVRER\'s questions folder, to build the same '
        'one from its training questions)') from error


def model_fields(config: ml_collections.ConfigDict,
                 vocab: vqa_data.Vocabulary) -> dict[str, Any]:
  """The config values that shape Aloe's parameters (model_config.json)."""
  vqa = config.vqa
  fields = {key: vqa[key] for key in (
      'num_frames', 'max_question_len', 'max_choice_len', 'word_dim',
      'd_model', 'num_layers', 'num_heads', 'mlp_size', 'head_size',
      'positions')}
  fields.update(layer_norm_epsilon=vqa.layer_norm_epsilon,
                vocab_size=len(vocab.questions),
                num_answers=len(vocab.answers),
                num_slots=config.savi.num_slots,
                slot_size=config.savi.slot_size)
  return fields


def aloe_abstract_params(config: ml_collections.ConfigDict,
                         vocab: vqa_data.Vocabulary) -> Any:
  """Shapes of the Aloe the VQA stage builds (stages.vqa.model_and_init)."""
  vqa = config.vqa
  model = vqa_task.build_aloe(vqa, len(vocab.questions), len(vocab.answers),
                              num_slots=config.savi.num_slots)
  length = vqa.max_question_len + vqa.max_choice_len
  slots = jnp.zeros((1, vqa.num_frames, config.savi.num_slots,
                     config.savi.slot_size))
  tokens = jnp.zeros((1, length), jnp.int32)
  pad = jnp.zeros((1, length), bool)
  return jax.eval_shape(lambda: model.init(
      jax.random.key(0), slots, tokens, pad, slots, tokens[:, None],
      pad[:, None]))['params']


def _check_flags(m: StateDictMapper) -> None:
  for name, expected in FLAGS.items():
    value = m.take(f'{PREFIX}{name}')
    if value is not None and not np.array_equal(value, expected):
      raise ConversionError(
          f'{PREFIX}{name} is {value.tolist()}, the fixed flag of the '
          f'official model (and of modules/aloe.py) is {list(expected)}: '
          'this checkpoint is not the official Aloe')


def convert_aloe(state_dict: dict[str, np.ndarray],
                 config: ml_collections.ConfigDict) -> Converted:
  """Official CLEVRERAloe -> {'params': ...} of `Aloe` (the variables the
  VQA stage's TrainState holds)."""
  if 'vqa' not in config:
    raise ConversionError(
        'an official Aloe checkpoint needs a config with a vqa section: use '
        '--config=configs/clevrer_vqa.py')
  require(config, 'vqa.positions', aloe_module.TOKEN,
          'learns one position per token (pos_enc=learnable)')
  require(config, 'vqa.layer_norm_epsilon', PYTORCH_LN_EPSILON,
          "uses PyTorch's LayerNorm epsilon")
  vqa = config.vqa
  vocab = vocabulary(config)
  m = StateDictMapper(state_dict)
  p = PREFIX
  sizes = 'config.vqa (d_model / word_dim)'
  layers.embedding(m, f'{p}q_embedding', 'word_embedding',
                   'config.vqa.vocab_file (question words) / word_dim')
  layers.linear(m, f'{p}q_in_proj', 'text_projection', sizes)
  layers.linear(m, f'{p}vision_in_proj', 'slot_projection',
                'config.savi.slot_size / config.vqa.d_model')
  cls = m.take(f'{p}CLS')  # [1, 1, d_model]
  if cls is not None:
    m.put('cls', cls.reshape(cls.shape[-1:]), f'{p}CLS', cls.shape, sizes)
  position = m.take(f'{p}transformer_encoder.pos_embedding')  # [1, L, D]
  if position is not None:
    m.put('position', position[0], f'{p}transformer_encoder.pos_embedding',
          position.shape,
          'config.vqa (num_frames / max_question_len / max_choice_len / '
          'd_model) / config.savi.num_slots (1 + T*N + L positions)')
  field = 'config.vqa (d_model / num_layers / num_heads / mlp_size)'
  for i in range(vqa.num_layers):
    layers.transformer_encoder_layer(
        m, f'{p}transformer_encoder.layers.{i}', f'encoder/block_{i}', field,
        num_heads=vqa.num_heads)
  heads = 'config.vqa.head_size / d_model'
  layers.linear(m, f'{p}cls_answer_mlp.0', 'open_head/layers_0', heads)
  layers.linear(m, f'{p}cls_answer_mlp.2', 'open_head/layers_2',
                'config.vqa.head_size / vocab_file (answers)')
  layers.linear(m, f'{p}mc_answer_mlp.0', 'choice_head/layers_0', heads)
  layers.linear(m, f'{p}mc_answer_mlp.2', 'choice_head/layers_2', heads)
  _check_flags(m)
  params = assemble(m, aloe_abstract_params(config, vocab), hints={
      f'{p}transformer_encoder.layers.': 'config.vqa.num_layers',
      f'{p}transformer_encoder.norm': 'a final LayerNorm (norm_last=True): '
                                      'not part of the official Aloe',
      f'{p}transformer_encoder.pos_embedding':
          "config.vqa.positions='token' (pos_enc='learnable')",
      f'{p}mask_': 'the masked-object loss (use_mask_obj_loss), which the '
                   'official code refuses on slots: not implemented',
  })
  return Converted('aloe', ALOE_STAGE, {'params': params})
