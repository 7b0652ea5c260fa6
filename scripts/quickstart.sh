#!/usr/bin/env bash
# Sets everything up, then runs the main job on its small default. Extra args go to it.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/dust-rl demo "$@"
