"""SAVi (and stochastic SAVi) as the slot model: `config.slot_model='savi'`.

Stage 1 is one stage, `train_savi`: frame reconstruction (+ the KL of
stochastic SAVi) on clips of `savi.clip_length` frames. Slots decode through
SAVi's spatial-broadcast decoder, whose per-slot alpha masks are the
segmentation and whose frozen copy gives SlotFormer's image loss L_I.

Workdir (inside the stage-1 workdir)::

    savi/checkpoints/<step>/   savi/identity.json (parent: null)
    savi/model_config.json     savi/train_log.jsonl
    slots/<split>/             meta 'parent' = SAVi run id + step
"""

from __future__ import annotations

import functools
import json
import os
from typing import Any

import jax
from jax.sharding import Mesh
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotformer_jax import inference
from slotformer_jax import losses
from slotformer_jax import models
from slotformer_jax import workdir as workdir_lib
from slotformer_jax.data import pipeline
from slotformer_jax.data.sources import get_video_source
from slotformer_jax.errors import ConfigError
from slotformer_jax.frames import frames_to_model
from slotformer_jax.frames import model_to_unit
from slotformer_jax.modules import initializers
from slotformer_jax.modules import slot_init
from slotformer_jax.modules.savi import SAVi
from slotformer_jax.slot_models.base import Decoded
from slotformer_jax.slot_models.base import Loaded
from slotformer_jax.slot_models.base import SlotModel
from slotformer_jax.slot_models.base import uses_foreign_stage1
from slotformer_jax.runtime import precision
from slotformer_jax.runtime import sharding
from slotformer_jax.evaluation.visualize import mask_overlay
from slotformer_jax.train import steps
from slotformer_jax.train import summaries
from slotformer_jax.train.trainer import Stage
from slotformer_jax.train.trainer import fit_stage

NAME = 'savi'


def savi_dir(workdir: str) -> str:
  return os.path.join(workdir, NAME)


def model_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """The config values that determine SAVi's parameter shapes / behaviour."""
  savi = config.savi.to_dict()
  fields = {key: savi[key] for key in (
      'num_slots', 'slot_size', 'encoder', 'slot_attention', 'predictor',
      'decoder', 'stochastic', 'initial_slots', 'posterior_head',
      'layer_norm_epsilon')}
  fields['resolution'] = list(config.data.resolution)
  # A SAVi that saw BGR frames (the official CLEVRER ones) needs
  # BGR frames; recorded only when not RGB, so older workdirs still match.
  channel_order = config.data.get('channel_order', 'rgb')
  if channel_order != 'rgb':
    fields['channel_order'] = channel_order
  return json.loads(json.dumps(fields))  # tuples -> lists, for comparison


def identity_fields(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """Everything that shapes SAVi's parameters: data, the savi section, seed."""
  return workdir_lib.stage_identity_fields(config, NAME)


def _example_clip(config: ml_collections.ConfigDict) -> jax.Array:
  return jnp.zeros((1, config.savi.clip_length, *config.data.resolution, 3),
                   jnp.float32)


def is_conditional(config: ml_collections.ConfigDict) -> bool:
  """Conditional SAVi: slots start from the first frame's boxes / points."""
  return config.savi.initial_slots in slot_init.CONDITIONAL


def _example_inputs(config: ml_collections.ConfigDict) -> dict[str, Any]:
  """Keyword inputs besides the clip that `SAVi.init` needs (the shapes of
  the conditional initialiser do not depend on the number of box rows)."""
  if not is_conditional(config):
    return {}
  return {'boxes': jnp.zeros((1, config.savi.num_slots - 1, 4), jnp.float32)}


def check_conditioning(config: ml_collections.ConfigDict, source: Any,
                       split: str) -> None:
  """Conditional SAVi needs boxes in the data and a slot per box row plus
  the background slot."""
  if not is_conditional(config) or not len(source):
    return
  item = source[0]
  option = f'savi.initial_slots={config.savi.initial_slots!r}'
  if 'boxes' not in item:
    raise ConfigError(
        f'{option} conditions the slots on boxes, but the {split} videos of '
        f'data.name={config.data.name!r} have none; use '
        "--config.savi.initial_slots=learned")
  rows = item['boxes'].shape[1]
  if rows + 1 > config.savi.num_slots:
    raise ConfigError(
        f'{option}: the data has {rows} box rows, which with the background '
        f'slot need savi.num_slots >= {rows + 1} (it is '
        f'{config.savi.num_slots}); set --config.savi.num_slots={rows + 1}')


def savi_stage(config: ml_collections.ConfigDict, workdir: str, mesh: Mesh,
               source: Any) -> Stage:
  """SAVi's training stage on `source` (the 'train' videos; only its
  `batches` read it)."""
  slot_model = Savi(config)
  model = slot_model.model
  stage_config = config.savi
  local_batch_size = sharding.per_host_batch_size(stage_config.batch_size, mesh)
  return Stage(
      name=NAME,
      directory=savi_dir(workdir),
      config=stage_config,
      loss_fn=precision.with_compute_dtype(functools.partial(
          losses.savi_loss, model=model,
          kl_weight=stage_config.kl_weight if stage_config.stochastic else 0.0),
          config.compute_dtype),
      init_params=lambda rng: initializers.initialize(
          steps.init_params(model, rng, _example_clip(config),
                            **_example_inputs(config)),
          jax.random.fold_in(rng, 1), stage_config.init),
      batches=lambda start_step: pipeline.train_batches(
          source, batch_size=local_batch_size,
          clip_length=stage_config.clip_length, seed=config.seed,
          start_step=start_step,
          fields=('video',) + slot_model.conditioning_fields,
          process_index=jax.process_index(),
          process_count=jax.process_count()),
      logging=config.get('logging'),
      images=_training_images(model),
  )


def train_savi(config: ml_collections.ConfigDict, workdir: str,
               mesh: Mesh) -> None:
  """Stage 1: SAVi on clips of the training videos (resumable)."""
  slot_model = Savi(config)
  if uses_foreign_stage1(slot_model, workdir, mesh, 'SAVi'):
    return
  source = get_video_source(config.data, 'train')
  check_conditioning(config, source, 'train')
  stage = savi_stage(config, workdir, mesh, source)
  fit_stage(stage, mesh=mesh, seed=config.seed, what=slot_model.label,
            identity_fields=identity_fields(config), parent=None,
            model_fields=model_fields(config))


def _training_images(model: SAVi):
  """TensorBoard pictures of the first clip of a training batch: its frames,
  SAVi's reconstruction and the slot masks over the frames."""

  @jax.jit
  def run(params, video, boxes):
    output = model.apply({'params': params}, frames_to_model(video),
                         boxes=boxes)
    return (model_to_unit(output.decoded.recon),
            output.decoded.alpha_masks[..., 0])

  def images(params, batch):
    video = batch['video'][:1]
    boxes = batch['boxes'][:1, 0] if 'boxes' in batch else None
    recon, alpha = jax.device_get(run(params, video, boxes))
    frames = np.asarray(video[0], np.float32) / 255.0
    return {'reconstruction': summaries.labelled_grid({
        'input': video[0],
        'reconstruction': summaries.to_uint8(recon[0]),
        'slot masks': summaries.to_uint8(mask_overlay(frames, alpha[0])),
    })}

  return images


class Savi(SlotModel):
  """SAVi / stochastic SAVi: `config.savi`, params = SAVi's parameters."""

  name = NAME
  label = 'SAVi'
  stage1 = {'train_savi': train_savi}
  stage_labels = {NAME: 'SAVi'}
  mask_source = 'decoder alpha masks'

  def __init__(self, config: ml_collections.ConfigDict):
    super().__init__(config)
    self.model = models.build_savi(config.savi,
                                   tuple(config.data.resolution))
    self.decoder = self.model.decoder  # alone: params['decoder']

  @property
  def slot_shape(self) -> tuple[int, int]:
    return self.config.savi.num_slots, self.config.savi.slot_size

  @property
  def num_train_steps(self) -> dict[str, int]:
    return {NAME: self.config.savi.num_train_steps}

  @property
  def conditioning_fields(self) -> tuple[str, ...]:
    return ('boxes',) if is_conditional(self.config) else ()

  def param_shapes(self) -> Any:
    return inference.param_shapes(self.model, _example_clip(self.config),
                                  **_example_inputs(self.config))

  def check_identity(self, workdir: str) -> dict[str, Any]:
    root = workdir_lib.stage1_workdir(self.config, workdir)
    return workdir_lib.checked_identity(
        savi_dir(root), identity_fields(self.config), self.label, root,
        'train_savi')

  def chain(self, workdir: str, steps: dict[str, int]
            ) -> tuple[dict[str, Any], dict[str, Any]]:
    identity, step = self.check_identity(workdir), int(steps[NAME])
    return ({NAME: {'run_id': identity['run_id'], 'step': step,
                    'fingerprint': identity['fingerprint']}},
            workdir_lib.slots_parent(identity, step, NAME))

  def load(self, workdir: str, mesh: Mesh) -> Loaded:
    directory = savi_dir(workdir_lib.stage1_workdir(self.config, workdir))
    workdir_lib.check_model_config(directory, model_fields(self.config),
                                   self.label)
    params, step = inference.restore(
        directory, self.param_shapes(), mesh, what=self.label,
        workdir=workdir, mode='train_savi',
        num_train_steps=self.config.savi.num_train_steps)
    identity, slots_parent = self.chain(workdir, {NAME: step})
    return Loaded(params=params, steps={NAME: step}, identity=identity,
                  step=step, slots_parent=slots_parent)

  def encode(self, params: Any, video: jax.Array, rng: jax.Array,
             carry: Any) -> tuple[jax.Array, Any]:
    boxes = None
    if isinstance(carry, dict):  # a fresh start, conditioned on these
      boxes, carry = carry.get('boxes'), None
    slots, _, carry = self.model.apply(
        {'params': params}, frames_to_model(video), carry,
        method=SAVi.encode, rngs={'sample': rng}, boxes=boxes)
    return slots, carry

  def decode(self, params: Any, slots: jax.Array,
             presence: jax.Array | None = None) -> Decoded:
    decoded = self.decoder.apply({'params': params['decoder']}, slots,
                                 presence)
    return Decoded(recon=model_to_unit(decoded.recon),
                   alpha_masks=decoded.alpha_masks,
                   rgb=model_to_unit(decoded.rgb))

  def observe(self, params: Any, slots: jax.Array, video: jax.Array,
              carry: Any) -> tuple[jax.Array, jax.Array, Any]:
    """SAVi's account of the real frames is its extracted slots decoded (a
    frame at a time: one frame's decoder activations in memory)."""
    del video

    def frame(frame_slots):  # [B, N, D]
      decoded = self.decode(params, frame_slots)
      return decoded.alpha_masks[..., 0], decoded.recon

    alpha, recon = jax.lax.map(frame, jnp.swapaxes(slots, 0, 1))
    return jnp.swapaxes(alpha, 0, 1), jnp.swapaxes(recon, 0, 1), carry

  def image_decoder(self, params: Any) -> tuple[Any, Any]:
    return self.decoder, params['decoder']
