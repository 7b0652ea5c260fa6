#!/usr/bin/env bash
# Sets up everything dust-rl needs in a project-local virtualenv (.venv).
# Idempotent: a second run only checks a stamp and returns in seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
VENV=.venv
STAMP=$VENV/.dust-rl-install-stamp

# Headless OpenGL: EGL (Mesa llvmpipe) preferred, OSMesa as the fallback.
if ! ldconfig -p | grep -qE 'libEGL\.so\.1|libOSMesa\.so'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[setup] installing Mesa EGL/OSMesa libraries"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
      libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 >/dev/null
  else
    echo "[setup] warning: no libEGL/libOSMesa found; install libegl1 libgl1-mesa-dri (or libosmesa6) for rendering" >&2
  fi
fi

[ -x $VENV/bin/python ] || "$PYTHON" -m venv $VENV
# pyproject.toml asks for ranges; constraints.txt holds the exact versions the project is tested with.
# A change to either reinstalls.
want=$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)
if [ "$(cat $STAMP 2>/dev/null)" != "$want" ]; then
  echo "[setup] installing Python packages into $VENV (first run: ~2 minutes)"
  # torch first, at its exact version from constraints.txt: a loose requirement would pull a multi-GB CUDA build.
  $VENV/bin/pip install -q --disable-pip-version-check -c constraints.txt torch
  $VENV/bin/pip install -q --disable-pip-version-check -c constraints.txt -e ".[dev]"
  $VENV/bin/python -c "import torch; assert torch.version.cuda is None, 'expected the CPU build of torch'" \
    || echo "[setup] note: a CUDA build of torch is installed" >&2
  echo "$want" > $STAMP
fi
