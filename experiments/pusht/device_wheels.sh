#!/usr/bin/env bash
# Wheels for running experiments/pusht/run.py (or, with the argument metaworld,
# experiments/metaworld/run.py) on a lent GPU machine whose image has JAX, Flax,
# Optax, Orbax, OpenCV and the scientific stack but none of the data, config and simulator
# packages, and no package index (Python 3.12, x86-64). Downloads them into .whl/core (data and
# training, 11 MiB) and .whl/sim (the simulator, 17 MiB; git-ignored), so that a call can carry
# both beside the 14 MiB dataset within the 64 MiB a call may carry. No
# imageio-ffmpeg (its wheel alone is 65 MiB): videos are written as GIF there. The device command
# installs them with
#   python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*/*.whl
#   export PYTHONPATH=/tmp/site:$PWD
# Arguments: the simulators to fetch, pusht (the default) and / or metaworld (MetaWorld, MuJoCo 3
# and its OpenGL bindings, into .whl/sim too).
set -euo pipefail
sims=("${@:-pusht}")
cd "$(dirname "$0")/../.."
rm -rf .whl && mkdir -p .whl/core .whl/sim
PLATFORMS=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64
           --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64
           --platform manylinux1_x86_64)
download() {  # DIR NAME==VERSION...: the versions this machine's tests run with
  local dir=$1; shift
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp "${PLATFORMS[@]}" -d "$dir" "$@"
}
# core: data, configs, training, evaluation (the dataset is carried, not generated there)
download .whl/core tensorflow-datasets==4.9.10 array_record==0.8.6 grain==0.2.18 \
  ml_collections==1.1.0 dm-tree==0.1.10 immutabledict==4.3.1 simple-parsing==0.1.9 \
  docstring_parser==0.18.0 tensorflow-metadata==1.21.0 googleapis-common-protos==1.76.0 \
  termcolor==3.3.0 toml==0.10.2 portpicker==1.6.0 importlib_resources==7.1.0 \
  tensorboardX==2.6.5 dm_pix==0.4.5
# promise (needed by tensorflow-datasets) is published as source only: build its wheel here
python3 -m pip wheel -q --no-deps -w .whl/core promise==2.3
for sim in "${sims[@]}"; do
  case $sim in
    pusht)  # the gym-pusht simulator, for policy evaluation and planning
      download .whl/sim gym-pusht==0.1.8 gymnasium==1.4.0 Farama-Notifications==0.0.6 \
        pymunk==6.11.1 cffi==2.0.0 pycparser==3.0 shapely==2.2.0 pygame==2.6.1 ;;
    metaworld)  # MetaWorld on MuJoCo 3, rendered through EGL
      download .whl/sim metaworld==3.1.1 mujoco==3.3.0 glfw==2.11.0 PyOpenGL==3.1.10 \
        gymnasium==1.4.0 Farama-Notifications==0.0.6 imageio==2.38.2 etils==1.15.0 ;;
    *) echo "unknown simulator $sim (pusht, metaworld)" >&2; exit 2 ;;
  esac
done
du -sh .whl/core .whl/sim
