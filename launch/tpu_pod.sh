#!/usr/bin/env bash
# Starts one process per host of a Cloud TPU pod slice; each calls
# jax.distributed.initialize() (--distributed), which discovers the others.
# The workdir must be on storage every host sees (e.g. a gs:// bucket mounted
# with gcsfuse, or a shared filesystem), and so must the data directory.
#   launch/tpu_pod.sh TPU_NAME ZONE CONFIG WORKDIR [flags...]
set -euo pipefail
tpu=${1:?TPU name}; zone=${2:?zone}; config=${3:?config}; workdir=${4:?workdir}
shift 4
gcloud compute tpus tpu-vm ssh "$tpu" --zone="$zone" --worker=all --command="
  cd ~/slotformer-jax && pip install -q -e . 'jax[tpu]' &&
  SLOTFORMER_DATA_DIR=${SLOTFORMER_DATA_DIR:-~/slotformer_data} \
  python -m slotformer_jax.main --distributed --config=$config \
      --workdir=$workdir $*"
