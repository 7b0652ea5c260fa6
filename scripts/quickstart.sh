#!/usr/bin/env bash
# Sets everything up, then runs the main job on its small default: collect expert demonstrations,
# train DUST, evaluate it in closed loop, write the report. Extra args go to `dust-rl quickstart`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/dust-rl quickstart "$@"
