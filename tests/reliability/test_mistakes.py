"""One `error:` line for every mistake a user can make (issue 27, part B).

Each test reproduces one mistake (or its class) that ended in a traceback, a
misleading line or a silently bad run, and checks the line that replaces it:
1. the --config argument: a missing file, a folder, a syntax error, a
   get_config that raises, an unknown variant; the command line: no
   --config, a wrong type, an unknown --mode (subprocesses: exit status 2
   for the command line, 1 for the file);
2. a frame size the decoder (SAVi) or the dVAE (STEVE) cannot produce,
   caught before any data is generated;
3. rates, sizes, clip norms, loss weights that cannot work, by field kind;
   a loss that becomes non-finite names its term;
4. places that cannot be written: the workdir (lock file), the dataset
   cache, the converter's output;
5. lines that sent the user the wrong way (issue 38): a video-prediction
   mode on a task config, the settings of a first run that made nothing,
   a CLEVRER download without the test videos.
"""

import errno
import itertools
import os
import re
import subprocess
import sys

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from slotformer_jax import errors
from slotformer_jax.config import checks as config_checks
from slotformer_jax.errors import UserError
from slotformer_jax.workdir.lock import FileLock
from slotformer_jax.modules.decoders import SpatialBroadcastDecoder
from slotformer_jax.official import convert as convert_official
from slotformer_jax.runtime import checkpoint as checkpoint_lib
from slotformer_jax.train.trainer import Diverged
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit

import pipeline_helpers
from pipeline_helpers import check
from slotformer_jax import slot_models
from slotformer_jax.slot_models import savi as savi_slots
from slotformer_jax.workdir.lock import workdir_lock
from slotformer_jax.workdir.paths import Paths

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), '..', '..'))
CONFIGS = os.path.join(ROOT, 'configs')
SYNTHETIC = os.path.join(CONFIGS, 'synthetic.py')


def _variants(path):
  """The variants a config file names in its get_config ('' included)."""
  with open(path) as f:
    source = f.read()
  found = re.findall(r"variant == '(\w+)'", source)
  for group in re.findall(r'variant in \(([^)]*)\)', source):
    found += re.findall(r"'(\w+)'", group)
  if os.path.basename(path) == 'movi.py':  # words joined: its VARIANTS
    found += re.findall(r"'(\w+)'", re.search(
        r'VARIANTS = \(([^)]*)\)', source).group(1))
  return list(dict.fromkeys([''] + found))


def _every_config_spec():
  for name in sorted(os.listdir(CONFIGS)):
    if name.endswith('.py') and not name.startswith('_'):
      path = os.path.join(CONFIGS, name)
      for variant in _variants(path):
        yield path + (f':{variant}' if variant else '')


def _main(*args, cwd):
  env = dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS='cpu',
             SLOTFORMER_DATA_DIR=os.path.join(cwd, 'data'))
  env.pop('XLA_FLAGS', None)
  return subprocess.run(
      [sys.executable, '-m', 'slotformer_jax.main', *args], cwd=cwd, env=env,
      capture_output=True, text=True, timeout=300)


def _one_error_line(result):
  assert 'Traceback' not in result.stderr, result.stderr
  lines = [line for line in result.stderr.splitlines()
           if line.startswith('error:')]
  assert len(lines) == 1, result.stderr
  others = [line for line in result.stderr.splitlines()
            if line.strip() and not line.startswith(('error:', 'pybullet'))
            and ' I slotformer_jax]' not in line]
  assert not others, result.stderr  # nothing but the one line (and INFO)
  return lines[0]


# --------------------------------------------------------------------------
# 1. the command line and the config file
# --------------------------------------------------------------------------


def _write_broken_config(folder):
  (folder / 'broken.py').write_text(
      'def get_config():\n  config = dict(\n  return config +\n')


@pytest.mark.parametrize('args, status, needles', [
    (['--config=missing/nope.py'], 2, ['missing/nope.py', 'does not exist']),
    (['--config=broken.py'], 1, ['broken.py, line 2: ']),
    ([], 2, ['--config is required']),
])
def test_config_argument_mistakes_are_one_line(tmp_path, monkeypatch, capsys,
                                               args, status, needles):
  """In-process: these end before absl parses the flags."""
  from slotformer_jax import main as main_lib  # pylint: disable=g-import-not-at-top
  _write_broken_config(tmp_path)
  monkeypatch.chdir(tmp_path)
  with pytest.raises(SystemExit) as exit_info:
    main_lib.run_main(['main.py', *args, f'--workdir={tmp_path / "run"}'])
  assert exit_info.value.code == status
  stderr = capsys.readouterr().err
  assert len(stderr.strip().splitlines()) == 1, stderr
  for needle in needles:
    assert needle in stderr and stderr.startswith('error: '), stderr
  assert not os.path.exists(tmp_path / 'run')


@pytest.mark.parametrize('args, status, needles', [
    ([f'--config={SYNTHETIC}:tiny', '--config.savi.num_slots=abc'], 2,
     ['--config.savi.num_slots=abc', 'invalid literal']),
    ([f'--config={SYNTHETIC}:tiny', '--mode=bogus'], 2,
     ['--mode=bogus', 'train_savi']),
    ([f'--config={SYNTHETIC}:tiny', '--config.savi.learning_rate=-1',
      '--mode=train_savi'], 1, ['savi.learning_rate must be a learning rate '
                                '> 0, got -1.0']),
])
def test_command_line_mistakes_are_one_line(tmp_path, args, status, needles):
  """In a subprocess: absl parses the flags once per process."""
  result = _main(*args, f'--workdir={tmp_path / "run"}', cwd=str(tmp_path))
  line = _one_error_line(result)
  assert result.returncode == status, result.stderr
  for needle in needles:
    assert needle in line, line
  assert not os.path.exists(tmp_path / 'run')  # before any work
  assert not os.path.exists(tmp_path / 'data' / 'synthetic_obj3d')


def test_a_config_file_that_fails_names_file_and_line(tmp_path):
  missing = tmp_path / 'nope.py'
  with pytest.raises(config_checks.ConfigFileError, match='does not exist'):
    config_checks.load_config_file(str(missing))
  with pytest.raises(config_checks.ConfigFileError, match='is a folder'):
    config_checks.load_config_file(str(tmp_path))
  raises = tmp_path / 'raises.py'
  raises.write_text('import math\n\n\ndef get_config():\n'
                    '  return math.sqrt(-1)\n')
  with pytest.raises(config_checks.ConfigError) as error:
    config_checks.load_config_file(str(raises))
  assert not isinstance(error.value, config_checks.ConfigFileError)
  assert f'{raises}, line 5: get_config() failed: ValueError: math domain' \
      in str(error.value)
  at_import = tmp_path / 'at_import.py'
  at_import.write_text('X = 1\nY = undefined_name\n')
  with pytest.raises(config_checks.ConfigError,
                     match=r'at_import.py, line 2: NameError'):
    config_checks.load_config_file(str(at_import))
  no_function = tmp_path / 'empty.py'
  no_function.write_text('CONFIG = {}\n')
  with pytest.raises(config_checks.ConfigError, match='no get_config'):
    config_checks.load_config_file(str(no_function))
  # check_overrides (main's first step) reports them too, not None.
  with pytest.raises(config_checks.ConfigFileError, match='does not exist'):
    config_checks.check_overrides([f'--config={missing}', '--config.seed=1'])
  with pytest.raises(config_checks.ConfigFileError, match='does not exist'):
    config_checks.check_overrides(['--config', str(missing)])


@pytest.mark.parametrize('path', sorted(
    os.path.join(CONFIGS, n) for n in os.listdir(CONFIGS)
    if n.endswith('.py') and not n.startswith('_')))
def test_an_unknown_variant_lists_the_known_ones(path):
  with pytest.raises(config_checks.ConfigFileError) as error:
    config_checks.load_config_file(path + ':no_such_variant')
  message = str(error.value)
  assert '\n' not in message and os.path.basename(path) in message
  known = [v for v in _variants(path) if v]
  if os.path.basename(path) == 'movi.py':  # words joined: it lists the words
    known = [w for v in known for w in v.split('_')]
  if known:
    assert 'no_such_variant' in message
    for variant in known:
      assert variant in message, message
  else:  # the fix: drop the colon (or the config says it has none)
    assert 'drop ":no_such_variant"' in message or 'has none' in message


# --------------------------------------------------------------------------
# 2. a frame size the decoder cannot produce
# --------------------------------------------------------------------------


def _decodes_to(broadcast, num_layers, resolution):
  decoder = SpatialBroadcastDecoder(
      output_resolution=resolution, broadcast_resolution=broadcast,
      features=(4,) * num_layers, kernel_size=3)
  slots = jnp.zeros((1, 2, 8))
  try:
    jax.eval_shape(decoder.init, jax.random.key(0), slots)
  except ValueError:
    return False
  return True


@pytest.mark.parametrize('broadcast, num_layers', [((8, 8), 2), ((4, 8), 3),
                                                   ((16, 16), 0)])
def test_decoder_resolutions_are_what_the_decoder_produces(broadcast,
                                                           num_layers):
  sizes = savi_slots.decoder_resolutions(broadcast, num_layers)
  candidates = set(sizes) | {(30, 30), (24, 24), (64, 64), (16, 8), (8, 16),
                             (32, 64), (128, 128)}
  for resolution in sorted(candidates):
    assert _decodes_to(broadcast, num_layers, resolution) == (
        resolution in sizes), resolution


def test_a_resolution_the_decoder_cannot_produce_fails_before_data(tmp_path):
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.resolution = (30, 30)
  with pytest.raises(UserError) as error:
    check(config, ('train_savi',), num_devices=1)
  message = str(error.value)
  assert 'data.resolution (30, 30)' in message
  assert '8x8, 16x16, 32x32 work' in message
  assert 'savi.decoder.broadcast_resolution' in message
  assert not os.path.exists(tmp_path / 'data')
  config.data.resolution = (16, 16)
  check(config, ('train_savi',), num_devices=1)


def test_a_resolution_the_dvae_cannot_produce_fails_before_data(tmp_path):
  config = pipeline_helpers.load_config('synthetic', 'steve_tiny')
  config.data.data_dir = str(tmp_path / 'data')
  config.data.resolution = (30, 30)
  with pytest.raises(UserError, match=r'multiples of 4 \(e.g. \(32, 32\)\)'):
    check(config, ('train_dvae',), num_devices=1)
  assert not os.path.exists(tmp_path / 'data')
  config.data.resolution = (36, 28)  # any multiple of 4 decodes back
  check(config, ('train_dvae',), num_devices=1)


# --------------------------------------------------------------------------
# 3. values that cannot work, by field kind; a loss that becomes non-finite
# --------------------------------------------------------------------------


@pytest.mark.parametrize('field, value, expected', [
    ('savi.learning_rate', -1.0, 'savi.learning_rate must be a learning '
     'rate > 0, got -1.0'),
    ('savi.learning_rate', 0.0, 'a learning rate > 0, got 0.0'),
    ('slotformer.learning_rate', float('nan'), 'a learning rate > 0, got nan'),
    ('slotformer.learning_rate', float('inf'), 'a learning rate > 0, got inf'),
    ('dvae.learning_rate', -1e-3, 'dvae.learning_rate must be'),
    ('steve.group_learning_rates.decoder', -1.0,
     'steve.group_learning_rates.decoder must be a learning rate > 0'),
    ('slot_lstm.learning_rate', 0.0, 'slot_lstm.learning_rate must be'),
    ('savi.warmup_fraction', -0.1, 'savi.warmup_fraction must be a fraction '
     'in [0, 1]'),
    ('slotformer.min_lr_fraction', 2.0, 'slotformer.min_lr_fraction must be'),
    ('savi.grad_clip', -1.0, 'savi.grad_clip must be a number >= 0'),
    ('savi.kl_weight', -1e-4, 'savi.kl_weight must be a number >= 0'),
    ('slotformer.image_loss_weight', -1.0, 'slotformer.image_loss_weight'),
    ('slotformer.dropout_rate', 1.0, 'slotformer.dropout_rate must be a rate '
     'in [0, 1)'),
    ('savi.layer_norm_epsilon', 0.0, 'savi.layer_norm_epsilon must be a '
     'number > 0'),
    ('savi.batch_size', 0, 'savi.batch_size must be an integer >= 1, got 0'),
    ('dvae.batch_size', -4, 'dvae.batch_size must be an integer >= 1'),
    ('steve.num_slots', 0, 'steve.num_slots must be an integer >= 1'),
    ('savi.num_slots', 0, 'savi.num_slots must be an integer >= 1'),
    ('slotformer.num_heads', 0, 'slotformer.num_heads must be an integer'),
    ('savi.decoder.features', (32, 0), 'savi.decoder.features must be '
     'integers >= 1'),
    ('savi.predictor.lstm_size', -1, 'savi.predictor.lstm_size must be an '
     'integer >= 0'),
    ('slotformer.burn_in', 12, 'burn_in 12 + rollout 3 (stride 1) needs 15 '
     'frames, the videos have 12'),
])
def test_values_that_cannot_work_fail_before_work(tmp_path, field, value,
                                                  expected):
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  config.data.data_dir = str(tmp_path / 'data')
  *sections, name = field.split('.')
  node = config
  for section in sections:
    node = node[section]
  node[name] = value
  with pytest.raises(UserError) as error:
    check(config, ('train_savi', 'train_slotformer'),
                           num_devices=1)
  assert expected in str(error.value)
  assert str(error.value).count(expected) == 1  # one line per problem
  assert not os.path.exists(tmp_path / 'data')


@pytest.mark.parametrize('field, value, expected', [
    ('data.resolution', (32,), 'data.resolution must be (H, W): a tuple of '
     '2, got (32,)'),
    ('data.resolution', 32, 'data.resolution must be (H, W): a tuple of 2, '
     'got 32'),
    ('data.resolution', (8, 8, 8), 'data.resolution must be (H, W)'),
    ('savi.decoder.broadcast_resolution', (8,), 'savi.decoder.'
     'broadcast_resolution must be (H, W): a tuple of 2, got (8,)'),
    ('savi.encoder.features', 64, 'savi.encoder.features must be a tuple, '
     'got 64'),
    ('savi.encoder.strides', (2,), 'savi.encoder.strides (2,) and '
     'savi.encoder.features (32, 32, 32, 32) must have one entry per layer'),
    ('savi.decoder.features', 32, 'savi.decoder.features must be a tuple'),
    ('evaluation.metrics', 'psnr', 'evaluation.metrics must be a tuple'),
])
def test_a_field_of_the_wrong_shape_is_one_line_before_work(
    tmp_path, field, value, expected):
  """Before: `--config.data.resolution=32` (which arrives as (32,)) ended in
  `ValueError: resolution must be (H, W) >= 8, got (32,)` from a dataclass,
  with a traceback; a broadcast grid of one entry, in a ValueError from
  the decoder's size check; strides and features of other lengths, in the
  encoder at the first step."""
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  config.data.data_dir = str(tmp_path / 'data')
  *sections, name = field.split('.')
  tree = config.to_dict()  # as a config file writes it: any type
  node = tree
  for section in sections:
    node = node[section]
  node[name] = value
  config = ml_collections.ConfigDict(tree)
  with pytest.raises(UserError) as error:
    check(config, ('train_savi', 'evaluate'), num_devices=1)
  assert expected in str(error.value), str(error.value)
  assert not os.path.exists(tmp_path / 'data')


def test_the_wrong_resolution_on_the_command_line_is_one_line(tmp_path):
  """The issue's command: one line, status 1, nothing written."""
  result = _main(f'--config={SYNTHETIC}:tiny', '--mode=train_savi',
                 '--config.data.resolution=32',
                 f'--workdir={tmp_path / "run"}', cwd=str(tmp_path))
  line = _one_error_line(result)
  assert result.returncode == 1, result.stderr
  assert 'data.resolution must be (H, W): a tuple of 2, got (32,)' in line
  assert not os.path.exists(tmp_path / 'run')
  assert not os.path.exists(tmp_path / 'data' / 'synthetic_obj3d')


@pytest.mark.parametrize('field, value, expected', [
    ('seed', -1, 'seed must be an integer in [0, 2147483646] (what a jax '
     'PRNG key holds), got -1'),
    # 2**40 ran the whole pipeline as seed 0 (a jax key holds 32 bits).
    ('seed', 2**40, 'seed must be an integer in [0, 2147483646]'),
    ('seed', 2**31 - 1, 'seed must be an integer in [0, 2147483646]'),
    ('seeds', (0, 2**31), 'seeds must be integers in [0, 2147483646]'),
    ('savi.targets', (), "savi.targets names no target; give one or more, "
     "e.g. ('rgb',)"),
])
def test_config_numbers_beyond_what_the_code_holds_are_one_line(
    tmp_path, field, value, expected):
  """Issue 61: these passed the checks, made the data and wrote
  config.json, then ended in `OverflowError ... out of bounds for int32`,
  `ValueError: expected non-negative integer` or a 35-line traceback."""
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  config.data.data_dir = str(tmp_path / 'data')
  *sections, name = field.split('.')
  node = config
  for section in sections:
    node = node[section]
  with node.ignore_type():
    node[name] = value
  with pytest.raises(UserError) as error:
    check(config, ('prepare_data', 'train_savi'), num_devices=1)
  assert expected in str(error.value), str(error.value)
  assert '\n' not in str(error.value)
  assert not os.path.exists(tmp_path / 'data')


def test_the_largest_seed_passes_and_aloe_s_seed_is_checked():
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  config.seed = 2**31 - 2
  check(config, ('train_savi',), num_devices=1)
  config = pipeline_helpers.load_config('synthetic_vqa')
  config.seed = 3_000_000
  with pytest.raises(UserError, match='seed 3000000 is too large for Aloe'):
    check(config, ('train_vqa',), num_devices=1)
  config.seed, config.vqa.seed = 0, 1000
  with pytest.raises(UserError, match=r'vqa.seed must be an integer in '
                     r'\[0, 999\], got 1000'):
    check(config, ('train_vqa',), num_devices=1)


def test_a_seed_out_of_range_on_the_command_line_writes_nothing(tmp_path):
  """The issue's command: one line, status 1, no data, no config.json."""
  result = _main(f'--config={SYNTHETIC}:tiny',
                 "--config.seeds=(0, 2147483648)",
                 f'--workdir={tmp_path / "run"}', cwd=str(tmp_path))
  line = _one_error_line(result)
  assert result.returncode == 1, result.stderr
  assert 'seeds must be integers in [0, 2147483646]' in line
  assert not os.path.exists(tmp_path / 'run' / 'config.json')
  assert not os.path.exists(tmp_path / 'data' / 'synthetic_obj3d')


@pytest.mark.parametrize('open_size, choice_size, expected', [
    (0, 8, None), (8, 0, None),  # one kind of question is not drawn
    (0, 0, 'vqa.open_batch_size and vqa.choice_batch_size are both 0'),
    (-8, 8, 'vqa.open_batch_size must be an integer >= 0, got -8'),
    (8, 3, 'vqa.choice_batch_size=3 does not split over the 2 devices'),
])
def test_aloe_batch_sizes_may_leave_out_one_kind_of_question(
    open_size, choice_size, expected):
  # Before: a batch of 0 was refused (`batch_size$`: an integer >= 1), so an
  # open-only or choice-only question set could not be trained on.
  config = pipeline_helpers.load_config('synthetic_vqa')
  config.vqa.open_batch_size, config.vqa.choice_batch_size = (open_size,
                                                              choice_size)
  if expected is None:
    check(config, ('train_vqa',), num_devices=2)
    return
  with pytest.raises(UserError) as error:
    check(config, ('train_vqa',), num_devices=2)
  assert str(error.value).count(expected) == 1, str(error.value)


@pytest.mark.parametrize('spec', list(_every_config_spec()))
def test_every_shipped_config_passes_the_field_kinds(spec):
  config = config_checks.load_config_file(spec)
  assert config_checks.check_field_kinds(config) == []
  assert config_checks.check_field_shapes(config) == []
  assert slot_models.get(config).check_config(frozenset()) == []


@pytest.mark.parametrize('spec', list(_every_config_spec()))
def test_every_shipped_config_passes_the_checks_of_its_whole_run(
    spec, tmp_path):
  # The checks once took the contact readout's section (epochs, no steps)
  # for a stage-1 part: every contact and planning run was refused.
  from slotformer_jax import stages  # pylint: disable=g-import-not-at-top
  from slotformer_jax.run import Run  # pylint: disable=g-import-not-at-top
  config = config_checks.load_config_file(spec)
  if 'source' in config.data:  # configs/videos.py: the user's folder
    config.data.source = str(tmp_path)
  run = Run.create(config, '/nonexistent/run')
  stages.check(run, stages.selected_stages(run, 'all'), num_devices=1,
               num_processes=1)


# Fields holding a path or a name of something outside the config: their
# value is checked where it is read (the data stage, the question reader).
_CHECKED_WHERE_READ = ('data.data_dir', 'data.prepared_config',
                       'stage1_workdir', 'vqa.questions_root',
                       'vqa.vocab_file')
def _string_fields(config, prefix=''):
  for key in config.keys():
    value = config[key]
    if isinstance(value, ml_collections.ConfigDict):
      yield from _string_fields(value, f'{prefix}{key}.')
    elif isinstance(value, str):
      yield f'{prefix}{key}'


@pytest.mark.parametrize('spec', list(_every_config_spec()))
def test_a_wrong_value_of_any_string_field_is_one_line_before_any_work(spec):
  # What main runs before it takes the workdir's lock and makes any data.
  from slotformer_jax import stages  # pylint: disable=g-import-not-at-top
  from slotformer_jax.run import Run  # pylint: disable=g-import-not-at-top
  shipped = config_checks.load_config_file(spec)
  # Fields no stage of this config reads: the evaluated split of video
  # prediction in a task's config, the data splits of the embedded PHYRE-
  # like planning (split by task).
  unread = (('evaluation.split',) if shipped.task else ()) + (
      ('readout.splits.train', 'readout.splits.val', 'readout.splits.test')
      if shipped.data.name == 'synthetic_phyre' else ())
  fields = [f for f in _string_fields(shipped)
            if f not in _CHECKED_WHERE_READ + unread]
  assert fields
  for field in fields:
    config = config_checks.load_config_file(spec)
    *sections, name = field.split('.')
    node = config
    for section in sections:
      node = node[section]
    node[name] = 'no_such_value'
    with pytest.raises(UserError) as error:
      run = Run.create(config, '/nonexistent/run')
      stages.check(run, stages.selected_stages(run, 'all'), num_devices=1,
                   num_processes=1)
    line = str(error.value)
    assert '\n' not in line and field in line and "'no_such_value'" in line, (
        field, line)


def test_declared_choices_are_the_ones_the_modules_take():
  # The config declares each field's values once; the modules below it
  # (which a config never imports) must take exactly those.
  from slotformer_jax.config.defaults import CHOICES  # pylint: disable=g-import-not-at-top
  from slotformer_jax.modules import encoders, initializers, slot_init  # pylint: disable=g-import-not-at-top
  from slotformer_jax.modules import stochastic_savi, transitions  # pylint: disable=g-import-not-at-top
  from slotformer_jax.runtime import precision  # pylint: disable=g-import-not-at-top
  from slotformer_jax.evaluation import metrics  # pylint: disable=g-import-not-at-top
  from slotformer_jax.modules import aloe, readouts, slotformer  # pylint: disable=g-import-not-at-top
  assert CHOICES['savi.initial_slots'] == slot_init.INITIAL_SLOTS
  assert CHOICES['savi.init'] == initializers.INITIALIZATIONS
  assert CHOICES['slotformer.init'] == initializers.INITIALIZATIONS
  assert CHOICES['savi.encoder.padding'] == encoders.PADDINGS
  assert CHOICES['steve.encoder.padding'] == encoders.PADDINGS
  assert CHOICES['savi.predictor.kind'] == transitions.PREDICTORS
  assert CHOICES['savi.posterior_head'] == stochastic_savi.POSTERIOR_HEADS
  assert CHOICES['compute_dtype'] == precision.COMPUTE_DTYPES
  assert CHOICES['evaluation.miou_absent_ids'] == metrics.ABSENT_ID_CONVENTIONS
  assert CHOICES['slotformer.positional_encoding'] == (slotformer.TEMPORAL,
                                                       slotformer.NAIVE)
  assert CHOICES['vqa.positions'] == (aloe.TOKEN, aloe.FRAME)
  assert CHOICES['readout.pairs'] == (readouts.UNORDERED,
                                      readouts.BOTH_ORDERS)


def test_a_positional_encoding_typo_is_one_line_before_any_data(tmp_path):
  result = _main('--config=' + SYNTHETIC + ':tiny',
                 f'--workdir={tmp_path / "run"}',
                 '--config.slotformer.positional_encoding=temporl',
                 cwd=str(tmp_path))
  assert result.returncode == 1
  line = _one_error_line(result)
  assert ("slotformer.positional_encoding must be one of 'temporal', "
          "'naive', got 'temporl'") in line, line
  # No dataset and no workdir made.
  assert not (tmp_path / 'data').exists()
  assert not (tmp_path / 'run').exists()


def _nan_stage(directory, checkpoint_every):
  config = ml_collections.ConfigDict(dict(
      num_train_steps=4, learning_rate=1e-2, warmup_fraction=0.0,
      grad_clip=0.0, min_lr_fraction=0.0,
      group_learning_rates={}, stop_check_every=1, batch_size=4,
      log_every=2,
      checkpoint_every=checkpoint_every))

  def loss_fn(params, batch, frozen_params, rng):
    del frozen_params, rng
    recon = jnp.mean(jnp.square(params['w'] - batch['x']))
    # From step 3 on the data carries a NaN into the KL term only.
    kl = jnp.mean(batch['x']) * jnp.where(batch['x'][0, 0] >= 2, jnp.nan, 0)
    return recon + kl, {'recon_loss': recon, 'kl': kl}

  def batches(start_step):
    for step in itertools.count(start_step):
      yield {'x': np.full((4, 3), float(step), np.float32)}

  return Stage(name='toy', directory=str(directory), config=config,
               loss_fn=loss_fn,
               init_params=lambda rng: {'w': jnp.zeros(3, jnp.float32)},
               batches=batches)


def test_a_non_finite_loss_names_stage_step_and_term(tmp_path):
  mesh = Mesh(np.asarray(jax.devices()[:1]), ('data',))
  with pytest.raises(Diverged) as error:
    fit(_nan_stage(tmp_path / 'toy', checkpoint_every=2), mesh=mesh, seed=0)
  message = str(error.value)
  assert message.startswith('toy: the loss became nan at step 4 '
                            '(non-finite: kl)'), message
  assert 'last good checkpoint is step 2' in message and '\n' not in message
  assert checkpoint_lib.Checkpointer(
      str(tmp_path / 'toy' / 'checkpoints'), read_only=True
  ).all_steps() == [2]  # the diverged state of step 4 is not saved


# --------------------------------------------------------------------------
# 4. places that cannot be written
# --------------------------------------------------------------------------


def _under_a_file(tmp_path):
  """A path that cannot be created even by root: its parent is a file."""
  blocker = tmp_path / 'a_file'
  blocker.write_text('')
  return blocker / 'sub'


def test_an_unwritable_workdir_is_one_line(tmp_path):
  workdir = str(_under_a_file(tmp_path))
  with pytest.raises(UserError) as error:
    workdir_lock(Paths.of(workdir)).acquire()
  assert str(error.value) == (
      f'cannot write the workdir {workdir} (Not a directory); give a '
      '--workdir you can write')


@pytest.mark.parametrize('code', [errno.EROFS, errno.EACCES])
def test_a_read_only_or_forbidden_workdir_is_one_line(tmp_path, monkeypatch,
                                                      code):
  """A read-only filesystem and a folder without write permission (root
  ignores chmod, so the refusal is simulated at os.open)."""
  real_open = os.open

  def refusing_open(path, flags, *args):
    if str(path).startswith(str(tmp_path)) and flags & os.O_CREAT:
      raise OSError(code, os.strerror(code), path)
    return real_open(path, flags, *args)
  monkeypatch.setattr(os, 'open', refusing_open)
  with pytest.raises(UserError) as error:
    workdir_lock(Paths.of(str(tmp_path / 'run'))).acquire()
  assert os.strerror(code) in str(error.value)
  assert f'the workdir {tmp_path / "run"}' in str(error.value)


@pytest.mark.skipif(os.geteuid() == 0, reason='root ignores permissions')
def test_a_workdir_in_a_read_only_folder_is_one_line(tmp_path):
  parent = tmp_path / 'locked'
  parent.mkdir()
  parent.chmod(0o555)
  try:
    with pytest.raises(UserError, match='Permission denied'):
      workdir_lock(Paths.of(str(parent / 'run'))).acquire()
  finally:
    parent.chmod(0o755)


def test_an_unwritable_dataset_cache_is_one_line(tmp_path):
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  data_dir = _under_a_file(tmp_path)
  config.data.data_dir = str(data_dir)
  with pytest.raises(UserError) as error:
    pipeline_helpers.prepare_data(config)
  message = str(error.value)
  assert message.startswith('cannot write the synthetic dataset')
  assert str(data_dir) in message and 'SLOTFORMER_DATA_DIR' in message


def test_an_unwritable_converter_output_is_one_line(tmp_path, monkeypatch):
  class Converted:
    stage = 'savi'
    family = 'savi'
    extras = {}
  checkpoint = tmp_path / 'savi.pth'
  checkpoint.write_bytes(b'')
  monkeypatch.setattr(convert_official.pth_reader, 'read_state_dict',
                      lambda path, reader: {})
  monkeypatch.setattr(convert_official.families, 'convert_state_dict',
                      lambda state_dict, config: Converted())
  workdir = str(_under_a_file(tmp_path))
  config = pipeline_helpers.load_config('synthetic', 'tiny')
  with pytest.raises(UserError, match='cannot write the workdir'):
    convert_official.convert_files(config, workdir, [str(checkpoint)])


def test_the_lock_still_refuses_a_live_holder(tmp_path):
  lock = FileLock(str(tmp_path / 'lock'), what='the folder')
  lock.acquire()
  try:
    with pytest.raises(UserError, match='in use by process'):
      FileLock(str(tmp_path / 'lock'), what='the folder').acquire()
  finally:
    lock.release()


def test_an_unwritable_prepare_output_is_one_line(tmp_path, capsys):
  import dataset_fixtures as fx  # pylint: disable=g-import-not-at-top
  from slotformer_jax.datasets import obj3d  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import prepare  # pylint: disable=g-import-not-at-top
  for split in ('train', 'val', 'test'):
    for t in range(1, 7):
      fx.write_png(tmp_path / 'OBJ3D' / split / '0'
                   / obj3d.FRAME_TEMPLATE.format(t),
                   np.full((24, 24, 3), 9 * t, np.uint8))
  data_dir = _under_a_file(tmp_path)
  assert prepare.main([
      '--dataset=obj3d', f'--source={tmp_path / "OBJ3D"}',
      f'--data_dir={data_dir}', '--resolution=16', '--num_frames=4',
      '--num_workers=1', '--no_progress']) == 1
  lines = capsys.readouterr().err.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith(
      f'error: cannot write the dataset folder {data_dir}/obj3d'), lines
  assert '--data_dir' in lines[0]


def test_the_converter_reports_a_missing_config_in_one_line(tmp_path):
  env = dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS='cpu')
  env.pop('XLA_FLAGS', None)
  result = subprocess.run(
      [sys.executable, '-m', 'slotformer_jax.official.convert',
       '--config=nope.py', f'--workdir={tmp_path / "run"}',
       f'--checkpoint={tmp_path / "x.pth"}'], cwd=str(tmp_path), env=env,
      capture_output=True, text=True, timeout=300)
  line = _one_error_line(result)
  assert result.returncode == 2
  assert 'config file nope.py does not exist' in line


# --------------------------------------------------------------------------
# 5. lines that sent the user the wrong way (issue 38)
# --------------------------------------------------------------------------


def test_a_video_prediction_mode_on_a_task_config_names_its_config():
  # `--mode=explore` on a contact run once said "Task stages need a task
  # config, e.g. configs/synthetic_contact.py": the config it was given.
  from slotformer_jax import stages  # pylint: disable=g-import-not-at-top
  from slotformer_jax.errors import CommandLineError  # pylint: disable=g-import-not-at-top
  from slotformer_jax.run import Run  # pylint: disable=g-import-not-at-top
  run = Run.create(config_checks.load_config_file(
      os.path.join(CONFIGS, 'synthetic_contact.py')), '/nonexistent/run')
  with pytest.raises(CommandLineError) as error:
    stages.selected_stages(run, 'explore')
  line = str(error.value)
  assert '\n' not in line and 'synthetic_contact' not in line, line
  assert line.endswith('--mode=explore belongs to configs/synthetic.py.')


def test_a_first_run_that_made_nothing_keeps_no_settings(tmp_path,
                                                         monkeypatch):
  # A first run that stopped before any work (here: no questions where
  # vqa.questions_root points) kept its config.json, and the corrected
  # command was refused as a change of settings (--allow_config_change).
  import types  # pylint: disable=g-import-not-at-top
  from slotformer_jax import main as main_lib  # pylint: disable=g-import-not-at-top
  from slotformer_jax.run import Run  # pylint: disable=g-import-not-at-top
  monkeypatch.setattr(main_lib, '_ALLOW_CONFIG_CHANGE',
                      types.SimpleNamespace(value=False))
  config = pipeline_helpers.load_config('clevrer_vqa')
  workdir = tmp_path / 'run'
  workdir.mkdir()  # as taking the workdir's lock does

  def train_vqa(questions_root: str) -> str:
    config.vqa.questions_root = str(tmp_path / questions_root)
    with pytest.raises(UserError) as error:
      main_lib._run(Run.create(config, str(workdir)), ('train_vqa',))  # pylint: disable=protected-access
    return str(error.value)

  assert 'typo/questions/train.json not found' in train_vqa('typo')
  assert not (workdir / 'config.json').exists()
  # The corrected command is a first run too: it fails for want of the
  # questions, not for its settings.
  assert 'clevrer/questions/train.json not found' in train_vqa('clevrer')
  # A workdir that holds work keeps the settings it was made with.
  (workdir / 'vqa' / 'slots').mkdir(parents=True)
  (workdir / 'vqa' / 'slots' / 'train.npy').write_bytes(b'slots')
  train_vqa('clevrer')
  assert (workdir / 'config.json').exists()
  assert 'was run with other settings: vqa.questions_root' in train_vqa(
      'elsewhere')


def test_clevrer_without_test_videos_names_the_splits_flag(tmp_path,
                                                            capsys):
  # The test videos are only for VQA's test predictions, but converting
  # every split is the default: the line asked for videos/test and stopped.
  import dataset_fixtures as fx  # pylint: disable=g-import-not-at-top
  from slotformer_jax.data import prepare  # pylint: disable=g-import-not-at-top
  source = tmp_path / 'CLEVRER'
  fx.write_clevrer_video(source, 'train', 0, num_frames=4)
  fx.write_clevrer_video(source, 'val', 10000, num_frames=4)
  assert prepare.main([
      '--dataset=clevrer', f'--source={source}',
      f'--data_dir={tmp_path / "data"}', '--resolution=8', '--num_frames=4',
      '--masks=ignore', '--num_workers=1', '--no_progress']) == 1
  error = capsys.readouterr().err
  assert error.startswith(f'error: CLEVRER: {source}/videos/test not found'
                          ), error
  assert 'without them convert the others: --splits=train,val' in error
  assert not (tmp_path / 'data').exists()


def test_a_long_error_line_keeps_its_reason():
  """An error quoted in a one-line message keeps the end of a long first
  line, where tensorstore puts the reason after two paths: a full disk
  under a deep run folder once read '... Failed writing: "/tmp/pytest-o'."""
  path = '/a/deep/run/folder/' + 'x' * 300
  error = ValueError(f'RESOURCE_EXHAUSTED: Error writing local file "{path}":'
                     ' Failed to write 47768 bytes to file 8: No space left '
                     "on device [os_error_code='28']\nsecond line")
  line = errors.brief(error)
  assert line.startswith('ValueError: RESOURCE_EXHAUSTED: Error writing')
  assert line.endswith("No space left on device [os_error_code='28']")
  assert len(line) < 330 and 'second line' not in line
  assert errors.brief(KeyError('k')) == "KeyError: 'k'"


def test_video_prediction_on_a_physion_contact_run_names_the_way(tmp_path):
  """Issue 61, case 9: on a Physion contact run, `--mode=explore` pointed
  to configs/synthetic.py only, and the missing val slots of the contact
  run were to be extracted with the contact config, which extracts no val
  (rc 0). Now the line names the Physion video-prediction config reading
  this run's stage 1, and a run reading it names the splits it has."""
  from slotformer_jax import stages  # pylint: disable=g-import-not-at-top
  from slotformer_jax.errors import CommandLineError  # pylint: disable=g-import-not-at-top
  from slotformer_jax.run import Run  # pylint: disable=g-import-not-at-top
  run = Run.create(config_checks.load_config_file(
      os.path.join(CONFIGS, 'physion_contact.py')), '/nonexistent/run')
  with pytest.raises(CommandLineError) as error:
    stages.selected_stages(run, 'explore')
  line = str(error.value)
  assert '\n' not in line
  assert ('on this run\'s data and stage 1: a new --workdir with '
          '--config=configs/physion.py --config.stage1_workdir=/nonexistent/'
          'run.') in line, line
