"""Downloads nobody should trust, one case each (issue 39); the fuzz of the
same readers is tests/reliability/test_reader_fuzz.py.

* MOVi: malformed features.json / dataset_info.json, PNG headers that claim
  other sizes (checked before decoding), a video name that is not UTF-8,
  and a dataset name that would lead the converter out of --source and
  --data_dir;
* CLEVRER: every kind of malformed question or vocabulary file;
* PHYRE and Physion: names from the layout files used in paths.

Each is one `error:` line (or one skipped video) naming the file, with
nothing written outside --data_dir and nothing a terminal acts on.
"""

import json
import shutil
import struct
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest

import dataset_fixtures as fx
from slotformer_jax.data import vqa
from slotformer_jax.data import media
from slotformer_jax.datasets import movi
from slotformer_jax.datasets import phyre
from slotformer_jax.datasets import physion
from slotformer_jax.data import prepare
from slotformer_jax.data import tfrecord


def _tree(folder):
  """{relative path: bytes} of every file under `folder`."""
  return {str(p.relative_to(folder)): p.read_bytes()
          for p in Path(folder).rglob('*') if p.is_file()}


def _one_error_line(capsys):
  err = capsys.readouterr().err
  lines = [line for line in err.splitlines() if line.startswith('error:')]
  assert len(lines) == 1 and 'Traceback' not in err, err
  assert all(c.isprintable() or c == '\n' for c in err), repr(err)
  return lines[0]


# --------------------------------------------------------------------------
# MOVi
# --------------------------------------------------------------------------


@pytest.fixture(scope='module')
def movi_download(tmp_path_factory):
  folder = tmp_path_factory.mktemp('movi') / 'movi_a' / '16x16' / '1.0.0'
  fx.write_movi(folder, shard_lengths={'train': [1]}, num_frames=3, size=16,
                seed=0, instances=(1, 2))
  return folder


def _copy(folder, tmp_path):
  copy = tmp_path / 'src' / 'a' / 'movi'
  shutil.copytree(folder, copy)
  return copy


def _convert(source, data_dir):
  movi.read_source.cache_clear()
  return prepare.main(['--dataset=movi', f'--source={source}',
                       f'--data_dir={data_dir}', '--num_workers=1',
                       '--no_progress', '--resolution=16',
                       '--max_objects=4'])


def _edit_json(path, edit):
  tree = json.loads(path.read_text())
  result = edit(tree)
  path.write_text(result if isinstance(result, str) else json.dumps(tree))


def _features(tree):
  return tree['featuresDict']['features']


@pytest.mark.parametrize('name, edit, needle', [
    ('features.json',
     lambda t: t['featuresDict'].update(features=list(_features(t).values())),
     'the top is a list, not an object'),
    ('features.json', lambda t: '[' * 100_000 + ']' * 100_000,
     'nested too deeply'),
    ('features.json', lambda t: '{"a": ' + '[' * 40 + ']' * 40 + '}',
     'deeper than 32 levels'),
    ('features.json', lambda t: _features(t)['instances']['sequence'][
        'feature']['featuresDict']['features']['positions']['tensor'].pop(
            'dtype') and None, "dtype None is not one of"),
    ('features.json', lambda t: _features(t)['video']['video'].update(
        shape={'dimensions': ['3', '1000000', '1000000', '3']}),
     'videos of 3 frames of 1000000x1000000'),
    ('features.json', lambda t: _features(t)['video']['video'].update(
        shape={'dimensions': ['3', '16', '16', '0']}),
     'video frames of (0,) and segmentations of (1,) channels'),
    ('dataset_info.json', lambda t: t['splits'][0].pop('name') and None,
     'split 0 is not an object with a text "name"'),
    ('dataset_info.json', lambda t: t.update(splits={'train': 1}),
     '"splits" is a dict, not a list'),
    ('dataset_info.json', lambda t: t['splits'][0].update(
        shardLengths=['1e9']), "a shard length is '1e9', not an integer"),
    ('dataset_info.json', lambda t: t.update(name='movi\x1b[2J'),
     "the name 'movi\\x1b[2J' holds a backslash, NUL or control character"),
])
def test_malformed_metadata_is_one_line(movi_download, tmp_path, capsys, name,
                                        edit, needle):
  """Before: AttributeError / KeyError / RecursionError tracebacks."""
  source = _copy(movi_download, tmp_path)
  _edit_json(source / name, edit)
  assert _convert(source, tmp_path / 'data') == 1
  line = _one_error_line(capsys)
  assert needle in line, line
  assert not (tmp_path / 'data' / 'movi_a').exists()


def test_a_name_that_leads_out_of_the_folders_is_refused(movi_download,
                                                        tmp_path, capsys):
  """dataset_info.json's name '../../escape': before, the converter read the
  shards `../../escape-train.tfrecord-*` outside --source and wrote
  array_record files to `<data_dir>/../../escape/` outside --data_dir.
  Now nothing is read or written."""
  source = _copy(movi_download, tmp_path)
  _edit_json(source / 'dataset_info.json',
             lambda t: t.update(name='../../escape'))
  # The shards where a converter that follows the name would look.
  for shard in source.glob('movi_a-*'):
    target = source / f'../../escape{shard.name[len("movi_a"):]}'
    shutil.copy(shard, target.resolve())
  data_dir = tmp_path / 'out' / 'data'
  before = _tree(tmp_path)
  assert _convert(source, data_dir) == 1
  line = _one_error_line(capsys)
  assert "the name '../../escape' leads out of the folder" in line, line
  assert _tree(tmp_path) == before  # nothing written anywhere


def _png_claiming(data, width, height):
  ihdr = bytearray(data[16:29])
  ihdr[0:8] = struct.pack('>II', width, height)
  return (data[:16] + bytes(ihdr)
          + struct.pack('>I', zlib.crc32(b'IHDR' + bytes(ihdr)) & 0xFFFFFFFF)
          + data[33:])


def _rewrite_record(source, edit):
  """Applies `edit` to the Example proto of the one train record."""
  from tensorflow_datasets.proto import tf_example_pb2  # pylint: disable=g-import-not-at-top
  shard = next(source.glob('*-train.tfrecord-*'))
  example = tf_example_pb2.Example.FromString(
      next(tfrecord.iter_records(shard)))
  edit(example.features.feature)
  fx.write_tfrecords(shard, [example.SerializeToString()])


@pytest.mark.parametrize('claim', [(10**6, 10**6), (12000, 12000), (17, 16)])
def test_a_frame_s_size_is_checked_from_its_header(movi_download, tmp_path,
                                                   capsys, claim):
  """A header claiming 10^6 x 10^6 pixels (PIL's bomb check: a traceback
  before), or any size other than features.json's: one line, before
  anything is decoded."""
  source = _copy(movi_download, tmp_path)

  def edit(features):
    frames = features['video'].bytes_list.value
    frames[1] = _png_claiming(frames[1], *claim)
  _rewrite_record(source, edit)
  assert _convert(source, tmp_path / 'data') == 1
  line = _one_error_line(capsys)
  width, height = claim
  assert f'a {height}x{width} frame (its PNG header), features.json says ' \
      '16x16' in line, line
  assert 'record 0' in line and 'download this file again' in line


def test_a_large_real_frame_is_refused_before_it_is_decoded(movi_download):
  """A real 4000 x 4000 frame where features.json says 16 x 16: refused
  from its header. Before, it was decoded first (48 MB here; a 12000 x
  12000 frame took 1.47 GB)."""
  from PIL import Image  # pylint: disable=g-import-not-at-top
  import io  # pylint: disable=g-import-not-at-top
  buffer = io.BytesIO()
  Image.new('RGB', (4000, 4000)).save(buffer, format='PNG')
  data = buffer.getvalue()
  tracemalloc.start()
  try:
    with pytest.raises(ValueError, match='a 4000x4000 frame .its PNG header'):
      movi._decode_png(data, (16, 16, 3), 'here')  # pylint: disable=protected-access
    peak = tracemalloc.get_traced_memory()[1]
  finally:
    tracemalloc.stop()
  assert peak < 4 << 20, peak  # the frame would be 48 MB


def test_a_video_name_that_is_not_utf8_is_one_line(movi_download, tmp_path,
                                                   capsys):
  """Before: a UnicodeDecodeError traceback from the worker."""
  source = _copy(movi_download, tmp_path)

  def edit(features):
    features['metadata/video_name'].bytes_list.value[0] = b'\xff\xfe\x1b[2J'
  _rewrite_record(source, edit)
  assert _convert(source, tmp_path / 'data') == 1
  line = _one_error_line(capsys)
  assert 'unreadable MOVi example (UnicodeDecodeError' in line, line


@pytest.mark.parametrize('key, value', [
    ('instances/bbox_frames/ragged_flat_values', 2**32 + 5),
    ('instances/bbox_frames/ragged_flat_values', 2**40),
    ('instances/bbox_frames/ragged_flat_values', -2**32 + 3),
    ('instances/bbox_frames/ragged_flat_values', 2**31),
    ('instances/bbox_frames/ragged_flat_values', -1),
    ('instances/bbox_frames/ragged_flat_values', 3),  # T: past the video
    ('instances/bbox_frames/ragged_flat_values', 2**63 - 1),
    ('instances/bbox_frames/ragged_flat_values', -2**63),
    ('metadata/num_instances', 2**16 + 2),  # uint16: it wrapped to 2
    ('metadata/num_instances', -2**63),
])
def test_an_integer_of_a_record_out_of_range_is_one_line(
    movi_download, tmp_path, capsys, key, value):
  """Before: the parser cast int64 to the declared int32 (uint16), so
  2**32 + 5 converted as frame 5, 2**40 as 0, -2**32 + 3 as 3, and
  2**16 + 2 instances as 2, with status 0. Every integer is now checked
  against its declared type before the cast, then by meaning (a frame of
  the video); nothing is written."""
  source = _copy(movi_download, tmp_path)

  def edit(features):
    features[key].int64_list.value[0] = value
  _rewrite_record(source, edit)
  assert _convert(source, tmp_path / 'data') == 1
  line = _one_error_line(capsys)
  assert 'record 0' in line, line
  if value not in (3, -1):
    assert (f'{key.split("/ragged")[0]} holds {value}, outside' in line
            or f'{key} holds {value}, outside' in line), line
  assert not any(p.is_file() and 'tfrecord' in p.name
                 for p in (tmp_path / 'data').rglob('*')), list(
                     (tmp_path / 'data').rglob('*'))


# Flows and depth (issue 51): every way a download can get them wrong is one
# line, before anything is written.


def _sequence_tensor(tree, key):
  return _features(tree)[key]['sequence']['feature']['tensor']


@pytest.mark.parametrize('edit, needle', [
    # Shape: three flow channels where MOVi has (delta row, delta column).
    (lambda t: _sequence_tensor(t, 'backward_flow').update(
        shape={'dimensions': ['16', '16', '3']}), 'backward_flow is declared '
     "as ((3, 16, 16, 3), 'uint16')"),
    # Dtype: a float32 flow, an 8-bit depth.
    (lambda t: _sequence_tensor(t, 'forward_flow').update(dtype='float32'),
     "forward_flow is declared as ((3, 16, 16, 2), 'float32')"),
    (lambda t: _features(t)['depth']['sequence']['feature']['image'].update(
        dtype='uint8'), "depth is declared as ((3,), (16, 16, 1), 'uint8')"),
    # A range of another shape, or none.
    (lambda t: _features(t)['metadata']['featuresDict']['features'][
        'depth_range']['tensor'].update(shape={'dimensions': ['3']}),
     'MOVi stores it as 3 uint16 frames of 16x16x1 with a float32 (2,) '
     'metadata/depth_range'),
    (lambda t: _features(t)['metadata']['featuresDict']['features'].pop(
        'backward_flow_range') and None, 'with range None'),
])
def test_flow_and_depth_declared_otherwise_are_one_line(
    movi_download, tmp_path, capsys, edit, needle):
  source = _copy(movi_download, tmp_path)
  _edit_json(source / 'features.json', edit)
  assert _convert(source, tmp_path / 'data') == 1
  line = _one_error_line(capsys)
  assert needle in line, line
  assert not (tmp_path / 'data' / 'movi_a').exists()


def _flow_values(key, edit):
  def rewrite(features):
    values = features[key].int64_list.value
    edit(values)
  return rewrite


def _range(key, values):
  def rewrite(features):
    field = features[f'metadata/{key}'].float_list.value
    del field[:]
    field.extend(values)
  return rewrite


def _depth_frame(frame):
  def rewrite(features):
    features['depth'].bytes_list.value[1] = frame(
        features['depth'].bytes_list.value[1])
  return rewrite


@pytest.mark.parametrize('edit, needle', [
    # Size: a value short, or a frame's worth too many.
    (_flow_values('backward_flow', lambda v: v.pop()), 'backward_flow'),
    (_flow_values('forward_flow', lambda v: v.extend([0] * 512)),
     'forward_flow'),
    # Range of a uint16: 65536 and -1 are refused before any cast.
    (_flow_values('backward_flow', lambda v: v.__setitem__(5, 65536)),
     'backward_flow holds 65536, outside [0, 65535]'),
    (_flow_values('forward_flow', lambda v: v.__setitem__(0, -1)),
     'forward_flow holds -1, outside [0, 65535]'),
    # The stored ranges: reversed, NaN, infinite, negative depth, too long.
    (_range('backward_flow_range', [3.0, -3.0]),
     'backward_flow_range is [3, -3], not a range'),
    (_range('forward_flow_range', [float('nan'), 1.0]),
     'forward_flow_range is [nan, 1], not a range'),
    (_range('backward_flow_range', [-1.0, float('inf')]),
     'backward_flow_range is [-1, inf], not a range'),
    (_range('depth_range', [-2.0, 9.0]),
     'depth_range is [-2, 9], not a range 0 <= low'),
    (_range('depth_range', [1.0, 2.0, 3.0]), 'depth_range'),
    # Depth frames: 8-bit where MOVi has 16, another size.
    (_depth_frame(lambda _: fx.png_bytes(np.zeros((16, 16, 1), np.uint8))),
     'a PNG of uint8 values, features.json says uint16'),
    (_depth_frame(lambda data: _png_claiming(data, 32, 16)),
     'a 16x32 frame (its PNG header), features.json says 16x16'),
])
def test_flow_and_depth_of_a_record_are_checked_in_one_line(
    movi_download, tmp_path, capsys, edit, needle):
  """A record whose flows or depth have the wrong size, values outside
  uint16, a range that is not one, or depth frames of another bit depth
  or size: one line naming the record; no shard is finished, no dataset
  written."""
  source = _copy(movi_download, tmp_path)
  _rewrite_record(source, edit)
  assert _convert(source, tmp_path / 'data') == 1
  line = _one_error_line(capsys)
  assert 'record 0' in line and needle in line, line
  assert 'download this file again' in line
  written = [p.name for p in (tmp_path / 'data').rglob('*') if p.is_file()]
  assert 'dataset_info.json' not in written
  assert not [n for n in written
              if 'array_record' in n and not n.endswith('.tmp')], written


# --------------------------------------------------------------------------
# CLEVRER questions and vocabularies
# --------------------------------------------------------------------------

_SCENES = [{'scene_index': 0, 'video_filename': 'video_00000.mp4',
            'questions': [
                {'question_id': 0, 'question_type': 'descriptive',
                 'question': 'what color is the cube?', 'answer': 'red'},
                {'question_id': 1, 'question_type': 'predictive',
                 'question': 'what will happen next?',
                 'choices': [{'choice_id': 0, 'choice': 'the cube collides',
                              'answer': 'correct'}]}]}]
_VOCAB = vqa.Vocabulary.from_scenes(_SCENES)


def _question(scenes):
  return scenes[0]['questions'][0]


def _choice(scenes):
  return scenes[0]['questions'][1]['choices'][0]


# The kinds of malformed content; each was a traceback from encode_question
# or read_json before (the choice id past int32 was found by the fuzz).
QUESTION_FILES = [
    ('an object at the top', lambda s: {'scenes': s},
     'is a dict, not a list of scenes'),
    ('a scene that is a list', lambda s: [list(s[0].values())],
     'scene 0 is a list, not an object'),
    ('no questions', lambda s: s[0].pop('questions') and s,
     "scene 0 has no 'questions'"),
    ('questions as an object', lambda s: s[0].update(questions={}) or s,
     "scene 0: 'questions' is a dict, not a list"),
    ('a scene index as text', lambda s: s[0].update(scene_index='0') or s,
     "scene 0: 'scene_index' is '0' (str), not an int"),
    ('a question id as a float', lambda s: _question(s).update(
        question_id=1.5) or s, "question 0: 'question_id' is 1.5 (float)"),
    ('a choice id past int32', lambda s: _choice(s).update(
        choice_id=2**31) or s,
     "choice 0: 'choice_id' is 2147483648, outside the 32-bit ints"),
    ('no question type', lambda s: _question(s).pop('question_type') and s,
     "question 0 has no 'question_type'"),
    ('a misspelled question type', lambda s: _question(s).update(
        question_type='descriptiv') or s,
     "the question type 'descriptiv' is not one of descriptive"),
    ('a question as a number', lambda s: _question(s).update(question=3) or s,
     "'question' is 3 (int), not a text"),
    ('an answer as a list', lambda s: _question(s).update(answer=['red'])
     or s, "'answer' is a list, not a text"),
    ('no choices', lambda s: s[0]['questions'][1].pop('choices') and s,
     "question 1 has no 'choices'"),
    ('a choice answer outside correct / wrong', lambda s: _choice(s).update(
        answer='yes') or s, "choice 0: the answer 'yes' is not 'correct' or "
     "'wrong'"),
    ('deep nesting', lambda s: '[' * 100_000 + ']' * 100_000,
     'nested too deeply'),
]


@pytest.mark.parametrize('what, edit, needle', QUESTION_FILES,
                         ids=[q[0] for q in QUESTION_FILES])
def test_a_malformed_question_file_is_one_line(tmp_path, what, edit, needle):
  del what
  scenes = json.loads(json.dumps(_SCENES))
  result = edit(scenes)
  (tmp_path / 'questions').mkdir()
  (tmp_path / 'questions' / 'train.json').write_text(
      result if isinstance(result, str) else json.dumps(result))
  with pytest.raises(vqa.QuestionFileError) as caught:
    vqa.encode_scenes(vqa.read_clevrer_questions(tmp_path, 'train'), _VOCAB,
                      8, 6)
  message = str(caught.value)
  assert needle in message and str(tmp_path) in message, message
  assert '\n' not in message


@pytest.mark.parametrize('edit, needle', [
    (lambda s: _question(s).update(question='what colour is the cube?')
     or s, "scene 0 question 0: the word 'colour' of 'what colour is the "
     "cube?' is not in the vocabulary"),
    (lambda s: _question(s).update(answer='purple\x1b[2J') or s,
     "scene 0 question 0: the answer 'purple\\x1b[2J' is not in the "
     'vocabulary'),
    (lambda s: _choice(s).update(choice='the cube collides with the cube '
                                 'and the cube') or s,
     'scene 0 question 1: 9 words do not fit in 6'),
])
def test_a_question_outside_the_vocabulary_is_one_line(tmp_path, edit,
                                                       needle):
  scenes = edit(json.loads(json.dumps(_SCENES)))
  with pytest.raises(vqa.QuestionFileError) as caught:
    vqa.encode_scenes(scenes, _VOCAB, 8, 6, path=tmp_path / 'train.json')
  assert needle in str(caught.value), caught.value
  assert str(tmp_path) in str(caught.value)


@pytest.mark.parametrize('content, needle', [
    (b'{"q_vocab": {"\xff": 0}, "a_vocab": {}}', 'is not UTF-8 text'),
    (json.dumps({'q_vocab': {'PAD': 0, 'a': True},
                 'a_vocab': {'PAD': 0}}).encode(),
     "q_vocab ids must be integers; 'a' has True"),
    (json.dumps({'q_vocab': ['PAD'], 'a_vocab': {'PAD': 0}}).encode(),
     "has no 'q_vocab' mapping"),
])
def test_a_malformed_vocabulary_is_one_line(tmp_path, content, needle):
  path = tmp_path / 'vocab.json'
  path.write_bytes(content)
  with pytest.raises(vqa.QuestionFileError) as caught:
    vqa.Vocabulary.load(path)
  assert needle in str(caught.value) and str(path) in str(caught.value)


# --------------------------------------------------------------------------
# PHYRE and Physion: names used in paths
# --------------------------------------------------------------------------


def test_a_phyre_rollout_id_that_leads_out_is_skipped(tmp_path):
  """An index line whose id is '../../../secret': before, the converter
  read `<source>/train/frames/../../../secret.png`, outside --source."""
  root = tmp_path / 'PHYRE'
  fx.write_json(root / phyre.META_FILE, {
      'format': phyre.FORMAT, 'format_version': phyre.FORMAT_VERSION,
      'tier': 'ball', 'eval_setup': 'ball_within_template', 'fold': 0,
      'fps': 1, 'frame_size': [8, 8]})
  (root / 'train' / 'frames').mkdir(parents=True)
  fx.write_png(tmp_path / 'secret.png', np.zeros((24, 8, 3), np.uint8))
  line = {'id': '../../../secret', 'task': '00002:013',
          'action': [0.1, 0.2, 0.3], 'success': True, 'num_frames': 3}
  (root / 'train' / phyre.INDEX_FILE).write_text(json.dumps(line) + '\n')
  options = phyre.Options(resolution=(8, 8), num_frames=3)
  (job,) = phyre.discover(root, 'train', options)
  with pytest.raises(media.SkipVideo) as caught:
    phyre.convert_rollout(job, options)
  assert caught.value.reason == 'bad_annotation'
  assert "rollout id '../../../secret.png' leads out of the folder" in (
      caught.value.message), caught.value.message


@pytest.mark.parametrize('eval_setup', ['../../x', 'a/b', 'x\x1b[2J'])
def test_a_phyre_eval_setup_that_is_no_name_is_refused(tmp_path, capsys,
                                                      eval_setup):
  """meta.json's eval_setup names the output folder: before, '../../x'
  wrote the dataset outside --data_dir."""
  root = tmp_path / 'PHYRE'
  fx.write_json(root / phyre.META_FILE, {
      'format': phyre.FORMAT, 'format_version': phyre.FORMAT_VERSION,
      'tier': 'ball', 'eval_setup': eval_setup, 'fold': 0, 'fps': 1,
      'frame_size': [8, 8]})
  (root / 'train' / 'frames').mkdir(parents=True)
  (root / 'train' / phyre.INDEX_FILE).write_text('{}\n')
  assert prepare.main(['--dataset=phyre', f'--source={root}',
                       f'--data_dir={tmp_path / "data"}', '--num_workers=1',
                       '--no_progress', '--splits=train']) == 1
  line = _one_error_line(capsys)
  assert 'is not a PHYRE eval setup name' in line, line
  assert not (tmp_path / 'data').exists()


def test_a_physion_split_list_that_leads_out_is_refused(tmp_path):
  """A split list entry '../../etc/passwd': before, it was read as a video
  of the split."""
  lists = tmp_path / 'lists'
  lists.mkdir()
  (lists / 'training_train.json').write_text(json.dumps(
      {'Dominoes': ['../../etc/passwd']}))
  with pytest.raises(ValueError, match="the video '../../etc/passwd' leads "
                     'out of the folder'):
    physion._listed_files(tmp_path / 'source', 'train',  # pylint: disable=protected-access
                          physion.Options(split_files=str(lists)))


def test_a_physion_label_row_with_too_few_columns_is_one_line(tmp_path):
  path = tmp_path / 'labels.csv'
  path.write_text('stimulus,extra,ground truth outcome\nname_img,x,True\n'
                  'short\n')
  with pytest.raises(ValueError, match=r'labels.csv:3: 1 columns, the label '
                     'is column 3'):
    physion.read_labels(path)


# --------------------------------------------------------------------------
# Integers read from a file: range-checked before any cast (issue 53)
# --------------------------------------------------------------------------

from slotformer_jax import files  # noqa: E402
from slotformer_jax.datasets import clevrer  # noqa: E402


@pytest.mark.parametrize('value', [2**31, 2**32 + 5, 2**40, -2**32 + 3, -1,
                                   2**63 - 1, -2**63, 10**400, 3.0, True,
                                   '7', np.int64(2**40)])
def test_an_int_from_a_file_outside_its_range_is_one_line(value):
  with pytest.raises(files.UntrustedFileError) as caught:
    files.int_in_range(value, 0, 2**31 - 1, what='x.json: frame')
  message = str(caught.value)
  assert message.startswith('x.json: frame is ') and '\n' not in message
  assert len(message) < 120, message  # 10**400 is not printed in full
  assert files.int_in_range(np.int32(7), 0, 9, what='x') == 7
  array = np.asarray([0, 2**40])
  with pytest.raises(files.UntrustedFileError, match='holds 1099511627776'):
    files.int_in_range(array, 0, 2**31 - 1, what='x')
  with pytest.raises(files.UntrustedFileError, match='float64 values'):
    files.int_in_range(np.zeros(2), 0, 9, what='x')


@pytest.mark.parametrize('counts, needle', [
    ([2**64, 0], 'is 18446744073709551616, outside'),  # OverflowError before
    ([2**62] * 4 + [16], 'is 4611686018427387904, outside'),  # sum wrapped
    ([1.5, 14.5], 'not a list of integers'),  # truncated to 1, 14 before
    ([True, 15], 'not a list of integers'),
    ('0' + 'o' * 30 + '0', 'more than 9 characters'),  # a 150-bit run
])
def test_clevrer_mask_runs_out_of_range_are_refused(counts, needle):
  with pytest.raises(ValueError, match=needle):
    clevrer.decode_rle({'size': [4, 4], 'counts': counts})


@pytest.mark.parametrize('size', [[2**32 + 4, 4], [4.0, 4], [10**400, 4]])
def test_clevrer_mask_sizes_out_of_range_are_refused(size):
  with pytest.raises(ValueError, match='an RLE size is'):
    clevrer.rle_size({'size': size, 'counts': [16]})


@pytest.mark.parametrize('scene_index', [2**32, -1, 1e400, 2.0])
def test_a_clevrer_scene_index_out_of_range_is_one_line(tmp_path,
                                                        scene_index):
  """1e400 (JSON's way to write infinity) was an OverflowError traceback;
  2.0 was read as 2."""
  (tmp_path / 'questions').mkdir()
  (tmp_path / 'questions' / 'train.json').write_text(json.dumps(
      [{'scene_index': scene_index, 'video_filename': 'video_00000.mp4',
        'questions': []}]).replace('Infinity', '1e400'))
  with pytest.raises(ValueError, match='cannot read the questions') as caught:
    clevrer._split_questions(tmp_path, 'train')  # pylint: disable=protected-access
  assert 'a scene_index is' in str(caught.value)


@pytest.mark.parametrize('object_id', [2**32, 2**32 + 1, 1.0, -2**63])
def test_a_clevrer_object_id_out_of_range_skips_the_video(tmp_path,
                                                          object_id):
  """1.0 and 2**32 + 1 were read as 1 (int()); now the video is skipped
  with a line naming the annotation."""
  annotation = tmp_path / 'annotation_00000.json'
  objects = [{'object_id': 0, 'color': 'red', 'material': 'metal',
              'shape': 'cube'},
             {'object_id': object_id, 'color': 'blue', 'material': 'rubber',
              'shape': 'sphere'}]
  annotation.write_text(json.dumps({
      'object_property': objects,
      'motion_trajectory': [{'objects': [{'object_id': 0,
                                          'inside_camera_view': True}]}]}))
  job = clevrer.VideoJob(key='video_00000', index=0,
                         video=tmp_path / 'video_00000.mp4',
                         annotation=annotation, annotation_expected=True,
                         proposal=None, proposal_expected=False)
  with pytest.raises(media.SkipVideo) as caught:
    clevrer._read_annotation(job, clevrer.Options())  # pylint: disable=protected-access
  assert caught.value.reason == 'bad_annotation'
  assert 'an object_id is' in caught.value.message, caught.value.message


def _phyre_folder(root, meta=None, line=None):
  fx.write_json(root / phyre.META_FILE, {
      'format': phyre.FORMAT, 'format_version': phyre.FORMAT_VERSION,
      'tier': 'ball', 'eval_setup': 'ball_within_template', 'fold': 0,
      'fps': 1, 'frame_size': [8, 8], **(meta or {})})
  (root / 'train' / 'frames').mkdir(parents=True)
  fx.write_png(root / 'train' / 'frames' / '0.png',
               np.zeros((24, 8, 3), np.uint8))
  entry = {'id': '0', 'task': '00002:013', 'action': [0.1, 0.2, 0.3],
           'success': True, 'num_frames': 3, **(line or {})}
  (root / 'train' / phyre.INDEX_FILE).write_text(
      json.dumps(entry).replace('Infinity', '1e400') + '\n')


@pytest.mark.parametrize('fold', [2**32, -1, 10**400, 1.0])
def test_a_phyre_fold_out_of_range_is_one_line(tmp_path, capsys, fold):
  root = tmp_path / 'PHYRE'
  _phyre_folder(root, meta={'fold': fold})
  assert prepare.main(['--dataset=phyre', f'--source={root}',
                       f'--data_dir={tmp_path / "data"}', '--num_workers=1',
                       '--no_progress', '--splits=train']) == 1
  line = _one_error_line(capsys)
  assert 'meta.json: fold is' in line, line
  assert not (tmp_path / 'data').exists()


@pytest.mark.parametrize('line, needle', [
    ({'task': '4294967301:013'}, "the task's template number is 4294967301"),
    ({'task': '99999999999999999999999:013'}, "template number is"),
    ({'action': [10**400, 0.0, 0.0]}, 'OverflowError'),  # a traceback before
    ({'action': [1e400, 0.0, 0.0]}, None),  # inf: a float, read as before
    ({'num_frames': 3.0}, 'num_frames is 3.0'),
    ({'num_frames': 2**32 + 3}, 'num_frames 4294967299 is not in 1..10000'),
])
def test_phyre_index_numbers_out_of_range_skip_the_rollout(tmp_path, line,
                                                           needle):
  root = tmp_path / 'PHYRE'
  _phyre_folder(root, line=line)
  options = phyre.Options(resolution=(8, 8), num_frames=3)
  (job,) = phyre.discover(root, 'train', options)
  if needle is None:
    assert job.problem is None
    return
  with pytest.raises(media.SkipVideo) as caught:
    phyre.convert_rollout(job, options)
  assert caught.value.reason == 'bad_annotation'
  assert needle in caught.value.message, caught.value.message


@pytest.mark.parametrize('label', ['4294967297', '2', '-1', '1e400', '1.0',
                                   'inf'])
def test_a_physion_label_that_is_no_0_1_true_false_is_one_line(tmp_path,
                                                                label):
  """Labels are read as one of four words, never cast (checked)."""
  path = tmp_path / 'labels.csv'
  path.write_text(f'stimulus,ground truth outcome\nname_img,{label}\n')
  with pytest.raises(ValueError, match='is not True/False'):
    physion.read_labels(path)


def _traced_read(root):
  """(scenes or the error, peak bytes traced while reading)."""
  tracemalloc.start()
  try:
    try:
      result = vqa.read_clevrer_questions(root, 'train')
    except vqa.QuestionFileError as error:
      result = error
    return result, tracemalloc.get_traced_memory()[1]
  finally:
    tracemalloc.stop()


def _question_file(root, scene, size):
  path = root / 'questions' / 'train.json'
  path.parent.mkdir(parents=True)
  count = size // (len(scene) + 1)
  path.write_text('[' + ','.join([scene] * count) + ']')
  return path.stat().st_size


def test_a_question_file_of_empty_objects_is_refused_in_little_memory(
    tmp_path):
  """Issue 61, case 7: `[{},{},...]` cost ~51 bytes of memory per byte of
  file (the whole file was parsed before any scene was checked; 48 MiB ->
  2.38 GiB): scene by scene, it is refused at scene 0."""
  size = _question_file(tmp_path, "{}", 1 << 20)
  result, peak = _traced_read(tmp_path)
  assert isinstance(result, vqa.QuestionFileError)
  assert "scene 0 has no 'scene_index'" in str(result)
  assert peak < 3 * size, (peak, size)  # the bytes and the text, no more


def test_valid_question_files_cost_a_few_bytes_of_memory_per_byte(tmp_path):
  """The most objects per byte a valid file can have (scenes without
  questions; questions of one word): what is kept stays within 8 bytes of
  memory per byte of file (docs/reliability.md: measured at the limit)."""
  question = ('{"question_id":0,"question_type":"descriptive",'
              '"question":"a","answer":"b"}')
  for name, scene in (
      ('empty', '{"scene_index":0,"video_filename":"v","questions":[]}'),
      ('questions', '{"scene_index":0,"video_filename":"v","questions":['
       + ','.join([question] * 100) + ']}')):
    root = tmp_path / name
    size = _question_file(root, scene, 512 << 10)
    scenes, peak = _traced_read(root)
    assert isinstance(scenes, list) and scenes, scenes
    assert peak < 8 * size, (name, peak / size)
    print(name, f"{peak / size:.2f} bytes traced per byte of file")


def test_a_scene_longer_than_its_limit_is_one_line(tmp_path, monkeypatch):
  monkeypatch.setattr(vqa, 'MAX_SCENE_CHARS', 4096)
  question = ('{"question_id":0,"question_type":"descriptive",'
              '"question":"a","answer":"b"}')
  path = tmp_path / 'questions' / 'train.json'
  path.parent.mkdir(parents=True)
  path.write_text('[{"scene_index":0,"video_filename":"v","questions":['
                  + ','.join([question] * 100) + ']}]')
  with pytest.raises(vqa.QuestionFileError) as raised:
    vqa.read_clevrer_questions(tmp_path, 'train')
  message = str(raised.value)
  assert 'element 0 is not valid within its first 4096 characters' in message
  assert '\n' not in message
