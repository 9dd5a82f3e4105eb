#!/usr/bin/env bash
# The Push-T `h100` profile end to end on a lent GPU machine (no package index there), from a
# fresh clone: data and success classifier on the machine's CPUs (the dataset simulated in one
# process per CPU: 1.1 min on 2 cores of the CPU VM, 2026-11-28; skipped where W/seedS/data and
# classifier are carried, prepared), then for all training seeds at once, on the one GPU, the
# world model, the policy evaluation and planning (held-out start states), each seed in its own
# workdir W/seedS sharing the first seed's data and classifier. Carry .whl (device_wheels.sh):
#   experiments/pusht/h100_device.sh W MINUTES [SEEDS] [overrides]
# e.g. `experiments/pusht/h100_device.sh /tmp/pusht 9 "0 1"`. MINUTES bounds each call of
# run.py (the stages resume where a call stopped: run the same command again to continue).
# STAGES (default "train policy plan summary") names the stages each seed runs; IMPROVE, where
# set, then improves a policy cloned from the noisy pushes in each seed's world model
# (experiments/improve/run.py --task push $IMPROVE --seed S, into W/seedS/improve), e.g.
#   STAGES=train IMPROVE="--no-upper_bound --evaluation_states 64" \
#       experiments/pusht/h100_device.sh W 5 "0 1"
# Summaries, logs, policy_eval/, plan/ and improve/ go to $OUT/pusht.tar. Measured on one H200 (2026-11-27),
# data and classifier prepared on the host and carried in W/seed0: `h100_device.sh W 7.3 "0 1"
# --no-lookahead --candidates 1,10,50` finished both seeds in 7.4 minutes (RESULTS.md beside this).
# With the data and classifier made there too, the same command runs the whole experiment for two
# training seeds from a fresh clone in one call: 515 s on one H200 with 16 CPU cores (2026-11-29):
#   experiments/pusht/h100_device.sh /tmp/pusht 7.3 "0 1" --no-lookahead --candidates 1,10,50
set -uo pipefail
W=$(realpath -m "$1"); minutes=$2; seeds=${3:-0 1}; shift $(( $# < 3 ? $# : 3 ))
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
stages=()
for stage in ${STAGES:-train policy plan summary}; do stages+=(--stage "$stage"); done
first=${seeds%% *}
JAX_PLATFORMS=cpu run "$first" --stage data --stage classifier 2>&1 | tail -3
nseeds=$(wc -w <<< "$seeds")
for seed in $seeds; do  # the seeds train and evaluate side by side: a 32.5M model leaves most of
  mkdir -p "$W/seed$seed"  # the GPU idle, and the closed-loop stages wait on the simulator
  for shared in data classifier; do  # one dataset and classifier for every seed
    [[ -e $W/seed$seed/$shared ]] || ln -s "$W/seed$first/$shared" "$W/seed$seed/$shared"
  done
  ( export XLA_PYTHON_CLIENT_MEM_FRACTION=$(python3 -c "print(round(0.9 / $nseeds, 3))")
    run "$seed" "${stages[@]}" > "$W/seed$seed.log" 2>&1
    echo "seed $seed: exit $? at $(( $(date +%s) - start )) s"
    grep -v "^  " "$W/seed$seed.log" \
      | grep -E "^## stage|pearson|held_out|block_iou|Error|stopped" | tail -20
    if [[ -n ${IMPROVE:-} ]]; then
      # shellcheck disable=SC2086  # IMPROVE holds several arguments
      python3 experiments/improve/run.py --task push --workdir "$W/seed$seed/model" \
          --out "$W/seed$seed/improve" --seed "$seed" $IMPROVE > "$W/seed$seed-improve.log" 2>&1
      echo "seed $seed improve: exit $? at $(( $(date +%s) - start )) s"
      grep -E "round [0-9]+:|Error" "$W/seed$seed-improve.log" | cut -c1-400 | tail -8
    fi ) &
done
wait
tar cf "${OUT:-/tmp}/pusht.tar" -C "$W" --exclude='*.gif' --exclude='checkpoints' \
    --exclude='data' --exclude='classifier' .
