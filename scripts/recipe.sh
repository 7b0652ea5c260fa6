#!/usr/bin/env bash
# Collect, train a named recipe, then evaluate on 50 validation and 50 held-out episodes. The recipe is `action-only`
# (pick_place from 2,000 demonstrations, docs/franka_results.md, "The recipe at 50 episodes per seed set"; `dust-rl
# train --help` lists them) unless the flags after RUN, added to `dust-rl train`, name another (`--recipe
# pick-place-readout`, README rows 2-9). STEPS=N trains N steps instead of 20,000. Every stage resumes: rerun the
# same command after an interruption.
# usage: [STEPS=N] bash scripts/recipe.sh TASK DEMOS [RUN [TRAIN FLAGS...]]
#   (RUN default: TASK_DEMOS_ao75_STEPS; 20,000 steps take ~2 h on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${STEPS:-20000}
task=$1 demos=$2 run=${3:-${1}_${2}_ao75_${steps}}
data=runs/data/${task}_${demos}
out=runs/train/$run
.venv/bin/dust-rl collect --task "$task" --episodes "$demos" --out "$data" --workers 1 --runtime.no-progress
if [ ! -f "$out/policy.pt" ]; then
  resume=()
  [ -f "$out/config.json" ] && resume=(--resume)
  .venv/bin/dust-rl train --recipe action-only --dataset "$data" --out "$out" --optim.steps "$steps" --runtime.threads 1 \
    --runtime.no-progress "${resume[@]}" "${@:4}"
fi
for seed in 5000 10000; do
  eval_out=runs/eval/${run}_seed$seed
  [ -f "$eval_out/report.json" ] || .venv/bin/dust-rl eval --policy "$out/policy.pt" --out "$eval_out" \
    --episodes 50 --seed $seed --workers 1 --runtime.threads 1 --videos 2 --runtime.no-progress
done
