#!/usr/bin/env bash
# Slow checks (50-seed expert tables) and the benchmarks.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[dev,ray]"  # the Ray backend's slow tests
.venv/bin/python -m pytest -q -m slow "$@"
.venv/bin/python -m dust_rl.bench.env_speed
.venv/bin/python -m dust_rl.bench.env_speed --env DustHumanoid-v0 --tasks pick_place lift_box
# The RL fine-tuning table's from-scratch reference row (BENCHMARKS.md, "SB3 from scratch"): ~22 min on one core.
.venv/bin/python -m dust_rl.bench.sb3_scratch --task press_button --algorithm sac --steps 100000 \
  --eval-every 20000 --no-progress --out runs/bench/sb3_scratch/press_button_sac
