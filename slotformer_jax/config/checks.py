"""Every check a config can fail, run before any work (data generation,
training), so a bad value costs seconds rather than a finished stage.

`check_overrides` turns an unknown `--config.a.b=...` into one line with the
nearest valid names; `validate` collects every problem of the stages a run
will execute into one `UserError`.
"""

from __future__ import annotations

import difflib
import importlib.util
import inspect
import math
import os
import re
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import ml_collections

from slotformer_jax.config import defaults
from slotformer_jax.config.defaults import CHOICES
from slotformer_jax.config.sections import DYNAMICS
from slotformer_jax.config.sections import dynamics_section
from slotformer_jax.config.sections import dynamics_stages
from slotformer_jax.config.sections import primary_dynamics
from slotformer_jax.config.sections import trained_dynamics
from slotformer_jax.errors import ConfigError

# Every section builder declares its fields' choices (`defaults.one_of`)
# when it runs: run them all once, so that a config read back from a
# workdir is checked as one built from a config file.
for _build in (defaults.base_config, defaults.vqa_config,
               defaults.contact_readout_config,
               defaults.planning_readout_config):
  _build()

_TRAINING_INTS = ('batch_size', 'num_train_steps', 'log_every',
                  'checkpoint_every')


class ConfigFileError(ConfigError):
  """The --config argument names no loadable config (a missing file, a
  variant the file does not have): a mistake of the command line."""


# The configs the package ships (setup.py installs configs/ as this
# package): `--config=configs/<name>.py` finds them from any folder.
SHIPPED_CONFIGS = 'slotformer_jax.configs'


def shipped_config(spec: str) -> str:
  """A --config value as a file: itself when it exists, else the shipped
  config of its name (`configs/synthetic.py:tiny` after a `pip install .`,
  run from any folder); unchanged when there is none."""
  path, colon, argument = spec.partition(':')
  if (not path.endswith('.py') or os.path.isfile(os.path.expanduser(path))
      or os.path.basename(os.path.dirname(path)) not in ('', 'configs')):
    return spec
  try:
    found = importlib.util.find_spec(SHIPPED_CONFIGS)
  except ImportError:
    found = None
  for folder in (found.submodule_search_locations or ()) if found else ():
    candidate = os.path.join(folder, os.path.basename(path))
    if os.path.isfile(candidate):
      return candidate + colon + argument
  return spec


def load_config_file(spec: str) -> ml_collections.ConfigDict:
  """'configs/synthetic.py:tiny' -> its get_config('tiny') (as absl does).

  Every way this can fail is one ConfigError naming the file (and line):
  ConfigFileError for the command line's part (no such file, a variant the
  file does not take), ConfigError for the file's (a syntax error, a
  get_config that raises).
  """
  path, colon, argument = shipped_config(spec).partition(':')
  expanded = os.path.expanduser(path)
  if not path:
    raise ConfigFileError('--config is empty; give a config file, e.g. '
                          '--config=configs/synthetic.py:tiny')
  if not os.path.isfile(expanded):
    what = 'is a folder' if os.path.isdir(expanded) else 'does not exist'
    raise ConfigFileError(
        f'config file {path} {what} (from {os.getcwd()}); e.g. '
        '--config=configs/synthetic.py:tiny')
  module_spec = importlib.util.spec_from_file_location(
      '_checked_config', expanded)
  if module_spec is None:
    raise ConfigFileError(f'config file {path} is not a Python file (.py)')
  module = importlib.util.module_from_spec(module_spec)
  try:
    module_spec.loader.exec_module(module)
  except SyntaxError as error:
    raise ConfigError(
        f'config file {path}, line {error.lineno}: {error.msg}') from None
  except Exception as error:  # pylint: disable=broad-except
    raise ConfigError(f'config file {path}, line {_error_line(error, expanded)}'
                      f': {_describe(error)}') from None
  get_config = getattr(module, 'get_config', None)
  if not callable(get_config):
    raise ConfigError(f'config file {path} defines no get_config()')
  if colon and not _takes_an_argument(get_config):
    raise ConfigFileError(
        f'config file {path} has no variants; drop ":{argument}"')
  try:
    return get_config(argument) if colon else get_config()
  except Exception as error:  # pylint: disable=broad-except
    call = f'get_config({argument!r})' if colon else 'get_config()'
    if 'variant' in str(error) and colon:
      raise ConfigFileError(
          f'config file {path}: {" ".join(str(error).split())}') from None
    raise ConfigError(
        f'config file {path}, line {_error_line(error, expanded)}: {call} '
        f'failed: {_describe(error)}') from None


def _takes_an_argument(function) -> bool:
  try:
    parameters = inspect.signature(function).parameters.values()
  except (TypeError, ValueError):
    return True
  return any(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD,
                        p.VAR_POSITIONAL) for p in parameters)


def _error_line(error: BaseException, path: str) -> int | str:
  """The line of `path` where `error` was raised last (deepest frame)."""
  line = '?'
  for frame in traceback.extract_tb(error.__traceback__):
    if os.path.abspath(frame.filename) == os.path.abspath(path):
      line = frame.lineno
  return line


def _describe(error: BaseException) -> str:
  message = ' '.join(str(error).split())
  return f'{type(error).__name__}: {message}' if message else \
      type(error).__name__


def unknown_override(config: ml_collections.ConfigDict, dotted: str
                     ) -> str | None:
  """None if `dotted` (e.g. 'savi.foo') names a field of `config`, else one
  line naming it and the nearest valid names."""
  node, walked = config, []
  for part in dotted.split('.'):
    keys = list(node.keys()) if isinstance(node, ml_collections.ConfigDict) \
        else []
    if part not in keys:
      where = '.'.join(walked) or 'the config'
      near = difflib.get_close_matches(part, keys, n=3, cutoff=0.5)
      prefix = '.'.join(walked) + '.' if walked else ''
      hint = (f'did you mean {", ".join(prefix + n for n in near)}?' if near
              else f'valid names there: {", ".join(sorted(keys)[:12])}')
      return f'unknown config field {dotted!r} (no {part!r} in {where}); {hint}'
    node = node[part]
    walked.append(part)
  return None


def config_spec(argv: Sequence[str]) -> str | None:
  """The value of the command line's last --config (either form)."""
  spec = None
  for i, arg in enumerate(argv):
    if arg.startswith('--config='):
      spec = arg[len('--config='):]
    elif arg == '--config' and i + 1 < len(argv):
      spec = argv[i + 1]
  return spec


def check_overrides(argv: Sequence[str]) -> str | None:
  """The first unknown `--config.<field>` of the command line, as one line
  (None when all are known or there is no --config). A config file that
  cannot be loaded raises its ConfigError (see `load_config_file`)."""
  spec = config_spec(argv)
  if spec is None:
    return None
  config = load_config_file(spec)
  for arg in argv:
    if arg.startswith('--config.'):
      dotted = arg[len('--config.'):].split('=', 1)[0]
      problem = unknown_override(config, dotted)
      if problem:
        return problem
  return None


# One rule per kind of field, by name (the last part of its dotted path):
# every config section is checked by the same table, so a new
# `foo_learning_rate` or `bar_batch_size` is covered without a new check.
# (pattern, kind, lowest, highest, describes)
_FIELD_KINDS = (
    (r'(^|_)learning_rate$|^group_learning_rates\.', 'float', 0.0, None,
     'a learning rate > 0'),
    (r'_fraction$|_share$|^positive_ratio$', 'float', 0.0, 1.0, 'a fraction in [0, 1]'),
    (r'dropout_rate$', 'float', 0.0, 1.0, 'a rate in [0, 1)'),
    (r'(^|_)weight$|^grad_clip$', 'float', 0.0, None, 'a number >= 0'),
    (r'epsilon$|^prior_sigma$|^gumbel_(start|final)$|_seconds$|'
     r'^object_scale$', 'float', 0.0, None, 'a number > 0'),
    # Aloe draws no question of a kind whose batch is 0 (open-only or
    # choice-only training); one must be > 0 (`validate`).
    (r'^vqa\.(open|choice)_batch_size$', 'int', 0, None, 'an integer >= 0'),
    # SAVi's encoder has no Transformer with 0 layers (the default).
    (r'^transformer\.num_layers$', 'int', 0, None, 'an integer >= 0'),
    # A folder of videos resampled to this rate (datasets/videos.py states
    # the same rule); before the int rule that `render.fps` follows.
    (r'^data\.fps$', 'float', 0.0, 1000.0,
     "a frame rate in [0, 1000] (0: the file's own)"),
    (r'batch_size$|_every$|^num_(slots|layers|heads|iterations|train_steps|'
     r'frames|candidates)$|^(slot|mlp|hidden|vocab|output|head|word|qkv)_size$|'
     r'^(embed_dim|d_model|kernel_size|chunk_length|clip_length|burn_in|'
     r'rollout|frame_stride|mlp_ratio|epochs|fps|scale|strip_every|'
     r'rollout_steps|video_length|observed_frames|predicted_frames|'
     r'rollout_frames|max_question_len|max_choice_len|max_choices|'
     r'max_instances)$', 'int', 1, None, 'an integer >= 1'),
    (r'^(lstm_size|max_context|num_videos|num_val|num_test|video_len|'
     r'dynamics_layouts|reader_workers)$', 'int', 0, None, 'an integer >= 0'),
    (r'^(features|strides|resolution|broadcast_resolution)$', 'ints', 1, None,
     'integers >= 1'),
)
# A rate or fraction of exactly its lowest value that cannot work.
_EXCLUSIVE_LOWEST = ('a learning rate > 0', 'a number > 0')


def _leaves(config, prefix=''):
  for key in config.keys():
    value = config[key]
    if isinstance(value, ml_collections.ConfigDict):
      yield from _leaves(value, f'{prefix}{key}.')
    else:
      yield f'{prefix}{key}', value


def _is_number(value) -> bool:
  return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_field_kinds(config: ml_collections.ConfigDict) -> list[str]:
  """One line per field whose value its kind (`_FIELD_KINDS`) rules out:
  a rate <= 0, a negative clip norm or loss weight, a size < 1, a NaN ..."""
  problems = []
  for dotted, value in _leaves(config):
    if value is None:  # an unset placeholder: its default applies
      continue
    parts = dotted.split('.')
    name = parts[-1]
    scoped = '.'.join(parts[-2:])
    for pattern, kind, lowest, highest, describes in _FIELD_KINDS:
      if not (re.search(pattern, name) or re.search(pattern, scoped)):
        continue
      if kind == 'int':
        good = (isinstance(value, int) and not isinstance(value, bool)
                and value >= lowest)
        if not good:
          problems.append(f'{dotted} must be an integer >= {lowest}, got '
                          f'{value!r}')
      elif kind == 'ints':
        items = value if isinstance(value, (tuple, list)) else (value,)
        good = all(isinstance(v, int) and not isinstance(v, bool)
                   and v >= lowest for v in items)
        if not good:
          problems.append(f'{dotted} must be {describes}, got {value!r}')
      else:
        good = _is_number(value) and math.isfinite(value) and (
            value > lowest if describes in _EXCLUSIVE_LOWEST
            else value >= lowest)
        if good and highest is not None:
          good = (value < highest if describes == 'a rate in [0, 1)'
                  else value <= highest)
        if not good:
          problems.append(f'{dotted} must be {describes}, got {value!r}')
      break
  return problems


# Tuple-valued fields, by name (as `_FIELD_KINDS`): how many entries each
# must have (None: any number). A single value where a tuple is meant
# (`features = 64` in a config file), or an (H, W) of another length
# (`--config.data.resolution=32` arrives as (32,)), failed where the field
# was first used, in a traceback.
_FIELD_SHAPES = (
    (r'^(resolution|broadcast_resolution)$', 2, '(H, W): a tuple of 2'),
    (r'^(encoder|decoder)\.(features|strides)$|^evaluation\.metrics$|'
     r'^extraction\.splits$|^readout\.(seeds|conditions|selected_steps)$',
     None, 'a tuple'),
)


def check_field_shapes(config: ml_collections.ConfigDict) -> list[str]:
  """One line per tuple field of the wrong shape (`_FIELD_SHAPES`), and
  per encoder whose strides and features differ in length (one stride per
  layer)."""
  problems = []
  for dotted, value in _leaves(config):
    if value is None:  # an unset placeholder: its default applies
      continue
    parts = dotted.split('.')
    for pattern, length, describes in _FIELD_SHAPES:
      if not (re.search(pattern, parts[-1])
              or re.search(pattern, '.'.join(parts[-2:]))):
        continue
      if not isinstance(value, (tuple, list)) or (
          length is not None and len(value) != length):
        problems.append(f'{dotted} must be {describes}, got {value!r}')
      break
    if parts[-1] == 'strides' and isinstance(value, (tuple, list)):
      section = config
      for part in parts[:-1]:
        section = section[part]
      features = section.get('features')
      if isinstance(features, (tuple, list)) and len(features) != len(
          value):
        where = '.'.join(parts[:-1])
        problems.append(
            f'{where}.strides {tuple(value)!r} and {where}.features '
            f'{tuple(features)!r} must have one entry per layer each')
  return problems


def validate(config: ml_collections.ConfigDict, stages: Sequence[str], *,
             num_devices: int, num_processes: int = 1,
             slot_model_problems: Callable[[], Sequence[str]] | Sequence[
                 str] = (),
             data_problems: Sequence[str] = (),
             dataset_splits: Sequence[str] = (),
             task_seeded: Sequence[str] = (),
             task_splits: Sequence[tuple[str, str]] = (),
             video_length: Callable[[str], int | None] = lambda split: None
             ) -> None:
  """Raises one UserError listing every problem of `stages` (main's modes).

  Args:
    slot_model_problems: the slot model's own (`SlotModel.check_config`),
      or a function giving them: called only once the fields have their
      kinds and shapes (a decoder size check needs an (H, W)).
    data_problems: those of `config.data` and `evaluation.clips`, which the
      dataset knows (`datasets.config_problems`).
    dataset_splits: the splits the dataset has (`Dataset.splits`; empty:
      not known), which every split the stages read must be.
    task_seeded: the task's stages that take several seeds (`Task.seeded`).
    task_splits: (field, split) of the data splits the task's stages read
      (`Task.reads`), each of which must be extracted and the dataset's.
    video_length: split -> frames per video when known without making data
      (None: unknown, checked later by the stage that reads them).
  """
  problems = list(data_problems)

  def positive(section: str, names: Sequence[str], allow_zero=()) -> None:
    node = config
    for part in section.split('.'):
      node = node[part]
    for name in names:
      value = node.get(name)
      lowest = 0 if name in allow_zero else 1
      if not isinstance(value, int) or isinstance(value, bool) or (
          value < lowest):
        problems.append(f'{section}.{name} must be an integer >= {lowest}, '
                        f'got {value!r}')

  def divisible(name: str, value) -> None:
    if isinstance(value, int) and value > 0 and value % num_devices:
      problems.append(
          f'{name}={value} does not split over the {num_devices} devices; '
          f'use a multiple of {num_devices}')
    elif isinstance(value, int) and value > 0 and value % num_processes:
      problems.append(f'{name}={value} does not split over the '
                      f'{num_processes} processes')

  stages = set(stages)
  dynamics = trained_dynamics(config)
  # Every part trained here by steps (`train_<section>`: stage 1, Aloe):
  # its section's training integers, and a batch that splits over the
  # devices. A task's readout (`train_readout`) trains by epochs: its
  # fields are checked by their kinds.
  for stage in sorted(stages):
    section = stage[len('train_'):]
    if (stage.startswith('train_') and section not in DYNAMICS
        and isinstance(config.get(section), ml_collections.ConfigDict)
        and 'num_train_steps' in config[section]):
      if section == 'vqa':  # one batch per kind of question
        positive(section, _TRAINING_INTS[1:])
        _check_vqa_batches(config.vqa, problems, divisible)
      else:
        positive(section, _TRAINING_INTS)
        divisible(f'{section}.batch_size', config[section].batch_size)
  if 'evaluate_vqa' in stages:
    divisible('vqa.eval_batch_size', config.vqa.eval_batch_size)
  positive('savi', ('num_slots', 'slot_size', 'clip_length'))
  positive('data', ('max_instances',))
  if 'extract_slots' in stages:
    positive('extraction', ('batch_size', 'chunk_length'))
    divisible('extraction.batch_size', config.extraction.batch_size)
  for name in dynamics:
    if f'train_{name}' in stages or stages & {'evaluate', 'render',
                                                'explore'}:
      section = dynamics_section(config, name)
      for key in ('burn_in', 'rollout', 'frame_stride', 'embed_dim',
                  'num_layers') + (_TRAINING_INTS if f'train_{name}' in stages
                                   else ()):
        value = section[key]
        if not isinstance(value, int) or value < 1:
          problems.append(f'{name}.{key} must be an integer >= 1, got '
                          f'{value!r}')
      if f'train_{name}' in stages:
        divisible(f'{name}.batch_size', section.batch_size)
  evaluating = bool(stages & {'evaluate', 'render', 'explore'})
  if evaluating:
    positive('evaluation', ('batch_size', 'rollout_steps', 'chunk_length'))
    positive('evaluation', ('num_videos',), allow_zero=('num_videos',))
    if 'evaluate' in stages:
      divisible('evaluation.batch_size', config.evaluation.batch_size)
  if 'render' in stages:
    positive('render', ('num_videos', 'fps', 'scale', 'strip_every'))
  if 'explore' in stages:
    positive('explore', ('num_videos', 'fps', 'scale'))

  problems.extend(choice_problems(config))
  targets = (config.savi.get('targets') if 'savi' in config else None)
  if isinstance(targets, (tuple, list)) and not targets:
    problems.append("savi.targets names no target; give one or more, e.g. "
                    "('rgb',)")
  problems.extend(seeds_problems(config, stages, task_seeded))
  if stages & {'train_vqa', 'evaluate_vqa'} and 'vqa' in config:
    problems.extend(_aloe_seed_problems(config))
  problems.extend(check_field_kinds(config))
  problems.extend(check_field_shapes(config))
  problems[:] = list(dict.fromkeys(problems))  # the same line from two checks
  _check_splits(config, task_splits, problems, dataset_splits)
  if not problems:  # sizes and lengths need the integers above to be sane
    problems.extend(slot_model_problems() if callable(slot_model_problems)
                    else slot_model_problems)
    _check_lengths(config, stages, dynamics, problems, video_length)
  if problems:
    raise ConfigError('config: ' + '; '.join(problems))


# The stages that take several seeds (config.seeds): stage 1's first part
# (no parent, no derived input) of any slot model, and the chain after it
# of SAVi and STEVE, seed s on stage-1 seed s (docs/seeds.md), with the
# readouts of every task (contact, planning on either layout) and Aloe
# (task model s on chain s).
SEEDED_STAGES = ('train_savi', 'train_dvae')
# The slot model's stages after its first part; extraction and the
# dynamics models' training follow (`seeded_stages`).
SEEDED_CHAINS = {'savi': (), 'steve': ('tokenize_frames', 'train_steve')}
# Stages that do no training or extraction of their own with the seeds.
_SEED_FREE_STAGES = ('prepare_data',)


def seeded_stages(slot_model: str, task_seeded: Sequence[str] = (),
                  dynamics: Sequence[str] = ()) -> tuple[str, ...]:
  """The stages that take several seeds with `slot_model`, whose task's
  seeded stages are `task_seeded` (`Task.seeded`; they follow the chain),
  with the training stages `dynamics` of the dynamics models
  (`sections.dynamics_stages`)."""
  chain = (SEEDED_CHAINS[slot_model] + ('extract_slots', *dynamics)
           if slot_model in SEEDED_CHAINS else ())
  return SEEDED_STAGES + chain + (tuple(task_seeded) if chain else ())


def _listed(values: Sequence[Any]) -> str:
  return ', '.join(repr(v) for v in values)


def choice_problems(config: ml_collections.ConfigDict,
                    fields: Sequence[str] | None = None) -> list[str]:
  """One line per field of `config` (or of `fields`) with a fixed set of
  values (`defaults.CHOICES`) that holds another value; a tuple field may
  hold any of them, each once."""
  problems = []
  for field in fields if fields is not None else sorted(CHOICES):
    node, *path = config, *field.split('.')
    for key in path:
      node = node.get(key) if isinstance(node, ml_collections.ConfigDict) \
          else None
    if node is None:
      continue  # a section this config has not got
    values = CHOICES[field]
    if isinstance(node, (tuple, list)):
      unknown = [v for v in node if v not in values]
      if unknown or len(set(node)) != len(node):
        problems.append(f'{field}={tuple(node)!r}: each must be one of '
                        f'{_listed(values)}, once')
    elif node not in values:
      problems.append(f'{field} must be one of {_listed(values)}, got '
                      f'{node!r}')
  return problems


# The largest seed: jax's PRNG keys of 32-bit ints (2**32 is the key of 0,
# silently), an int32 array of the seeds of a several-seed run, and a
# dynamics model drawing with its chain's seed + 1.
MAX_SEED = 2**31 - 2


def _is_seed(value: Any) -> bool:
  return (isinstance(value, int) and not isinstance(value, bool)
          and 0 <= value <= MAX_SEED)


def seeds_problems(config: ml_collections.ConfigDict,
                   stages: Sequence[str],
                   task_seeded: Sequence[str] = ()) -> list[str]:
  """One line per bad `seeds` / `seed_data_order` / `on_seed_divergence` /
  `seed_axis` / `seed_loop`, and one naming the stages of `stages` that do
  not take several seeds yet (or the setting that keeps them from it)."""
  seeds = config.seeds
  problems = []
  if not _is_seed(config.seed):
    problems.append(f'seed must be an integer in [0, {MAX_SEED}] (what a '
                    f'jax PRNG key holds), got {config.seed!r}')
  if seeds is not None:
    if not isinstance(seeds, (tuple, list)) or not seeds:
      problems.append(f'seeds must be a non-empty tuple of ints, e.g. '
                      f'(0, 1, 2), got {seeds!r}')
    elif not all(_is_seed(s) for s in seeds):
      problems.append(f'seeds must be integers in [0, {MAX_SEED}] (what a '
                      f'jax PRNG key holds), got {tuple(seeds)!r}')
    elif len(set(seeds)) != len(seeds):
      duplicates = sorted({s for s in seeds if list(seeds).count(s) > 1})
      problems.append(f'seeds must be distinct, got {tuple(seeds)!r} '
                      f'({", ".join(map(str, duplicates))} repeated)')
  problems.extend(choice_problems(config, (
      'seed_data_order', 'on_seed_divergence', 'seed_loop')))
  if not isinstance(config.seed_axis, bool):
    problems.append(f'seed_axis must be True or False, got '
                    f'{config.seed_axis!r}')
  if problems or seeds is None or len(seeds) < 2:
    return problems
  seeded = seeded_stages(config.slot_model, task_seeded,
                         dynamics_stages(config))
  refused = sorted(s for s in stages
                   if s not in seeded + _SEED_FREE_STAGES)
  if refused:
    problems.append(
        f'seeds={tuple(seeds)} trains several seeds in '
        f'{", ".join(seeded)} only for now (slot_model='
        f'{config.slot_model!r}; docs/seeds.md); {", ".join(refused)} '
        f'{"does" if len(refused) == 1 else "do"} not take several seeds '
        'yet (their per-seed inputs and outputs are not built): run them '
        'with one seed (--config.seed=<s>, no --config.seeds)')
  return problems


def _aloe_seed_problems(config: ml_collections.ConfigDict) -> list[str]:
  """Aloe draws with run seed * 1000 + vqa.seed (`stages.vqa.aloe_seed`):
  a seed too, so in range, and vqa.seed below 1000 keeps runs apart."""
  value = config.vqa.get('seed')
  if not (isinstance(value, int) and not isinstance(value, bool)
          and 0 <= value < 1000):
    return [f'vqa.seed must be an integer in [0, 999], got {value!r}']
  runs = config.seeds if isinstance(config.seeds, (tuple, list)) else (
      config.seed,)
  largest = max((s for s in runs if _is_seed(s)), default=0)
  if largest * 1000 + value > MAX_SEED:
    return [f'seed {largest} is too large for Aloe, which draws with seed '
            f'* 1000 + vqa.seed (at most {MAX_SEED}): give seeds up to '
            f'{(MAX_SEED - value) // 1000}']
  return []


def _check_vqa_batches(vqa: ml_collections.ConfigDict, problems: list[str],
                       divisible: Callable[[str, Any], None]) -> None:
  """Aloe's two batches: each an integer >= 0 (0: that kind of question is
  not drawn), not both 0, each split over the devices."""
  sizes = {f'vqa.{name}': vqa[name]
           for name in ('open_batch_size', 'choice_batch_size')}
  for name, size in sizes.items():
    if not isinstance(size, int) or isinstance(size, bool) or size < 0:
      problems.append(f'{name} must be an integer >= 0, got {size!r}')
      return
    divisible(name, size)
  if not any(sizes.values()):
    problems.append('vqa.open_batch_size and vqa.choice_batch_size are both '
                    '0: Aloe would train on nothing; give one kind of '
                    'question a batch')


def _check_splits(config: ml_collections.ConfigDict,
                  task_splits: Sequence[tuple[str, str]],
                  problems: list[str],
                  dataset_splits: Sequence[str] = ()) -> None:
  """The splits the stages read must be the dataset's, and those the task
  reads ones whose slots are extracted: before, evaluation.split='valid'
  was accepted, three stages trained, and evaluation then asked, forever,
  for slots that the extraction (of extraction.splits only) never makes."""
  extracted = tuple(config.extraction.splits)
  for field, split in task_splits:
    if split not in extracted:
      problems.append(
          f'{field}={split!r} is not one of the splits whose slots are '
          f'extracted (extraction.splits: {", ".join(extracted)}); use one '
          'of them, or add it to extraction.splits if the dataset has it')
  if not dataset_splits:
    return
  read = [(f'extraction.splits[{i}]', split)
          for i, split in enumerate(extracted)] + list(task_splits)
  for field, split in read:
    if split not in dataset_splits:
      problems.append(f'{field}={split!r} is not a split of '
                      f'{config.data.name} (it has '
                      f'{", ".join(dataset_splits)})')


def _check_lengths(config, stages, dynamics, problems, video_length) -> None:
  train_length = video_length('train') if stages & {
      'train_savi', *dynamics_stages(config)} else None
  if train_length is not None:
    if 'train_savi' in stages and config.savi.clip_length > train_length:
      problems.append(f'savi.clip_length={config.savi.clip_length} is longer '
                      f'than the {train_length}-frame videos')
    for name in dynamics:
      section = dynamics_section(config, name)
      needed = (section.burn_in + section.rollout - 1) * section.frame_stride + 1
      if f'train_{name}' in stages and needed > train_length:
        problems.append(
            f'{name}: burn_in {section.burn_in} + rollout {section.rollout} '
            f'(stride {section.frame_stride}) needs {needed} frames, the '
            f'videos have {train_length}')
  if stages & {'evaluate', 'render', 'explore'}:
    length = video_length(config.evaluation.split)
    section = dynamics_section(config, primary_dynamics(config))
    needed = ((section.burn_in + config.evaluation.rollout_steps - 1)
              * section.frame_stride + 1)
    if length is not None and needed > length:
      problems.append(
          f'evaluation needs {needed} frames per video (burn-in '
          f'{section.burn_in} + evaluation.rollout_steps '
          f'{config.evaluation.rollout_steps}, stride '
          f'{section.frame_stride}), the videos have {length}; lower '
          f'evaluation.rollout_steps to at most '
          f'{(length - 1) // section.frame_stride + 1 - section.burn_in}')
