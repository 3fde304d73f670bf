#!/usr/bin/env bash
# 53.2M-step runs of the robot presets, one after another, each in one process, for
# `benchmarks/chain.sh start NAME bash benchmarks/runs_50m.sh ...` on the GPU machine (after
# benchmarks/warp_gpu.sh installed Warp; run from a copy of the checkout outside it, e.g.
# /root/code, since each device command replaces the checkout). Each finished (or failed)
# run's log (each line timed from launch), metrics.jsonl and config.json are copied at once to
# $DONE/PRESET-sSEED/, so a command that polls need only copy $DONE off the machine.
#   bash benchmarks/runs_50m.sh t1:0 t1:2 t1-rough:1      (PRESET:SEED ...)
# Environment: MEN (the robots' assets, default /tmp/men), DONE (default /root/done),
# STEPS (default 53248000: 13 chunks of 4.096M), EXTRA (more `train` flags, e.g. --pushes on).
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
men=${MEN:-/tmp/men}
done_dir=${DONE:-/root/done}
# Warp's start-up notes (its version, devices, kernel cache, module loads), not errors naming Warp.
warp_notes='Warp [0-9.]* initialized\|Module .* load on device\|warp.config\|Kernel cache\|/root/.cache/warp\|Devices:\|"cpu"\|"cuda:0"\|CUDA Toolkit'
for run in "$@"; do
  preset=${run%%:*}
  seed=${run##*:}
  name=$preset-s$seed
  out=/root/runs/$name
  mkdir -p "$done_dir/$name"
  # shellcheck disable=SC2086
  bash "$here/timed_train.sh" --preset "$preset" --impl warp --menagerie "$men" --out "$out" \
    --seed "$seed" --total-steps "${STEPS:-53248000}" ${EXTRA:-} 2>&1 \
    | grep --line-buffered -v "$warp_notes" >"$done_dir/$name/train.log"
  cp "$out/metrics.jsonl" "$out/config.json" "$done_dir/$name/" 2>/dev/null
  echo "$name ended: $(tail -n 1 "$done_dir/$name/train.log")"
done
