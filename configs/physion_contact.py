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

import os

from slotformer_jax.config.checks import load_config_file
from slotformer_jax.config.defaults import contact_readout_config


def get_config():
  # By path, not `from configs import physion`: the file works from any
  # folder, whatever is on sys.path.
  config = load_config_file(
      os.path.join(os.path.dirname(os.path.abspath(__file__)), 'physion.py'))
  config.extraction.splits = ('train', 'readout_train', 'readout_val', 'test')
  config.task = 'contact'
  # The defaults are the official readout (config/defaults.py); besides:
  config.readout = r = contact_readout_config()
  r.video_len = 75
  r.num_pictures = 4
  return config
