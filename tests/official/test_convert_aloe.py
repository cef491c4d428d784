"""The official Aloe and readout converters against an independent NumPy
implementation of the official modules (tests/official_aloe_reference.py).

Official-format state dicts (official key names and shapes, random values)
are converted; each mapped layer kind (the embedding, the Transformer layer
with a key-padding mask, the heads) is checked on its own, then the whole
converted Aloe answers a hand-made batch of CLEVRER-format questions (through
the pipeline's question encoding and batching) as the NumPy reference does,
and the readouts give its logits; then the errors and the workdir the
converter writes (read back by the VQA and readout stages).
"""

import json
import os

from flax import serialization
import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

import dataset_fixtures as fx
import official_aloe_reference as aref
import official_reference as ref
from configs import physion_contact
from slotformer_jax.official import convert as convert_official
from slotformer_jax.data import vqa_questions
from slotformer_jax.data import prepare
from slotformer_jax.stages import vqa as vqa_stages
from slotformer_jax.data import vqa as vqa_data
from slotformer_jax.config.defaults import base_config
from slotformer_jax.config.defaults import vqa_config
from slotformer_jax.errors import ConfigError
from slotformer_jax.modules.transformer import TransformerBlock
from slotformer_jax.official import common
from slotformer_jax.official import families
from slotformer_jax.official import layers
from slotformer_jax.official.layers import StateDictMapper
from slotformer_jax.stages import contact as contact_stages
from slotformer_jax.tasks import contact
from slotformer_jax.tasks import phyre_planning
from slotformer_jax.tasks import vqa as vqa_task
from slotformer_jax.train.trainer import checkpointer_for
from slotformer_jax.workdir.paths import Paths
from slotformer_jax.workdir import identity as identity_lib
from pipeline_helpers import run_stage
from slotformer_jax.run import Run

TOLERANCE = 1e-4  # float32 modules vs the float64 reference


def _close(actual, expected, tolerance=TOLERANCE):
  actual = np.asarray(actual, np.float64)
  assert actual.shape == expected.shape, (actual.shape, expected.shape)
  worst = np.max(np.abs(actual - expected))
  assert worst < tolerance, worst


def _params(m: StateDictMapper, prefix: str):
  return common.unflatten({
      path[len(prefix) + 1:]: assigned.value
      for path, assigned in m.params.items() if path.startswith(prefix + '/')})


# --------------------------------------------------------------------------
# The layer kinds these families add
# --------------------------------------------------------------------------


def test_embedding():
  r = ref._Random(0)  # pylint: disable=protected-access
  sd = {'emb.weight': r.rng.standard_normal((9, 4))}
  m = StateDictMapper(sd)
  layers.embedding(m, 'emb', 'layer', 'field')
  ids = np.array([[0, 3, 8, 3]])
  out = nn.Embed(9, 4).apply({'params': _params(m, 'layer')}, ids)
  _close(out, sd['emb.weight'][ids])


def test_transformer_layer_with_key_padding_mask():
  """nn.TransformerEncoderLayer's src_key_padding_mask == the key mask Aloe
  builds (nn.make_attention_mask over the kept tokens)."""
  r = ref._Random(1)  # pylint: disable=protected-access
  sd = {}
  ref.add_transformer_layer(sd, r, 'layer', 12, 20)
  m = StateDictMapper(sd)
  layers.transformer_encoder_layer(m, 'layer', 'block', 'field', num_heads=3)
  x = r.rng.standard_normal((2, 7, 12))
  pad = np.zeros((2, 7), bool)
  pad[0, 5:] = pad[1, 2:4] = True
  mask = nn.make_attention_mask(np.ones((2, 7), bool), ~pad)
  out = TransformerBlock(num_heads=3, mlp_size=20, layer_norm_epsilon=1e-5
                         ).apply({'params': _params(m, 'block')}, x, mask)
  expected = aref.masked_transformer_layer(x, sd, 'layer', 3, pad)
  _close(out, expected)
  # The padded keys matter: without the mask the outputs differ.
  unmasked = TransformerBlock(num_heads=3, mlp_size=20,
                              layer_norm_epsilon=1e-5).apply(
                                  {'params': _params(m, 'block')}, x)
  assert np.max(np.abs(np.asarray(unmasked) - expected)) > 1e-2


# --------------------------------------------------------------------------
# Aloe
# --------------------------------------------------------------------------

# A hand-made CLEVRER-format question file (one scene).
SCENES = [{
    'scene_index': 10000, 'video_filename': 'video_10000.mp4',
    'questions': [
        {'question_id': 0, 'question_type': 'descriptive',
         'question': 'What is the color of the cube?', 'answer': 'red'},
        {'question_id': 1, 'question_type': 'descriptive',
         'question': 'How many spheres are moving?', 'answer': '2'},
        {'question_id': 2, 'question_type': 'descriptive',
         'question': 'Are there any collisions?', 'answer': 'yes'},
        {'question_id': 3, 'question_type': 'predictive',
         'question': 'What will happen next?',
         'choices': [
             {'choice_id': 0, 'choice': 'The cube collides with the sphere',
              'answer': 'correct'},
             {'choice_id': 1, 'choice': 'The sphere exits',
              'answer': 'wrong'}]},
        {'question_id': 4, 'question_type': 'explanatory',
         'question': 'Which of the following is responsible for the '
                     'collision?',
         'choices': [
             {'choice_id': 0, 'choice': 'The red cube', 'answer': 'wrong'},
             {'choice_id': 1, 'choice': 'The presence of the sphere',
              'answer': 'correct'},
             {'choice_id': 2, 'choice': 'The cube entering',
              'answer': 'wrong'}]},
    ]}]
ANSWERS = ('0', '1', '2', 'red', 'yes', 'no')


def write_vocabulary(path) -> vqa_data.Vocabulary:
  """The vocabulary of SCENES in the official CLEVRER_vocab.json format:
  one line, {"q_vocab": {word: id}, "a_vocab": {answer: id}}, PAD = 0."""
  vocab = vqa_data.Vocabulary.from_scenes(SCENES, answers=ANSWERS)
  with open(path, 'w') as f:
    f.write(json.dumps({'q_vocab': vocab.questions, 'a_vocab': vocab.answers}))
  return vocab


def aloe_config(vocab_file) -> ml_collections.ConfigDict:
  """A tiny config.vqa with the official relations: d_model = (word_dim + 2
  + 2) * num_heads, PyTorch's LayerNorm epsilon, learned token positions."""
  config = base_config()
  config.savi.num_slots, config.savi.slot_size = 3, 8
  config.task = 'vqa'
  config.vqa = vqa = vqa_config()
  vqa.num_frames, vqa.video_length, vqa.frame_stride = 2, 4, 2
  vqa.rollout_frames = 2
  vqa.max_question_len, vqa.max_choice_len, vqa.max_choices = 10, 6, 3
  vqa.word_dim, vqa.num_heads = 2, 2
  vqa.d_model = (vqa.word_dim + 4) * vqa.num_heads
  vqa.num_layers, vqa.mlp_size, vqa.head_size = 2, 16, 8
  vqa.layer_norm_epsilon = 1e-5
  vqa.num_train_steps = 7
  vqa.vocab_file = str(vocab_file)
  return config


def official_aloe(config, vocab, seed=0):
  vqa = config.vqa
  return aref.aloe_state_dict(
      seed, vocab_size=len(vocab.questions), num_answers=len(vocab.answers),
      input_dim=vqa.word_dim + 2, num_heads=vqa.num_heads,
      slot_size=config.savi.slot_size,
      input_len=(vqa.num_frames * config.savi.num_slots
                 + vqa.max_question_len + vqa.max_choice_len),
      num_layers=vqa.num_layers, ffn_dim=vqa.mlp_size,
      cls_mlp_size=vqa.head_size)


@pytest.fixture
def aloe_setup(tmp_path):
  vocab = write_vocabulary(tmp_path / 'CLEVRER_vocab.json')
  config = aloe_config(tmp_path / 'CLEVRER_vocab.json')
  return config, vocab, official_aloe(config, vocab)


def test_official_vocabulary_file_loads(tmp_path):
  vocab = write_vocabulary(tmp_path / 'vocab.json')
  assert vqa_data.Vocabulary.load(tmp_path / 'vocab.json') == vocab
  config = aloe_config(tmp_path / 'vocab.json')
  # vqa.vocab_file is read without any questions folder.
  assert vqa_questions.vocabulary(config) == vocab
  for broken in ({'q_vocab': vocab.questions},
                 {'q_vocab': {'PAD': 1, 'a': 0}, 'a_vocab': vocab.answers},
                 {'q_vocab': {'PAD': 0, 'a': 2}, 'a_vocab': vocab.answers}):
    with open(tmp_path / 'broken.json', 'w') as f:
      json.dump(broken, f)
    with pytest.raises(ConfigError, match='broken.json'):
      vqa_data.Vocabulary.load(tmp_path / 'broken.json')


def test_aloe_answers_a_question_batch_as_the_official_model(aloe_setup):
  """Hand-made questions -> the pipeline's encoding and batches -> the
  converted Aloe's open answers and choice logits == the NumPy reference's
  on the same tokens and slots."""
  config, vocab, state = aloe_setup
  vqa = config.vqa
  converted = families.convert_state_dict(state, config)
  assert (converted.family, converted.stage) == ('aloe', 'vqa')
  questions = vqa_data.encode_scenes(SCENES, vocab, vqa.max_question_len,
                                     vqa.max_choice_len)
  rng = np.random.default_rng(3)
  slots = rng.standard_normal((vqa.video_length + vqa.rollout_frames,
                               config.savi.num_slots, config.savi.slot_size))
  batches = vqa_task.QuestionBatches(
      questions, lambda name: slots, video_length=vqa.video_length,
      num_frames=vqa.num_frames, stride=vqa.frame_stride,
      max_choices=vqa.max_choices)
  batch, open_ids, choice_ids = next(batches.eval_batches(4, 3))
  assert (len(open_ids), len(choice_ids)) == (3, 2)
  model = vqa_task.build_aloe(config.vqa, len(vocab.questions), len(vocab.answers),
                            num_slots=config.savi.num_slots)
  answers, choice_logits = jax.jit(
      lambda p, b: vqa_task.predict(p, b, model=model))(
          converted.params, jax.tree.map(jnp.asarray, batch))
  kwargs = dict(num_heads=vqa.num_heads, num_layers=vqa.num_layers)
  open_logits = aref.aloe_open_logits(
      batch['open_slots'], batch['open_tokens'], batch['open_pad'], state,
      **kwargs)
  np.testing.assert_array_equal(np.asarray(answers), open_logits.argmax(-1))
  _close(model.apply(converted.params, jnp.asarray(batch['open_slots']),
                     jnp.asarray(batch['open_tokens']),
                     jnp.asarray(batch['open_pad']), method='open_logits'),
         open_logits)
  # Multiple choice: one row per (question, choice), as official mc_flag.
  n_q, n_c = batch['choice_tokens'].shape[:2]
  rows = np.repeat(batch['choice_slots'], n_c, axis=0)
  expected = aref.aloe_choice_logits(
      rows, batch['choice_tokens'].reshape(n_q * n_c, -1),
      batch['choice_pad'].reshape(n_q * n_c, -1), state,
      question_len=vqa.max_question_len, **kwargs).reshape(n_q, n_c)
  valid = batch['choice_valid']
  _close(np.where(valid, choice_logits, 0), np.where(valid, expected, 0))
  np.testing.assert_array_equal(np.asarray(choice_logits)[valid] > 0,
                                expected[valid] > 0)
  # The question / choice flags matter: the choice rows are not read as
  # descriptive questions.
  as_open = aref.aloe_cls(rows, batch['choice_tokens'].reshape(n_q * n_c, -1),
                          batch['choice_pad'].reshape(n_q * n_c, -1), state,
                          **kwargs)
  as_choice = aref.aloe_cls(
      rows, batch['choice_tokens'].reshape(n_q * n_c, -1),
      batch['choice_pad'].reshape(n_q * n_c, -1), state,
      question_len=vqa.max_question_len, **kwargs)
  assert np.max(np.abs(as_open - as_choice)) > 1e-3


def test_aloe_config_must_be_the_official_one(aloe_setup):
  config, _, state = aloe_setup
  config.vqa.positions = 'frame'
  with pytest.raises(families.ConversionError, match='vqa.positions'):
    families.convert_state_dict(state, config)
  config.vqa.positions = 'token'
  config.vqa.layer_norm_epsilon = 1e-6
  with pytest.raises(families.ConversionError,
                     match='vqa.layer_norm_epsilon=1e-05'):
    families.convert_state_dict(state, config)
  config.vqa.layer_norm_epsilon = 1e-5
  config.vqa.vocab_file = None  # and no questions folder: no vocabulary
  with pytest.raises(families.ConversionError, match='vqa.vocab_file'):
    families.convert_state_dict(state, config)
  del config['vqa']
  with pytest.raises(families.ConversionError, match='clevrer_vqa.py'):
    families.convert_state_dict(state, config)


def test_aloe_missing_and_unknown_keys_in_one_error(aloe_setup):
  config, _, state = aloe_setup
  del state['transformer_model.mc_answer_mlp.2.bias']
  state['transformer_model.transformer_encoder.layers.2.linear1.weight'] = (
      np.zeros((16, 12)))
  state['transformer_model.mask_token'] = np.zeros((1, 8))
  with pytest.raises(families.ConversionError) as error:
    families.convert_state_dict(state, config)
  message = str(error.value)
  assert 'missing keys' in message and 'unknown keys' in message
  assert 'transformer_model.mc_answer_mlp.2.bias' in message
  assert ('transformer_model.transformer_encoder.layers.2.linear1.weight  '
          '(config.vqa.num_layers)') in message
  assert 'use_mask_obj_loss' in message


def test_aloe_shape_errors_name_key_and_field(aloe_setup, tmp_path):
  config, vocab, state = aloe_setup
  config.savi.num_slots = 4  # more slot tokens than the official positions
  with pytest.raises(families.ConversionError) as error:
    families.convert_state_dict(state, config)
  message = str(error.value)
  assert 'transformer_model.transformer_encoder.pos_embedding: checkpoint ' \
         'shape (1, 23, 12)' in message
  assert 'config.savi.num_slots' in message
  config.savi.num_slots = 3
  # Another vocabulary than the checkpoint's.
  bigger = vqa_data.Vocabulary(
      dict(vocab.questions, extra=len(vocab.questions)), vocab.answers)
  (tmp_path / 'other.json').write_text(bigger.to_json())
  config.vqa.vocab_file = str(tmp_path / 'other.json')
  with pytest.raises(families.ConversionError,
                     match=r'q_embedding.weight: checkpoint shape .* '
                     'config.vqa.vocab_file'):
    families.convert_state_dict(state, config)


def test_aloe_fixed_flags_are_checked(aloe_setup):
  config, _, state = aloe_setup
  state['transformer_model.mc_question_token'] = np.array([0.0, 1.0])
  with pytest.raises(families.ConversionError, match='mc_question_token'):
    families.convert_state_dict(state, config)


def test_aloe_writes_the_vqa_variant_the_config_selects(aloe_setup, tmp_path,
                                                        monkeypatch):
  config, vocab, state = aloe_setup
  config.vqa.inputs, config.vqa.seed = 'observed', 2
  workdir = str(tmp_path / 'run')
  [directory] = _convert_files(config, workdir, tmp_path, monkeypatch,
                               {'model_400.pth': state})
  assert directory == os.path.join(workdir, 'vqa', 'observed_s2')
  mesh = jax.sharding.Mesh(np.array(jax.devices()), ('data',))
  aloe = vqa_stages.load_aloe(Run.create(config, workdir, mesh))
  assert aloe.vocab == vocab and aloe.step == config.vqa.num_train_steps
  params = aloe.params
  expected = families.convert_state_dict(state, config).params
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(params),
               expected)
  checkpointer = checkpointer_for(directory, read_only=True)
  assert checkpointer.latest_step() == config.vqa.num_train_steps
  checkpointer.close()
  identity = identity_lib.read_identity(directory)
  assert identity['fields']['vqa']['num_layers'] == config.vqa.num_layers
  assert identity['parent'] is None  # no slot model in this workdir
  with open(os.path.join(directory, 'model_config.json')) as f:
    assert json.load(f)['vocab_size'] == len(vocab.questions)
  with open(os.path.join(directory, convert_official.CONVERTED_FROM_FILE)) as f:
    assert json.load(f)['family'] == 'aloe'
  with pytest.raises(FileExistsError):
    _convert_files(config, workdir, tmp_path, monkeypatch,
                   {'model_400.pth': state})


def test_converted_aloe_writes_the_evaluation_server_file(
    aloe_setup, tmp_path, monkeypatch):
  """A converted Aloe in a CLEVRER workdir: evaluate_vqa on a test split
  without answers writes CLEVRER's prediction file, whose answers are the
  NumPy reference's on the same slot frames (the middle window; predictive
  questions on the rollout)."""
  config, vocab, state = aloe_setup
  vqa = config.vqa
  second = dict(SCENES[0], scene_index=10001,
                video_filename='video_10001.mp4')
  scenes = [json.loads(json.dumps(scene)) for scene in (second, SCENES[0])]
  for scene in scenes:  # the test split has no answers
    for q in scene['questions']:
      q.pop('answer', None)
      for choice in q.get('choices', ()):
        choice.pop('answer')
  os.makedirs(tmp_path / 'CLEVRER' / 'questions')
  with open(tmp_path / 'CLEVRER' / 'questions' / 'test.json', 'w') as f:
    json.dump(scenes, f)
  # The converted test split the slots were extracted from: questions are
  # joined to its videos by name.
  for index in (10000, 10001):
    fx.write_clevrer_video(tmp_path / 'CLEVRER', 'test', index,
                           num_frames=4, size=8, annotated=False)
  assert prepare.main([
      '--dataset=clevrer', f'--source={tmp_path / "CLEVRER"}',
      f'--data_dir={tmp_path / "data"}', '--resolution=8', '--num_frames=4',
      '--splits=test', '--masks=ignore', '--num_workers=1',
      '--no_progress']) == 0
  config.data.name, config.data.channel_order = 'clevrer', 'bgr'
  config.data.data_dir, config.data.resolution = str(tmp_path / 'data'), (8, 8)
  config.vqa.questions_root = str(tmp_path / 'CLEVRER')
  config.vqa.eval_split = 'test'
  workdir = str(tmp_path / 'run')
  _convert_files(config, workdir, tmp_path, monkeypatch,
                 {'model_400.pth': state})
  # Slots of the two videos (file-name order), observed then rolled out.
  slots = np.random.default_rng(4).standard_normal(
      (2, vqa.video_length + vqa.rollout_frames, config.savi.num_slots,
       config.savi.slot_size)).astype(np.float32)
  os.makedirs(os.path.join(workdir, 'vqa', 'slots'))
  np.save(os.path.join(workdir, 'vqa', 'slots', 'test.npy'), slots)
  mesh = jax.sharding.Mesh(np.array(jax.devices()), ('data',))
  assert run_stage(config, workdir, mesh, 'evaluate_vqa') == {}
  with open(os.path.join(Paths.of(workdir).aloe(vqa.inputs, vqa.seed),
                         'predictions_test.json')) as f:
    predictions = json.load(f)
  assert [s['scene_index'] for s in predictions] == [10000, 10001]
  start = vqa_task.num_starts(vqa.video_length, vqa.num_frames,
                              vqa.frame_stride) // 2
  kwargs = dict(num_heads=vqa.num_heads, num_layers=vqa.num_layers)
  checked = 0
  for scene in scenes:
    video = slots[int(scene['video_filename'] == 'video_10001.mp4')]
    entries = {e['question_id']: e for s in predictions
               if s['scene_index'] == scene['scene_index']
               for e in s['questions']}
    for q in scene['questions']:
      encoded = vqa_data.encode_question(scene, q, vocab, vqa.max_question_len,
                                         vqa.max_choice_len)
      frames = vqa_task.question_frames(
          start, video_length=vqa.video_length, available=len(video),
          num_frames=vqa.num_frames, stride=vqa.frame_stride,
          predictive=q['question_type'] == 'predictive')
      rows = np.repeat(video[frames][None], len(encoded.tokens), axis=0)
      if encoded.is_descriptive:
        logits = aref.aloe_open_logits(rows, encoded.tokens, encoded.pad_mask,
                                       state, **kwargs)
        expected = vocab.answer_names[int(logits.argmax())]
        assert entries[q['question_id']]['answer'] == expected
      else:
        logits = aref.aloe_choice_logits(
            rows, encoded.tokens, encoded.pad_mask, state,
            question_len=vqa.max_question_len, **kwargs)
        assert entries[q['question_id']]['choices'] == [
            {'choice_id': int(c), 'answer': 'correct' if x > 0 else 'wrong'}
            for c, x in zip(encoded.choice_ids, logits)]
      checked += 1
  assert checked == 10


def test_aloe_after_savi_and_slotformer_in_one_command(tmp_path, monkeypatch):
  """SAVi, SlotFormer and Aloe in one command (Aloe listed first): written
  in pipeline order, Aloe's identity naming the SlotFormer whose rollouts
  its slots are."""
  import test_convert_official as tco  # pylint: disable=g-import-not-at-top
  config = tco.tiny_config()
  vocab = write_vocabulary(tmp_path / 'vocab.json')
  small = aloe_config(tmp_path / 'vocab.json')
  config.vqa = small.vqa
  savi_state = tco.official_savi(config)
  workdir = str(tmp_path / 'run')
  directories = _convert_files(config, workdir, tmp_path, monkeypatch, {
      'aloe.pth': official_aloe(config, vocab),
      'slotformer.pth': tco.official_slotformer(config, savi_state),
      'savi.pth': savi_state})
  assert directories == [Paths.of(workdir).model('savi'),
                         Paths.of(workdir).dynamics('slotformer'),
                         Paths.of(workdir).aloe(config.vqa.inputs,
                                                config.vqa.seed)]
  slotformer = identity_lib.read_identity(directories[1])
  assert identity_lib.read_identity(directories[2])['parent'] == {
      'slotformer_run_id': slotformer['run_id'],
      'slotformer_step': config.slotformer.num_train_steps}


def _convert_files(config, workdir, tmp_path, monkeypatch, states, **kwargs):
  """convert_official.convert_files on {file name: state dict}, the .pth
  reading replaced by the dicts (the reader has its own tests)."""
  files = {str(tmp_path / name): state for name, state in states.items()}
  for path in files:
    open(path, 'wb').close()
  monkeypatch.setattr(convert_official.pth_reader, 'read_state_dict',
                      lambda path, reader: files[path])
  return convert_official.convert_files(config, workdir, list(files),
                                        **kwargs)


# --------------------------------------------------------------------------
# The Physion readout
# --------------------------------------------------------------------------


def physion_config():
  config = physion_contact.get_config()
  config.steve.num_slots, config.steve.slot_size = 4, 6
  config.readout.conditions, config.readout.seeds = ('rollout',), (0,)
  return config


def official_physion_readout(config, seed=0):
  return aref.physion_readout_state_dict(
      seed, num_slots=config.steve.num_slots,
      slot_size=config.steve.slot_size, feats_dim=config.steve.slot_size)


def test_physion_readout_matches_numpy():
  config = physion_config()
  state = official_physion_readout(config)
  converted = families.convert_state_dict(state, config)
  assert converted.stage == 'readout'
  slots = np.random.default_rng(0).standard_normal((3, 5, 4, 6))
  out = contact.build_readout(config.readout, config.steve.slot_size).apply(
      {'params': converted.params}, slots)
  _close(out, aref.physion_readout_logits(slots, state))


def test_physion_readout_errors():
  config = physion_config()
  state = official_physion_readout(config)
  config.readout.pairs = 'both_orders'
  with pytest.raises(families.ConversionError, match='readout.pairs'):
    families.convert_state_dict(state, config)
  config.readout.pairs = 'unordered'
  config.steve.num_slots = 5
  with pytest.raises(families.ConversionError,
                     match='comb_idx .*config.steve.num_slots'):
    families.convert_state_dict(state, config)
  config.steve.num_slots = 4
  config.readout.features = 7
  with pytest.raises(families.ConversionError,
                     match=r'linear1.weight: checkpoint shape \(6, 12\).*'
                     'config.readout.features'):
    families.convert_state_dict(state, config)
  config.readout.features = None
  config.readout.seeds = (0, 1)
  with pytest.raises(families.ConversionError, match='readout.seeds'):
    families.convert_state_dict(state, config)
  config.readout.seeds = (0,)
  del state['linear2.bias']
  state['linear3.weight'] = np.zeros((1, 1))
  with pytest.raises(families.ConversionError,
                     match='(?s)missing keys.*linear2.bias.*unknown keys.*'
                     'linear3.weight'):
    families.convert_state_dict(state, config)
  with pytest.raises(families.ConversionError, match='physion_contact.py'):
    families.convert_state_dict(official_physion_readout(config),
                                aloe_config('unused'))


def test_physion_readout_is_evaluated_from_its_seed_folder(tmp_path,
                                                           monkeypatch):
  """The converted readout lands in readout/rollout/seed_0 with a
  selection.json naming its source; evaluate_readout applies it at the
  given threshold."""
  config = physion_config()
  config.readout.num_pictures = 0
  state = official_physion_readout(config)
  workdir = str(tmp_path / 'run')
  [directory] = _convert_files(config, workdir, tmp_path, monkeypatch,
                               {'readout.pth': state}, readout_threshold=0.6)
  assert directory == os.path.join(workdir, 'readout', 'rollout', 'seed_0')
  with open(os.path.join(directory, 'selection.json')) as f:
    selection = json.load(f)
  assert selection['converted'] is True
  assert selection['converted_from'] == str(tmp_path / 'readout.pth')
  assert selection['threshold'] == 0.6 and selection['val_accuracy'] is None
  assert identity_lib.read_identity(directory)['fields']['readout'][
      'pairs'] == 'unordered'
  rng = np.random.default_rng(1)
  slots = rng.standard_normal((20, 5, 4, 6)).astype(np.float32)
  labels = (rng.random(20) < 0.5).astype(np.float32)
  monkeypatch.setattr(contact_stages, '_features_by_condition',
                      lambda *args: ({'rollout': slots}, labels))
  mesh = jax.sharding.Mesh(np.array(jax.devices()), ('data',))
  results = run_stage(config, workdir, mesh, 'evaluate_readout')
  probabilities = 1 / (1 + np.exp(-aref.physion_readout_logits(slots, state)))
  accuracy = float(((probabilities > 0.6) == labels.astype(bool)).mean())
  assert results['rollout']['test_accuracy'] == [pytest.approx(accuracy)]
  assert results['rollout']['val_accuracy_mean'] is None
  with pytest.raises(FileExistsError):
    _convert_files(config, workdir, tmp_path, monkeypatch,
                   {'readout.pth': state})


# --------------------------------------------------------------------------
# The PHYRE readout
# --------------------------------------------------------------------------


def _config_file(name, variant=''):
  import importlib.util  # pylint: disable=g-import-not-at-top
  spec = importlib.util.spec_from_file_location(
      name, os.path.join(os.path.dirname(__file__), '..', '..', 'configs',
                         f'{name}.py'))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant) if variant else module.get_config()


def phyre_config():
  config = _config_file('phyre', 'planning')
  config.savi.num_slots, config.savi.slot_size = 3, 8
  r = config.readout
  r.embed_dim, r.num_layers, r.num_heads, r.mlp_ratio = 8, 2, 2, 2
  r.conditions, r.seeds = ('rollout',), (1,)
  return config


def official_phyre_readout(config, seed=0, num_selected=2):
  r = config.readout
  return aref.phyre_readout_state_dict(
      seed, slot_size=config.savi.slot_size, d_model=r.embed_dim,
      num_layers=r.num_layers, ffn_dim=r.mlp_ratio * r.embed_dim,
      num_selected=num_selected)


def test_phyre_readout_matches_numpy_and_is_written_for_plan(tmp_path,
                                                             monkeypatch):
  config = phyre_config()
  state = official_phyre_readout(config)
  converted = families.convert_state_dict(state, config)
  assert converted.stage == 'planning'
  slots = np.random.default_rng(2).standard_normal((4, 6, 3, 8))
  model = phyre_planning.build_classifier(config.readout, 'rollout')
  kwargs = dict(sel_slots=config.readout.selected_steps,
                num_heads=config.readout.num_heads,
                num_layers=config.readout.num_layers)
  expected = aref.phyre_readout_logits(slots, state, **kwargs)
  _close(model.apply({'params': converted.params}, slots), expected)
  workdir = str(tmp_path / 'run')
  [directory] = _convert_files(config, workdir, tmp_path, monkeypatch,
                               {'readout.pth': state})
  assert directory == os.path.join(workdir, 'planning', 'rollout', 'seed_1')
  # What plan reads.
  with open(os.path.join(directory, 'params.msgpack'), 'rb') as f:
    params = serialization.msgpack_restore(f.read())
  _close(model.apply({'params': params}, slots), expected)
  with open(os.path.join(directory, 'selection.json')) as f:
    assert json.load(f)['converted'] is True


def test_phyre_readout_errors():
  config = phyre_config()
  state = official_phyre_readout(config)
  config.readout.layer_norm_epsilon = 1e-6
  with pytest.raises(families.ConversionError,
                     match='readout.layer_norm_epsilon'):
    families.convert_state_dict(state, config)
  config.readout.layer_norm_epsilon = 1e-5
  config.readout.conditions = ('first_frame',)  # one frame, not two
  with pytest.raises(families.ConversionError,
                     match='enc_t_pe covers 2 frames.*selected_steps'):
    families.convert_state_dict(state, config)
  config.readout.conditions = ('rollout',)
  state['enc_t_pe'] = np.zeros_like(state['enc_t_pe'])  # t_pe='learnable'
  with pytest.raises(families.ConversionError, match="t_pe='sin'"):
    families.convert_state_dict(state, config)
  state = official_phyre_readout(config)
  config.readout.embed_dim = 16
  with pytest.raises(families.ConversionError,
                     match=r'in_proj.weight: checkpoint shape \(8, 8\).*'
                     'config.readout.embed_dim'):
    families.convert_state_dict(state, config)


# --------------------------------------------------------------------------
# The official configs take the official sizes
# --------------------------------------------------------------------------


def test_official_configs_convert_official_sized_checkpoints(tmp_path):
  """State dicts of the official configs' sizes (aloe_clevrer_params-rollout
  with CLEVRER's 82 words and 22 answers, readout_physion_params,
  readout_phyre_params-fold0) convert with configs/clevrer_vqa.py,
  configs/physion_contact.py and configs/phyre.py:planning."""
  words = ['PAD'] + [f'w{i:02d}' for i in range(81)]
  answers = ['PAD'] + [f'a{i:02d}' for i in range(21)]
  with open(tmp_path / 'CLEVRER_vocab.json', 'w') as f:
    json.dump({'q_vocab': {w: i for i, w in enumerate(words)},
               'a_vocab': {a: i for i, a in enumerate(answers)}}, f)
  config = _config_file('clevrer_vqa')
  config.vqa.vocab_file = str(tmp_path / 'CLEVRER_vocab.json')
  state = aref.aloe_state_dict(
      0, vocab_size=82, num_answers=22, input_dim=16, num_heads=8,
      slot_size=128, input_len=(6 + 1) * 25 + 20 + 12, num_layers=12,
      ffn_dim=512, cls_mlp_size=128)
  params = families.convert_state_dict(state, config).params['params']
  assert params['position'].shape == (208, 144)
  assert params['word_embedding']['embedding'].shape == (82, 14)
  config = _config_file('physion_contact')
  config.readout.conditions, config.readout.seeds = ('rollout',), (0,)
  state = aref.physion_readout_state_dict(0, num_slots=6, slot_size=192,
                                          feats_dim=192)
  assert families.convert_state_dict(state, config).params['relation'][
      'kernel'].shape == (384, 192)
  config = _config_file('phyre', 'planning')
  config.readout.conditions, config.readout.seeds = ('rollout',), (0,)
  state = aref.phyre_readout_state_dict(0, slot_size=128, d_model=128,
                                        num_layers=4, ffn_dim=512,
                                        num_selected=2)
  assert set(families.convert_state_dict(state, config).params[
      'transformer']) == {f'block_{i}' for i in range(4)}
