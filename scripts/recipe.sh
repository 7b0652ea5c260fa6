#!/usr/bin/env bash
# The recipe that solves pick_place from 2,000 demonstrations (docs/franka_results.md, "The recipe at 50 episodes per seed set"):
# stride-8 EfficientNet-Lite0 tokens pooled to 8x8 per camera, text fusion, the action-only trunk, 75% of the
# batches from the first 4 rows of an episode, 20,000 steps; then 50 validation and 50 held-out episodes.
# STEPS=N trains N steps instead; flags after RUN are added to `dust-rl train` (e.g. the token read-out's,
# docs/franka_results.md, "The token read-out"). Every stage resumes: rerun the same command after an interruption.
# usage: [STEPS=N] bash scripts/recipe.sh TASK DEMOS [RUN [TRAIN FLAGS...]]
#   (RUN default: TASK_DEMOS_ao75_STEPS; 20,000 steps take ~2 h on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${STEPS:-20000}
task=$1 demos=$2 run=${3:-${1}_${2}_ao75_${steps}}
data=runs/data/${task}_${demos}
out=runs/train/$run
.venv/bin/dust-rl collect --task "$task" --episodes "$demos" --out "$data" --workers 1 --no-progress
if [ ! -f "$out/policy.pt" ]; then
  resume=()
  [ -f "$out/config.json" ] && resume=(--resume)
  .venv/bin/dust-rl train --recipe plain --dataset "$data" --out "$out" --optim.steps "$steps" --optim.lr 3e-4 --runtime.threads 1 \
    --policy.image-encoder efficientnet-lite0-s8 --policy.cond-grid 8 8 --policy.text-fusion --data.start-rows 4 \
    --data.start-fraction 0.75 --policy.variant action_only --logging.checkpoint-every 2000 --runtime.no-progress "${resume[@]}" "${@:4}"
fi
for seed in 5000 10000; do
  eval_out=runs/eval/${run}_seed$seed
  [ -f "$eval_out/report.json" ] || .venv/bin/dust-rl eval --policy "$out/policy.pt" --out "$eval_out" \
    --episodes 50 --seed $seed --workers 1 --threads 1 --videos 2 --no-progress
done
