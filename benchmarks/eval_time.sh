#!/usr/bin/env bash
# Times the evaluation stage on 100 held-out embedded videos at 64x64 with
# 6 burn-in frames and 44 rollout steps (the OBJ3D protocol), with the
# synthetic config's model sizes. The models are trained for a handful of
# steps only: the timing does not depend on the weights.
#
#   bash benchmarks/eval_time.sh [workdir] [extra --config overrides...]
#
# Prints the evaluation table; `<workdir>/eval/metrics.json` has the seconds
# ('seconds': savi / rollout / total). Add --config.evaluation.savi_metrics=False
# to time the rollouts alone, and
# "--config.evaluation.metrics=('psnr','ssim','lpips')" to time LPIPS too.
set -euo pipefail
workdir="${1:-/tmp/slotformer_jax_eval_time}"
shift || true
common=(
  --config=configs/synthetic.py --workdir="$workdir"
  --config.data.resolution='(64, 64)' --config.data.num_frames=50
  --config.data.num_train=16 --config.data.num_val=4 --config.data.num_test=100
  --config.savi.decoder.broadcast_resolution='(16, 16)'
  --config.savi.num_train_steps=2 --config.savi.batch_size=4
  --config.slotformer.num_train_steps=2 --config.slotformer.batch_size=4
  --config.slot_lstm.train=True --config.slot_lstm.num_train_steps=2
  --config.evaluation.rollout_steps=44 --config.evaluation.chunk_length=50
  --config.extraction.chunk_length=50
  "$@"
)
for mode in train_savi extract_slots train_slotformer train_slot_lstm; do
  python -m slotformer_jax.main "${common[@]}" --mode="$mode" > /dev/null
done
python -m slotformer_jax.main "${common[@]}" --mode=evaluate
python - "$workdir" <<'PY'
import json, sys
seconds = json.load(open(f'{sys.argv[1]}/eval/metrics.json'))['seconds']
print('evaluation seconds:', {k: round(v, 1) for k, v in seconds.items()})
PY
