#!/bin/bash
# Training on a Cloud TPU VM slice: the same command on every worker; jax.distributed reads the
# TPU environment (wmjax train calls it when TPU_WORKER_HOSTNAMES is set).
#
#   launch/tpu_vm.sh my-tpu us-central2-b configs/wpe.py /mnt/gcs/ckpt/wpe --config.batch_size=256
#
# Every worker needs wmjax installed (the first command below does it) and WORKDIR must be one
# directory all workers share, e.g. a gcsfuse mount of a bucket at the same path on each worker.
set -euo pipefail
TPU=$1
ZONE=$2
CONFIG=$3
WORKDIR=$4
shift 4
gcloud compute tpus tpu-vm ssh "$TPU" --zone "$ZONE" --worker=all --command \
  "pip install -q 'jax[tpu]' && pip install -q -e ~/wmjax"
gcloud compute tpus tpu-vm ssh "$TPU" --zone "$ZONE" --worker=all --command \
  "cd ~/wmjax && wmjax train --config $CONFIG --workdir $WORKDIR $*"
