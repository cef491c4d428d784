#!/usr/bin/env bash
# The prepared GPU check (issue 24 part 5): every train step of the paper
# configs at the paper's per-device batch (the config's global batch over
# the paper's 4 GPUs), float32 and bfloat16, on the first GPU. One process
# per case (so each peak memory is its own), a time budget for all of them
# (cases left when it runs out are listed as skipped), one table at the end.
# The compiles come first, GPU_CHECK_PARALLEL (default 4) at a time, into a
# persistent compilation cache; the timed runs then load them from it, one
# at a time. The cache is OUT_DIR/cache (delete it to time compiles again).
#
#   bash benchmarks/gpu_check.sh [OUT_DIR]           # on the GPU machine
#   bash benchmarks/gpu_check.sh --smoke [OUT_DIR]   # tiny configs, 1 step:
#                                                    # runs on CPU too
#
# Expects an installed jax with CUDA (pip install -e . 'jax[cuda12]==<the
# installed jax>' beforehand): nothing is downloaded at run time. Writes
# OUT_DIR/gpu_check.jsonl (one JSON line per case) and OUT_DIR/gpu_check.md.
# Each case's stderr (a traceback, if it failed) is in OUT_DIR/stderr/.
# Environment: GPU_CHECK_BUDGET_S (default 420: under 8 minutes with the
# table), GPU_CHECK_CASE_TIMEOUT_S (default 150), GPU_CHECK_DTYPES (default
# "float32 bfloat16"), GPU_CHECK_CASES ("config step;..." to run a subset).
# Then, is the first run input-bound? Each of GPU_CHECK_FED_CASES (default
# "obj3d savi;obj3d slotformer", float32) is timed fed by the real reader
# (GPU_CHECK_READER_WORKERS worker processes, default 2, and device
# prefetch, as training feeds it) against the same step on a batch already
# on the device: per step ms both ways and 'input-bound' / 'compute-bound'
# (OUT_DIR/gpu_check_fed.jsonl and a second table), within
# GPU_CHECK_FED_BUDGET_S (default 150; 0 skips it). Its fixture (converted
# OBJ3D-like videos) is kept in OUT_DIR/feed.
set -u
cd "$(dirname "$0")/.."
SMOKE=()
if [[ "${1:-}" == "--smoke" ]]; then SMOKE=(--smoke); shift; fi
OUT_DIR="${1:-/tmp/gpu_check}"
mkdir -p "$OUT_DIR/stderr"  # stderr of each case (its traceback, if it failed)
ROWS="$OUT_DIR/gpu_check.jsonl"
: > "$ROWS"
BUDGET_S="${GPU_CHECK_BUDGET_S:-420}"
CASE_TIMEOUT_S="${GPU_CHECK_CASE_TIMEOUT_S:-150}"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # peak = what the step used

CASES=(
  "obj3d savi" "obj3d slotformer"
  "clevrer savi" "clevrer slotformer"
  "phyre savi" "phyre slotformer"
  "physion dvae" "physion steve" "physion slotformer"
)
if [[ -n "${GPU_CHECK_CASES:-}" ]]; then
  IFS=';' read -r -a CASES <<<"$GPU_CHECK_CASES"
fi
export JAX_COMPILATION_CACHE_DIR="$OUT_DIR/cache"
export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
export JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES=0
START=$SECONDS
# A row for a case whose process ended without writing one (a crash, a
# usage error): its exit status and the last line it printed, quotes and
# control characters removed so the row stays one line of JSON.
failed_row() {  # rows_file config step dtype exit_status stderr_file
  local last
  last=$(grep -v '^[[:space:]]*$' "$6" 2>/dev/null | tail -n 1 \
         | tr -d '"\\|[:cntrl:]' | cut -c1-300)
  echo "{\"config\": \"$2\", \"step\": \"$3\", \"dtype\": \"$4\", \"error\": \"failed (exit $5): ${last:-no output}\"}" >>"$1"
}
# Phase 1: the compiles, in parallel (CPU-bound), bounded by the budget.
for dtype in ${GPU_CHECK_DTYPES:-float32 bfloat16}; do
  for case in "${CASES[@]}"; do
    read -r config step <<<"$case"
    echo "--config=$config --step=$step --dtype=$dtype"
  done
done | timeout "$((BUDGET_S / 2))" xargs -P "${GPU_CHECK_PARALLEL:-4}" -L 1 \
  python benchmarks/gpu_check.py --compile_only "${SMOKE[@]}" \
  >/dev/null 2>"$OUT_DIR/compile_stderr.txt"
echo "compiles done after $((SECONDS - START)) s" >&2
# Phase 2: the timed runs, one at a time.
for dtype in ${GPU_CHECK_DTYPES:-float32 bfloat16}; do
  for case in "${CASES[@]}"; do
    read -r config step <<<"$case"
    left=$((BUDGET_S - (SECONDS - START)))
    if ((left < 20)); then
      echo "{\"config\": \"$config\", \"step\": \"$step\", \"dtype\": \"$dtype\", \"error\": \"skipped: time budget of ${BUDGET_S} s spent\"}" >>"$ROWS"
      continue
    fi
    limit=$((left < CASE_TIMEOUT_S ? left : CASE_TIMEOUT_S))
    before=$(wc -l <"$ROWS")
    timeout "$limit" python benchmarks/gpu_check.py --config="$config" \
      --step="$step" --dtype="$dtype" --json="$ROWS" "${SMOKE[@]}" \
      >/dev/null 2>"$OUT_DIR/stderr/${config}_${step}_${dtype}.txt"
    rc=$?
    if ((rc == 124)); then
      echo "{\"config\": \"$config\", \"step\": \"$step\", \"dtype\": \"$dtype\", \"error\": \"timed out after ${limit} s\"}" >>"$ROWS"
    elif (($(wc -l <"$ROWS") == before)); then
      failed_row "$ROWS" "$config" "$step" "$dtype" "$rc" "$OUT_DIR/stderr/${config}_${step}_${dtype}.txt"
    fi
  done
done
# Phase 3: the steps fed by the real reader vs on a resident batch.
FED_ROWS="$OUT_DIR/gpu_check_fed.jsonl"
: > "$FED_ROWS"
FED_START=$SECONDS
FED_BUDGET_S="${GPU_CHECK_FED_BUDGET_S:-150}"
if ((FED_BUDGET_S > 0)); then
  IFS=';' read -r -a FED_CASES <<<"${GPU_CHECK_FED_CASES:-obj3d savi;obj3d slotformer}"
  for case in "${FED_CASES[@]}"; do
    read -r config step <<<"$case"
    left=$((FED_BUDGET_S - (SECONDS - FED_START)))
    if ((left < 20)); then
      echo "{\"config\": \"$config\", \"step\": \"$step\", \"dtype\": \"float32\", \"error\": \"skipped: time budget of ${FED_BUDGET_S} s spent\"}" >>"$FED_ROWS"
      continue
    fi
    before=$(wc -l <"$FED_ROWS")
    timeout "$left" python benchmarks/gpu_check.py --config="$config" \
      --step="$step" --dtype=float32 --json="$FED_ROWS" --fed \
      --reader_workers="${GPU_CHECK_READER_WORKERS:-2}" \
      --fed_dir="$OUT_DIR/feed" "${SMOKE[@]}" \
      >/dev/null 2>"$OUT_DIR/stderr/fed_${config}_${step}.txt"
    rc=$?
    if ((rc == 124)); then
      echo "{\"config\": \"$config\", \"step\": \"$step\", \"dtype\": \"float32\", \"error\": \"timed out after ${left} s\"}" >>"$FED_ROWS"
    elif (($(wc -l <"$FED_ROWS") == before)); then
      failed_row "$FED_ROWS" "$config" "$step" float32 "$rc" "$OUT_DIR/stderr/fed_${config}_${step}.txt"
    fi
  done
fi
python - "$ROWS" "$OUT_DIR/gpu_check.md" "$((SECONDS - START))" "$FED_ROWS" <<'EOF'
import json, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
lines = ['| config | step | dtype | batch/device | median s/step | peak GiB '
         '| GFLOP/step | TFLOP/s | load s (cached compile) | device |',
         '|---|---|---|---|---|---|---|---|---|---|']
for r in rows:
  if 'error' in r:
    lines.append(f"| {r['config']} | {r['step']} | {r['dtype']} | "
                 f"{r['error']} |||||||")
    continue
  peak = 'n/a' if r['peak_bytes'] is None else f"{r['peak_bytes'] / 2**30:.2f}"
  lines.append(
      f"| {r['config']} | {r['step']} | {r['dtype']} | "
      f"{r['per_device_batch']} | {r['median_seconds']:.4f} | {peak} | "
      f"{r['flops'] / 1e9:.1f} | {r['tflops_per_second']:.2f} | "
      f"{r['compile_seconds']:.1f} | {r['device']} |")
lines.append(f'\n{len(rows)} cases in {sys.argv[3]} s.')
fed = [json.loads(line) for line in open(sys.argv[4])]
if fed:
  lines += ['', 'Fed by the real reader (reader worker processes + device '
            'prefetch) vs on a batch already on the device; input-bound: '
            'more than 10 % slower fed:', '',
            '| config | step | reader workers | ms/step fed | ms/step '
            'resident | fed / resident | verdict |',
            '|---|---|---|---|---|---|---|']
  for r in fed:
    if 'fed_ms' not in r:
      lines.append(f"| {r['config']} | {r['step']} | "
                   f"{r.get('error', 'no fed timing')} |||||")
      continue
    lines.append(f"| {r['config']} | {r['step']} | {r['reader_workers']} | "
                 f"{r['fed_ms']:.1f} | {r['resident_ms']:.1f} | "
                 f"{r['fed_over_resident']:.2f} | {r['verdict']} |")
open(sys.argv[2], 'w').write('\n'.join(lines) + '\n')
print('\n'.join(lines))
EOF
