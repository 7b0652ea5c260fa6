#!/usr/bin/env bash
# The README's per-task table: for each Franka task, 200 expert demonstrations, the 3,000-step recipe, and
# 20 held-out episodes (seeds 10000..10019). Every stage resumes, so rerunning continues where it stopped.
# TASKS="push stack" bash scripts/franka_table.sh runs a subset; extra args go to `dust-rl train`.
set -euo pipefail
cd "$(dirname "$0")/.."
for task in ${TASKS:-open_drawer close_drawer press_button push pick_place stack peg_insert pick_into_bin}; do
  .venv/bin/dust-rl collect --task "$task" --episodes 200 --out "runs/data/$task" --workers 1 --runtime.no-progress
  if [ ! -f "runs/train/$task/policy.pt" ]; then
    resume=()
    [ -f "runs/train/$task/config.json" ] && resume=(--resume)
    .venv/bin/dust-rl train --recipe defaults --dataset "runs/data/$task" --out "runs/train/$task" --optim.steps 3000 \
      --optim.lr 3e-4 --runtime.threads 1 --runtime.no-progress "${resume[@]}" "$@"
  fi
  [ -f "runs/eval/$task/report.json" ] || .venv/bin/dust-rl eval --policy "runs/train/$task/policy.pt" \
    --out "runs/eval/$task" --episodes 20 --workers 1 --runtime.no-progress
done
