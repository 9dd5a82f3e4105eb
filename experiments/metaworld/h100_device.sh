#!/usr/bin/env bash
# The MetaWorld `h100` profile end to end on a lent GPU machine (no package index there) from a
# fresh clone, data included: the dataset simulated on the machine's CPUs (one process per CPU,
# rendered through the GPU's EGL), then on the GPU the reader, the world model, the open-loop arm
# metrics and the policy evaluation against the simulator (held-out start states).
#   experiments/metaworld/h100_device.sh W [overrides]
# Carry .whl (experiments/pusht/device_wheels.sh metaworld: 57 MiB) and .gl (the EGL loaders:
# the device tool's README gives the apt-get download line). NO_WHEELS=1 where the packages are
# installed already (a CPU dry run: NO_WHEELS=1 experiments/metaworld/h100_device.sh W --smoke).
# The summary, logs, metrics and pictures go to $OUT/metaworld.tar, also when a stage fails or
# the GPU stages are stopped at LIMIT_S seconds from the start (default 560: a device command may
# run 600 s). The stages resume: the same command again continues where this one stopped.
set -uo pipefail
start=$(date +%s)
W=$(realpath -m "$1"); shift
if [[ -n ${OUT:-} ]]; then
  mkdir -p "$OUT"
  trap 'tar -cf "$OUT/metaworld.tar" -C "$W" --exclude=data --exclude=model/checkpoints .' EXIT
fi
if [[ -z ${NO_WHEELS:-} ]]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
      .whl/*/*.whl || exit 1
fi
if [[ -d .gl ]]; then  # GLVND and EGL loaders for the NVIDIA driver's EGL
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MUJOCO_GL=egl
command -v nvidia-smi > /dev/null && nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
profile=(experiments/metaworld/run.py --profile h100 --workdir "$W")
JAX_PLATFORMS=cpu python3 "${profile[@]}" --stage data "$@" 2>&1 | tail -2
echo "data: $(( $(date +%s) - start )) s"
# SIGTERM at the limit: the training loop saves a checkpoint and stops
timeout -s TERM $(( ${LIMIT_S:-560} - ($(date +%s) - start) )) python3 "${profile[@]}" \
    --stage reader --stage train --stage metrics --stage policy --stage summary "$@" \
    >> "$W/run.log" 2>&1
echo "exit $? at $(( $(date +%s) - start )) s"
grep -E "^## stage|^step [0-9]+/|pearson|held_out|Error" "$W/run.log" | tail -20
