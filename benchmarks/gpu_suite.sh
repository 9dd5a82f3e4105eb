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
#   benchmarks/gpu_suite.sh all
#
# The fused kernels (wmjax.nn.kernels), parts that may be named together in one call:
#   benchmarks/gpu_suite.sh kernels-mlp       # the MLP kernels alone at XL/2's shape against
#                                             # XLA, tile settings side by side (~2 min); later
#                                             # parts of the same call take the fastest tiles
#   benchmarks/gpu_suite.sh kernels-xl-train  # XL/2's train step: baseline, MLP kernel, both
#                                             # kernels, both unrolled (~4.5 min)
#   benchmarks/gpu_suite.sh kernels-wpe-train # the same for WPE-600M (~4.5 min)
#   benchmarks/gpu_suite.sh kernels-rollout   # 59-call rollouts of both, baseline vs both
#                                             # kernels (~4 min)
# e.g. `gpu_suite.sh kernels-mlp kernels-xl-train` within one 10-minute command.
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

# Settings compared, one knob at a time: the XLA baseline, the fused MLP, the fused MLP with the
# fused LayerNorm-modulate, then the same with unrolled layers (no scan: no per-layer stacking
# copies of the saved activations). Rollouts: the baseline and both kernels. Tile settings of
# the MLP kernels: MLP_BLOCKS (the train steps and rollouts use the first),
# rows,cols,depth,warps,stages each.
MLP_BLOCKS=${MLP_BLOCKS:-"128,128,64,8,3 128,128,64,4,4 128,256,64,8,3 256,128,64,8,3 64,128,64,4,4"}
TRAIN_SETTINGS=("mlp_kernel=xla norm_kernel=xla" "mlp_kernel=pallas norm_kernel=xla"
                "mlp_kernel=pallas norm_kernel=pallas"
                "mlp_kernel=pallas norm_kernel=pallas scan_layers=False")
ROLLOUT_SETTINGS=("mlp_kernel=xla norm_kernel=xla" "mlp_kernel=pallas norm_kernel=pallas")

setting_flags() {  # "k=v k=v" -> --config.model.k=v ... in flags, -v-v in tag
  flags=() tag=""
  local kv
  for kv in $1; do flags+=("--config.model.$kv"); tag+="-${kv#*=}"; done
}

train_runs() {  # NAME CONFIG: the train step of each TRAIN_SETTINGS; a failing one (out of
  local name=$1 spec=$2 setting flags tag  # memory, say) is reported and the next one runs
  local blocks=(${MLP_BLOCKS})
  for setting in "${TRAIN_SETTINGS[@]}"; do
    setting_flags "$setting"
    echo "== $name train $setting"
    $py benchmarks/train_step.py --config "$spec" "${fast[@]}" "${flags[@]}" \
        --config.model.remat=dots --batch 16 --steps 5 --mlp_blocks "${blocks[0]}" \
        --out "$out/kernels-train-$name$tag-$platform.json" > "$traces-$name$tag-train.log" 2>&1 \
      && grep -E '"(step_ms|mfu)"' "$out/kernels-train-$name$tag-$platform.json" \
      || { echo "train step failed:"; tail -3 "$traces-$name$tag-train.log"; }
  done
}

rollout_runs() {  # NAME CONFIG FORWARD_ROLLOUT_ARGS...: 59-call rollouts of ROLLOUT_SETTINGS
  local name=$1 spec=$2 setting flags tag; shift 2
  local blocks=(${MLP_BLOCKS})
  for setting in "${ROLLOUT_SETTINGS[@]}"; do
    setting_flags "$setting"
    echo "== $name rollout $setting"
    $py benchmarks/forward_rollout.py --config "$spec" "${fast[@]}" "${flags[@]}" \
        --config.sampling.num_steps=59 --batch 8 --repeats 2 --mlp_blocks "${blocks[0]}" "$@" \
        --out "$out/kernels-rollout-$name$tag-$platform.json" > "$traces-$name$tag-roll.log" 2>&1 \
      && grep -E '"rollout_frames_per_s"' "$out/kernels-rollout-$name$tag-$platform.json" \
      || { echo "rollout failed:"; tail -3 "$traces-$name$tag-roll.log"; }
  done
}

fastest_blocks() {  # the MLP kernels' fastest tile setting in mlp_kernel.py's JSON $1 (else none)
  $py -c 'import json, sys
runs = [r for r in json.load(open(sys.argv[1]))["runs"] if r["impl"] == "pallas" and "ms" in r]
b = min(runs, key=lambda r: r["ms"])["blocks"] if runs else None
print(",".join(str(b[k]) for k in ("rows", "cols", "depth", "warps", "stages")) if b else "")' "$1"
}

kernels_mlp() {
  local blocks=() b best
  for b in ${MLP_BLOCKS}; do blocks+=(--blocks "$b"); done
  $py benchmarks/mlp_kernel.py --rows 81920 --width 1152 "${blocks[@]}" \
      --out "$out/kernels-mlp-xl-$platform.json" 2>&1 | grep -E '^\{"impl"|Error' || true
  best=$(fastest_blocks "$out/kernels-mlp-xl-$platform.json" 2>/dev/null || true)
  # the parts after this one take the fastest tiles found (the first of MLP_BLOCKS otherwise)
  if [[ -n $best ]]; then MLP_BLOCKS="$best ${MLP_BLOCKS}"; echo "MLP tiles: $best"; fi
}

[[ $# -gt 0 ]] || set -- all
for part in "$@"; do
  case "$part" in
    kernels-mlp) kernels_mlp ;;
    kernels-xl-train) train_runs xl configs/irasim.py:XL ;;
    kernels-wpe-train) train_runs wpe configs/wpe_600m.py ;;
    kernels-rollout) rollout_runs xl configs/irasim.py:XL --frames 15
                     rollout_runs wpe configs/wpe_600m.py --frames 18 ;;
    check) check ;;
    train) train ;;
    rollout) rollout ;;
    all) train; rollout ;;
    *) echo "usage: $0 [check|train|rollout|all|kernels-mlp|kernels-xl-train|kernels-wpe-train|"\
            "kernels-rollout ...]" >&2; exit 2 ;;
  esac
done
