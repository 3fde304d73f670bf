#!/usr/bin/env bash
# A Playground robot task (T1JoystickFlatTerrain, G1JoystickFlatTerrain, ...): td3-jax (its
# preset) and Brax PPO (Playground's locomotion_params settings for the task) side by side, each
# on its own GPU of one host, each clocked from its own process launch, then merged into one
# CSV/plot/JSON/table with FastTD3's published curve drawn on the plot (benchmarks/compare.py).
#
# Usage: benchmarks/robots_compare.sh OUT TASK BUDGET_S [--td3-flag KEY=VALUE ...]
#   Robot assets: MENAGERIE_ROOT, or .assets/<robot>.tar.xz (benchmarks/robots.py --pack) which
#   this script unpacks into a temporary Menagerie root.
#   td3-jax keeps a checkpoint (compare.py --td3-checkpoint) in OUT/TASK/td3_TASK, so
#   `td3-jax render` / `td3-jax export` can follow in the same command.
set -u
out=$1 task=$2 budget=$3
shift 3
if [ -z "${MENAGERIE_ROOT:-}" ] && ls .assets/*.tar.xz >/dev/null 2>&1; then
  MENAGERIE_ROOT=$(mktemp -d)
  for archive in .assets/*.tar.xz; do tar -xJf "$archive" -C "$MENAGERIE_ROOT"; done
  export MENAGERIE_ROOT
fi
mkdir -p "$out/$task"
limit=$((${budget%.*} + 240))
CUDA_VISIBLE_DEVICES=0 timeout "$limit" python3 benchmarks/compare.py --env "$task" \
  --budget-s "$budget" --algos td3 --td3-checkpoint --num-evals 0 "$@" --out "$out/$task" \
  >"$out/$task-td3.log" 2>&1 &
CUDA_VISIBLE_DEVICES=1 timeout "$limit" python3 benchmarks/compare.py --env "$task" \
  --budget-s "$budget" --algos ppo --num-evals 0 --out "$out/$task" \
  >"$out/$task-ppo.log" 2>&1 &
wait
grep -h -E '^\[(td3|ppo)\] .* return' "$out/$task-td3.log" "$out/$task-ppo.log" | tail -n 40
python3 benchmarks/compare.py --env "$task" --budget-s "$budget" --out "$out/$task" --merge \
  >"$out/$task-merge.log" 2>&1
tail -n 14 "$out/$task-merge.log"
