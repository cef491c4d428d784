#!/usr/bin/env bash
# Runs the whole pipeline on this machine (all local CPUs/GPUs/TPU cores).
#   launch/local.sh configs/synthetic.py runs/demo [--config.field=value ...]
set -euo pipefail
config=${1:?usage: launch/local.sh CONFIG WORKDIR [flags...]}
workdir=${2:?usage: launch/local.sh CONFIG WORKDIR [flags...]}
shift 2
exec python -m slotformer_jax.main --config="$config" --workdir="$workdir" "$@"
