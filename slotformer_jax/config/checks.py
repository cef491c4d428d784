"""Every check a config can fail, run before any work (data generation,
training), so a bad value costs seconds rather than a finished stage.

`check_overrides` turns an unknown `--config.a.b=...` into one line with the
nearest valid names; `validate` collects every problem of the stages a run
will execute into one `UserError`.
"""

from __future__ import annotations

import difflib
import importlib.util
import os
from collections.abc import Sequence

import ml_collections

from slotformer_jax import models
from slotformer_jax.errors import ConfigError

FRAME_METRICS = ('psnr', 'ssim', 'lpips')
OBJECT_METRICS = ('ari', 'fg_ari', 'fg_miou', 'ar')

_TRAINING_INTS = ('batch_size', 'num_train_steps', 'log_every',
                  'checkpoint_every')


def load_config_file(spec: str) -> ml_collections.ConfigDict:
  """'configs/synthetic.py:tiny' -> its get_config('tiny') (as absl does)."""
  path, _, argument = spec.partition(':')
  module_spec = importlib.util.spec_from_file_location(
      '_checked_config', os.path.expanduser(path))
  module = importlib.util.module_from_spec(module_spec)
  module_spec.loader.exec_module(module)
  return module.get_config(argument) if argument else module.get_config()


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


def check_overrides(argv: Sequence[str]) -> str | None:
  """The first unknown `--config.<field>` of the command line, as one line
  (None when all are known or the config file cannot be loaded here)."""
  spec = None
  for arg in argv:
    if arg.startswith('--config='):
      spec = arg[len('--config='):]
  if spec is None:
    return None
  try:
    config = load_config_file(spec)
  except Exception:  # pylint: disable=broad-except
    return None  # absl reports it
  for arg in argv:
    if arg.startswith('--config.'):
      dotted = arg[len('--config.'):].split('=', 1)[0]
      problem = unknown_override(config, dotted)
      if problem:
        return problem
  return None


def _video_length(config: ml_collections.ConfigDict, split: str
                  ) -> int | None:
  """Frames per video when known without generating data: the synthetic
  config's value, or the first video of an already converted dataset."""
  if config.data.name == 'synthetic':
    return int(config.data.get('num_frames', 40))
  try:
    # Imported here: reading needs tensorflow_datasets.
    from slotformer_jax.data import sources  # pylint: disable=g-import-not-at-top
    source = sources.get_video_source(config.data, split)
    return len(source[0]['video']) if len(source) else None
  except Exception:  # pylint: disable=broad-except
    return None  # a missing dataset is reported by the stage with its fix


def validate(config: ml_collections.ConfigDict, stages: Sequence[str], *,
             num_devices: int, num_processes: int = 1) -> None:
  """Raises one UserError listing every problem of `stages` (main's modes)."""
  problems = []

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
  if config.slot_model not in ('savi', 'steve'):
    problems.append(
        f"slot_model must be 'savi' (incl. stochastic SAVi) or 'steve', got "
        f'{config.slot_model!r}')
  if config.slot_model == 'steve':
    for section in ('dvae', 'steve'):
      if 'train_' + section in stages:
        positive(section, _TRAINING_INTS)
        divisible(f'{section}.batch_size', config[section].batch_size)
  positive('savi', ('num_slots', 'slot_size', 'clip_length'))
  positive('data', ('max_instances',))
  if 'train_savi' in stages:
    positive('savi', _TRAINING_INTS)
    divisible('savi.batch_size', config.savi.batch_size)
  if 'extract_slots' in stages:
    positive('extraction', ('batch_size', 'chunk_length'))
    divisible('extraction.batch_size', config.extraction.batch_size)
  dynamics = [models.SLOTFORMER] + (
      [models.SLOT_LSTM] if config.slot_lstm.train else [])
  for name in dynamics:
    if f'train_{name}' in stages or stages & {'evaluate', 'render',
                                                'explore'}:
      section = models.dynamics_config(config, name)
      for key in ('burn_in', 'rollout', 'frame_stride', 'embed_dim',
                  'num_layers') + (_TRAINING_INTS if f'train_{name}' in stages
                                   else ()):
        value = section.get(key)
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
    unknown = [m for m in config.evaluation.metrics
               if m not in FRAME_METRICS + OBJECT_METRICS]
    if unknown:
      problems.append(
          f'unknown evaluation.metrics {unknown}; known: '
          f'{", ".join(FRAME_METRICS + OBJECT_METRICS)}')
    if config.evaluation.clips not in ('first', 'clevrer'):
      problems.append("evaluation.clips must be 'first' or 'clevrer', got "
                      f'{config.evaluation.clips!r}')
  if 'render' in stages:
    positive('render', ('num_videos', 'fps', 'scale', 'strip_every'))
  if 'explore' in stages:
    positive('explore', ('num_videos', 'fps', 'scale'))

  if not problems:  # lengths need the integers above to be sane
    _check_lengths(config, stages, dynamics, problems)
  if problems:
    raise ConfigError('config: ' + '; '.join(problems))


def _check_lengths(config, stages, dynamics, problems) -> None:
  train_length = _video_length(config, 'train') if stages & {
      'train_savi', 'train_slotformer', 'train_slot_lstm'} else None
  if train_length is not None:
    if 'train_savi' in stages and config.savi.clip_length > train_length:
      problems.append(f'savi.clip_length={config.savi.clip_length} is longer '
                      f'than the {train_length}-frame videos')
    for name in dynamics:
      section = models.dynamics_config(config, name)
      needed = (section.burn_in + section.rollout - 1) * section.frame_stride + 1
      if f'train_{name}' in stages and needed > train_length:
        problems.append(
            f'{name}: burn_in {section.burn_in} + rollout {section.rollout} '
            f'(stride {section.frame_stride}) needs {needed} frames, the '
            f'videos have {train_length}')
  if stages & {'evaluate', 'render', 'explore'}:
    length = _video_length(config, config.evaluation.split)
    section = config.slotformer
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
