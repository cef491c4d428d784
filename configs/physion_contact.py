"""Physion object contact prediction on the converted Physion layout.

`configs/physion.py` (the paper's Physion models) plus the official readout
(physion_vqa/configs/readout_physion_params.py): slots of the first 75
frames, of which the first 45 (1.5 s at 30 fps) are observed and the rest
rolled out by SlotFormer (trained on every 3rd frame, so the rollout is
interleaved over the 3 frame offsets as the official rollout script does);
the relation readout with the official unordered pairs, feature size 192,
Adam 1e-3 with cosine decay, batch 64, 50 epochs; checkpoint and threshold
chosen on 'readout_val' (the official script picks them on test), 3 seeds.
Labels come from the converter's `label` field (readout_labels.csv for the
Readout Fitting videos, labels.csv for the Testing videos).

As configs/physion.py, the slot model is STEVE (the paper's Physion
pipeline): the stages are train_dvae, tokenize_frames, train_steve,
extract_slots, train_slotformer (on STEVE's slots), train_readout,
evaluate_readout, and the readout reads STEVE's 192-d slots;
`--config.slot_model=savi` swaps SAVi in.
"""

import ml_collections

from configs import physion


def get_config():
  config = physion.get_config()
  config.extraction.splits = ('train', 'readout_train', 'readout_val', 'test')
  config.task = 'contact'
  config.readout = r = ml_collections.ConfigDict()
  r.observed_frames = 45
  r.video_len = 75
  r.label_field = 'label'
  r.splits = ml_collections.ConfigDict(dict(
      train='readout_train', val='readout_val', test='test'))
  r.conditions = ('observed', 'rollout', 'copy_last', 'ground_truth')
  r.seeds = (0, 1, 2)
  # None: the slot size (192), as the official readout (typed, so that
  # --config.readout.features=N can set it).
  r.features = ml_collections.config_dict.placeholder(int)
  r.pairs = 'unordered'
  r.epochs = 50
  r.batch_size = 64
  r.learning_rate = 1e-3
  r.warmup_fraction = 0.0
  r.rollout_batch_size = 32
  r.num_pictures = 4
  return config
