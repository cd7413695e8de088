#!/bin/bash
# jaxdrive on a Cloud TPU VM pod slice: the same command on every worker.
#   launch/tpu_pod.sh TPU_NAME ZONE configs/stdit3_xl.py gs://bucket/runs/xl [jaxdrive train options]
# Each worker runs `jaxdrive train`; jax.distributed.initialize() reads the TPU metadata
# (jaxdrive.parallel.initialize_distributed detects TPU_WORKER_HOSTNAMES / multislice). The
# workdir should be a GCS path or a shared disk that every worker sees. Install first with
#   gcloud compute tpus tpu-vm ssh TPU --zone ZONE --worker=all \
#     --command='pip install "jax[tpu]" && pip install -e ~/jaxdrive'
set -euo pipefail
TPU=${1:?usage: launch/tpu_pod.sh TPU_NAME ZONE CONFIG WORKDIR [options]}
ZONE=${2:?zone}
CONFIG=${3:?config}
WORKDIR=${4:?workdir}
shift 4
EXTRA=$(printf ' %q' "$@")
gcloud compute tpus tpu-vm ssh "$TPU" --zone "$ZONE" --worker=all \
  --command="cd ~/jaxdrive && jaxdrive train --config $CONFIG --workdir $WORKDIR$EXTRA"
