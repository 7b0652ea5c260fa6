#!/usr/bin/env bash
# Runs `dust-rl bench gpu` on a GPU machine without network access, from gpu_bundle/ (scripts/gpu_bundle.sh
# builds it where there is network). That machine's python3 must have torch with CUDA, numpy, transformers
# and safetensors; the rest comes from the bundle's wheels into a folder of their own (SITE).
# Usage: bash scripts/gpu_check.sh [dust-rl bench gpu arguments, e.g. --out /tmp/gpu_check --budget-s 300]
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bundle=$root/gpu_bundle
site=${SITE:-/tmp/dust_rl_site}
menagerie=/tmp/dust_rl_menagerie

python3 -m pip install -q --disable-pip-version-check --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target "$site" "$bundle"/wheels/*.whl
if ! ldconfig -p | grep -q 'libEGL\.so\.1'; then  # headless rendering needs the GL vendor-neutral loaders
  for deb in "$bundle"/debs/*.deb; do dpkg -x "$deb" /; done
  ldconfig
fi
nvidia_egl=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
if [ -f $nvidia_egl ] && [ -z "${__EGL_VENDOR_LIBRARY_FILENAMES:-}" ]; then
  export __EGL_VENDOR_LIBRARY_FILENAMES=$nvidia_egl
fi
mkdir -p $menagerie && tar -xJf "$bundle/franka.tar.xz" -C $menagerie
export PYTHONPATH=$site MENAGERIE_ROOT=$menagerie MUJOCO_GL=${MUJOCO_GL:-egl}
cd /tmp  # import the installed package, not the checkout's source folders (whose layout needs installing)
exec python3 -m dust_rl.cli bench gpu --text-encoder "$bundle/text_encoder" "$@"
