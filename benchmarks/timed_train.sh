#!/usr/bin/env bash
# `python3 -m td3_jax train "$@"` with every output line prefixed by the seconds since this
# script started (imports, environment creation and compiles included): start-up and time to a
# return "from launch". Not a terminal, so the run prints one line per evaluation.
#   bash benchmarks/timed_train.sh --preset t1 --impl warp --out /root/t1 --time-budget-s 300
set -uo pipefail
start=$(date +%s.%N)
python3 -m td3_jax train "$@" 2>&1 | while IFS= read -r line; do
  awk -v now="$(date +%s.%N)" -v t0="$start" -v text="$line" \
    'BEGIN { printf "%8.1f  %s\n", now - t0, text }'
done
exit "${PIPESTATUS[0]}"
