#!/usr/bin/env bash
# The Push-T `h100` profile end to end on a lent GPU machine (no package index there), from a
# fresh clone: data and success classifier on the host CPUs, then per training seed the world
# model, the policy evaluation and planning on the GPU (held-out start states), each seed in its
# own workdir W/seedS sharing seed 0's data and classifier. Carry .whl (device_wheels.sh):
#   experiments/pusht/h100_device.sh W MINUTES [SEEDS] [overrides]
# e.g. `experiments/pusht/h100_device.sh /tmp/pusht 9 "0 1"`. MINUTES bounds each call of
# run.py (the stages resume where a call stopped: run the same command again to continue).
# Summaries, logs, policy_eval/ and plan/ go to $OUT/pusht.tar.
set -uo pipefail
W=$1; minutes=$2; seeds=${3:-0 1}; shift $(( $# < 3 ? $# : 3 ))
if [[ -z ${NO_WHEELS:-} ]]; then  # NO_WHEELS=1: the packages are installed already
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
      .whl/*/*.whl || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
start=$(date +%s)
run() {  # SEED STAGE... : run.py on seed SEED's workdir
  local seed=$1; shift
  python3 experiments/pusht/run.py --profile h100 --workdir "$W/seed$seed" --video_format gif \
      --minutes "$minutes" --config.seed="$seed" "$@" "${overrides[@]}"
}
overrides=("$@")
first=${seeds%% *}
JAX_PLATFORMS=cpu run "$first" --stage data --stage classifier 2>&1 | tail -3
for seed in $seeds; do
  mkdir -p "$W/seed$seed"
  for shared in data classifier; do  # one dataset and classifier for every seed
    [[ -e $W/seed$seed/$shared ]] || ln -s "$W/seed$first/$shared" "$W/seed$seed/$shared"
  done
  run "$seed" --stage train --stage policy --stage plan --stage summary 2>&1 \
      | tee "$W/seed$seed.log" | grep -v "^  " | grep -E "^## stage|pearson|held_out|block_iou|Error|stopped" | tail -20
  echo "seed $seed done at $(( $(date +%s) - start )) s"
done
tar cf "${OUT:-/tmp}/pusht.tar" -C "$W" --exclude='*.gif' --exclude='checkpoints' \
    --exclude='data' --exclude='classifier' .
