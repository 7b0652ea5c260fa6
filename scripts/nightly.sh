#!/usr/bin/env bash
# Slow checks (50-seed expert tables) and the benchmarks.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/pip install -q --disable-pip-version-check -e ".[dev,ray]"  # the Ray backend's slow tests
.venv/bin/python -m pytest -q -m slow "$@"
.venv/bin/python -m dust_rl.benchmarks.env_speed
.venv/bin/python -m dust_rl.benchmarks.env_speed --env DustHumanoid-v0 --tasks pick_place lift_box
