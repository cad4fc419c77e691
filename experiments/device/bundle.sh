#!/usr/bin/env bash
# .device/ for experiments/device/run_full.sh (`make device-bundle`): the wheels that the
# device image (Python 3.12, JAX with CUDA, flax, optax, orbax, OpenCV, matplotlib, tqdm)
# lacks, at the versions this venv has, for CPython 3.12 on manylinux x86_64; a wheel built
# here where the index has only a source archive (pure Python: feetech-servo-sdk); and a copy
# of the lbipe folder (3 MB), since ../shared does not travel with the working tree.
set -euo pipefail
python=${1:?usage: bundle.sh VENV_PYTHON}
lbipe=${JAXINERTIA_LBIPE_DIR:-../shared/lbipe}
packages='mujoco|mujoco-core|mujoco-studio|glfw|pyopengl|websockets|mujoco-mjx|trimesh|dynamixel-sdk|pyserial|feetech-servo-sdk'
rm -rf .device && mkdir -p .device/wheels
for req in $("$python" -m pip freeze 2>/dev/null | grep -i -E "^($packages)==" ); do
  "$python" -m pip download --quiet --no-deps --only-binary=:all: --implementation cp \
      --python-version 3.12 --abi cp312 --platform manylinux_2_28_x86_64 \
      --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
      -d .device/wheels "$req" >/dev/null 2>&1 \
    || "$python" -m pip wheel --quiet --no-deps -w .device/wheels "$req" >/dev/null 2>&1 \
    || { echo "device-bundle: no wheel for $req" >&2; exit 1; }
done
n=$(ls .device/wheels/*.whl | wc -l)
[ "$n" -eq 11 ] || { echo "device-bundle: $n wheels, 11 expected" >&2; exit 1; }
[ -d "$lbipe/data" ] || { echo "device-bundle: no lbipe folder at $lbipe (JAXINERTIA_LBIPE_DIR)" >&2; exit 1; }
cp -r "$lbipe" .device/lbipe && chmod -R u+w .device/lbipe
echo "device-bundle: $n wheels and the lbipe folder in .device/ ($(du -sh .device | cut -f1)); carry [\".device\"]"
