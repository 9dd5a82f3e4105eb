#!/usr/bin/env bash
# The accelerator measurements of benchmarks/RESULTS.md for the two full-size models: IRASim-XL/2
# (256x320 frames as 32x40x4 SDXL latents, 16-frame windows) and WPE-600M (256x256 frames as
# 32x32x16 SD3 latents, 9 context + 9 new frames), in bf16 with cuDNN attention on a GPU
# (`attention_impl=auto`: splash on TPU).
#
#   benchmarks/gpu_suite.sh check    # the train settings compiled for an H100 (no GPU needed)
#   benchmarks/gpu_suite.sh train    # check, then the train step at batch 16: time, MFU,
#                                    # compiled and peak memory, device time by op (a
#                                    # jax.profiler trace of 3 steps)
#   benchmarks/gpu_suite.sh rollout  # batch-8 rollouts: frames/s at 59 calls per block (PNDM-50's
#                                    # cost) and at DDIM-10; WPE with and without the KV cache
#   benchmarks/gpu_suite.sh rollout-fp8  # XL/2 rollouts at batch 8, unrolled layers, DDIM-10 and
#                                        # 59 calls: bf16 matmuls, then float8 ones
#                                        # (model.fp8_matmuls, calibrated scales), same call
#   benchmarks/gpu_suite.sh all
#
# What the backward pass keeps, one knob at a time (parts that may be named together in one call):
#   benchmarks/gpu_suite.sh settings-xl-train  # XL/2's train step at batch 16 for each of
#                                              # TRAIN_SETTINGS (over 2 min each with the
#                                              # compile on an H200; a setting is
#                                              # model fields, or section.field=value)
#   benchmarks/gpu_suite.sh settings-wpe-train # the same for WPE-600M
# A setting that does not fit the card is reported and the next one runs.
#
# On a machine with no package index (the lent GPU machines), carry .whl/core
# (experiments/pusht/device_wheels.sh) and start the command with
#   python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/core/*.whl
#   export PYTHONPATH=/tmp/site:$PWD
#
# Batch 16 with remat 'dots' compiles to 67.5 GiB (IRASim-XL/2) and 66.3 GiB (WPE-600M) per H100,
# so JAX may take 95 % of the card here (its default, 75 %, is about 60 GiB); train_step.py stops
# before the first step when the compiled step is larger than the device's memory.
# JSON goes to benchmarks/results/ (or $OUT_DIR). Each part takes about 3 to 5 minutes on one H100.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${OUT_DIR:-benchmarks/results}
traces=${TRACE_DIR:-${TMPDIR:-/tmp}/wmjax-traces}
mkdir -p "$out"
py=${PYTHON:-python3}  # the interpreter that has JAX (PYTHON=...)
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.95}
platform=$($py -c "import jax; print(jax.default_backend())")
fast=(--config.model.dtype=bfloat16 --config.model.attention_impl=auto)

check() {
  # The suite's train settings compiled for the card first (deviceless, on the host's CPU; about a
  # minute each): `wmjax compile` exits 1, with the setting train.auto_fit would choose, when one
  # does not fit what JAX may take (XLA_PYTHON_CLIENT_MEM_FRACTION of the card).
  for spec in irasim.py:XL wpe_600m.py; do
    wmjax compile --config "configs/$spec" --target "${COMPILE_TARGET:-h100}" --batch 16 \
        --config.model.dtype=bfloat16 --config.model.attention_impl=auto \
        --config.model.remat=dots --out "$out/compile-${spec%%.py*}-b16-dots.json" > /dev/null
  done
}

train() {
  check
  # IRASim-XL/2 trains on 16-frame windows, WPE-600M on 20-frame ones (WPE table 5: batch 16).
  $py benchmarks/train_step.py --config configs/irasim.py:XL "${fast[@]}" \
      --config.model.remat=dots --batch 16 --steps 5 --profile "$traces/train-irasim" \
      --out "$out/train_step-irasim-XL_2-bf16-b16-$platform.json"
  $py benchmarks/train_step.py --config configs/wpe_600m.py "${fast[@]}" \
      --config.model.remat=dots --batch 16 --steps 5 --profile "$traces/train-wpe" \
      --out "$out/train_step-wpe-600m-bf16-b16-$platform.json"
}

rollout() {
  for steps in 59 10; do
    # IRASim chains 15-frame blocks after one context frame (bidirectional: no KV cache).
    $py benchmarks/forward_rollout.py --config configs/irasim.py:XL "${fast[@]}" \
        --config.sampling.num_steps=$steps --batch 8 --frames 15 --repeats 2 \
        --out "$out/forward_rollout-irasim-XL_2-bf16-steps$steps-$platform.json"
    # WPE: 9 context + 9 new frames, causal, with and without the temporal KV cache.
    for kv in True False; do
      $py benchmarks/forward_rollout.py --config configs/wpe_600m.py "${fast[@]}" \
          --config.sampling.num_steps=$steps --config.sampling.kv_cache=$kv \
          --batch 8 --frames 18 --repeats 2 \
          --out "$out/forward_rollout-wpe-600m-bf16-steps$steps-kv$kv-$platform.json"
    done
  done
}

rollout_fp8() {
  # float8 against bf16 matmuls, one knob, the baseline in the same call; each run under
  # SETTING_TIMEOUT seconds (default 300). Predicted for an H100 (benchmarks/RESULTS.md,
  # 2026-11-30): DDIM-10 blocks 868 ms in bf16, 609 ms with float8 matmuls.
  local steps fp8
  for steps in 10 59; do
    for fp8 in False True; do
      echo "== xl rollout steps=$steps fp8_matmuls=$fp8"
      timeout "${SETTING_TIMEOUT:-300}" \
        $py benchmarks/forward_rollout.py --config configs/irasim.py:XL "${fast[@]}" \
          --config.model.scan_layers=False --config.model.fp8_matmuls=$fp8 \
          --config.sampling.num_steps=$steps --batch 8 --frames 15 --repeats 2 \
          --out "$out/forward_rollout-irasim-XL_2-unrolled-fp8$fp8-steps$steps-$platform.json" \
        > "$traces-rollout-fp8$fp8-steps$steps.log" 2>&1 \
        && grep -E '"(rollout_frames_per_s|forward_ms)"' \
             "$out/forward_rollout-irasim-XL_2-unrolled-fp8$fp8-steps$steps-$platform.json" \
        || { echo "rollout failed:"; tail -3 "$traces-rollout-fp8$fp8-steps$steps.log"; }
    done
  done
}

# Settings compared, one knob at a time, unrolled layers (a scan stacks each layer's saved
# activations, copies an unrolled stack does not make): what remat keeps, from weight matmuls
# (dots) to everything (none: 131 GiB for XL/2, an H200 only), and no remat over two micro-batches
# of 8. On an H200 (2026-11-30, benchmarks/RESULTS.md): XL/2 dots 607.0 ms, dots_attention 610.9,
# none over two micro-batches 552.9; each XL/2 setting took about 2.5 minutes with its compile,
# and a WPE-600M one more than 135 s. TRAIN_SETTINGS="remat=dots scan_layers=False;remat=none
# scan_layers=False" runs those settings instead (';' between settings). Each runs under
# SETTING_TIMEOUT seconds (default 300), so that one slow setting cannot take a whole 10-minute
# device call; three settings fit one call.
IFS=';' read -r -a TRAIN_SETTINGS <<< "${TRAIN_SETTINGS:-}"
[[ ${#TRAIN_SETTINGS[@]} -gt 0 ]] || TRAIN_SETTINGS=(
    "remat=dots scan_layers=False" "remat=none scan_layers=False optim.grad_accum=2"
    "remat=dots_elementwise scan_layers=False")

setting_flags() {  # "k=v section.k=v" -> --config.model.k=v --config.section.k=v in flags,
  flags=() tag=""  # -v-v in tag
  local kv
  for kv in $1; do
    if [[ ${kv%%=*} == *.* ]]; then flags+=("--config.$kv"); else flags+=("--config.model.$kv"); fi
    tag+="-${kv#*=}"
  done
}

train_runs() {  # NAME CONFIG: the train step of each TRAIN_SETTINGS; a failing one (out of
  local name=$1 spec=$2 setting flags tag  # memory, say) is reported and the next one runs
  for setting in "${TRAIN_SETTINGS[@]}"; do
    setting_flags "$setting"
    echo "== $name train $setting"
    timeout "${SETTING_TIMEOUT:-300}" \
      $py benchmarks/train_step.py --config "$spec" "${fast[@]}" "${flags[@]}" --batch 16 \
        --steps 5 --out "$out/settings-train-$name$tag-$platform.json" \
        > "$traces-$name$tag-train.log" 2>&1 \
      && grep -E '"(step_ms|mfu)"' "$out/settings-train-$name$tag-$platform.json" \
      || { echo "train step failed:"; tail -3 "$traces-$name$tag-train.log"; }
  done
}

[[ $# -gt 0 ]] || set -- all
for part in "$@"; do
  case "$part" in
    settings-xl-train) train_runs xl configs/irasim.py:XL ;;
    settings-wpe-train) train_runs wpe configs/wpe_600m.py ;;
    check) check ;;
    train) train ;;
    rollout) rollout ;;
    rollout-fp8) rollout_fp8 ;;
    all) train; rollout ;;
    *) echo "usage: $0 [check|train|rollout|rollout-fp8|all|settings-xl-train|settings-wpe-train ...]" >&2
       exit 2 ;;
  esac
done
