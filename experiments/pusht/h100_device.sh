#!/usr/bin/env bash
# The Push-T `h100` profile on a lent GPU machine (no package index there): train, then the
# policy evaluation, within one 10-minute command. Carry .whl (experiments/pusht/device_wheels.sh)
# and the workdir W holding data/ and classifier/ made on the host:
#   JAX_PLATFORMS=cpu python experiments/pusht/run.py --profile h100 --workdir W \
#       --stage data --stage classifier [overrides]
#   experiments/pusht/h100_device.sh W TRAIN_MINUTES [overrides]   # on the GPU machine
# Results (logs, policy_eval/, the model's metrics and frame grids) go to $OUT/pusht.tar.
set -uo pipefail
W=$1; minutes=$2; shift 2
if [[ -z ${NO_WHEELS:-} ]]; then  # NO_WHEELS=1: the packages are installed already
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
      .whl/*/*.whl || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
args=(--profile h100 --workdir "$W" --video_format gif "$@")
start=$(date +%s)
python3 experiments/pusht/run.py "${args[@]}" --stage train --minutes "$minutes" 2>&1 \
    | tee "$W/train.log" | grep -v "^  " | grep -E "step|eval|agent|error|Error|stopped" | tail -40
echo "train stage: $(( $(date +%s) - start )) s"
timeout 240 python3 experiments/pusht/run.py "${args[@]}" --stage policy 2>&1 \
    | tee "$W/policy.log" | tail -25
echo "all: $(( $(date +%s) - start )) s"
tar cf "${OUT:-/tmp}/pusht.tar" -C "$W" --exclude='*.gif' --exclude='checkpoints' \
    --exclude='data' --exclude='classifier' .
