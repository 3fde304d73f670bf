#!/usr/bin/env bash
# 53.2M-step runs of the robot presets, one after another, each in one process, for
# `benchmarks/chain.sh start NAME bash benchmarks/runs_50m.sh ...` on the GPU machine (after
# benchmarks/warp_gpu.sh installed Warp; from a copy of the checkout outside it, e.g.
# /root/code, since each device command replaces the checkout). Each run's log (each line timed
# from launch; Warp's start-up notes included) streams to $DONE/PRESET-sSEED/train.log, and its
# metrics.jsonl and config.json are copied there as it ends, with its exit status in the
# "ended" line: a command that polls copies one folder, and a machine that goes back loses at
# most the run in progress (whose records stay in /root/runs/PRESET-sSEED until then).
#   bash benchmarks/runs_50m.sh t1:0 t1:2 t1-rough:1      (PRESET:SEED ...)
# Environment: MEN (the robots' assets, default /tmp/men), DONE (default /root/done), RUNS
# (the runs' folders, default /root/runs),
# STEPS (default 53248000: 13 chunks of 4.096M), EXTRA (more `train` flags, e.g. --pushes on),
# KEEP (1 keeps each run's checkpoints; by default those of a run that finished are removed:
# only the records come back, and four runs' rings, 15-46 GB each, would fill the machine's
# disk; a run that failed or was stopped keeps them for a --resume).
# On a machine of two GPUs, two chains run side by side, one a GPU, each with its own DONE:
#   CUDA_VISIBLE_DEVICES=0 DONE=/root/done0 RUNS=/root/runs0 \
#     bash benchmarks/chain.sh start a bash benchmarks/runs_50m.sh g1:1
#   CUDA_VISIBLE_DEVICES=1 DONE=/root/done1 RUNS=/root/runs1 \
#     EXTRA='--return-bound 5 --v-min -5 --v-max 5' \
#     bash benchmarks/chain.sh start b bash benchmarks/runs_50m.sh g1:1
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
cd "$here/.." || exit 2
for run in "$@"; do
  [[ $run =~ ^[a-z0-9-]+:[0-9]+$ ]] || { echo "runs_50m: '$run' is not PRESET:SEED"; exit 2; }
done
done_dir=${DONE:-/root/done}
for run in "$@"; do
  preset=${run%%:*}
  seed=${run##*:}
  name=$preset-s$seed
  out=${RUNS:-/root/runs}/$name
  mkdir -p "$done_dir/$name"
  # shellcheck disable=SC2086
  bash benchmarks/timed_train.sh --preset "$preset" --impl warp --menagerie "${MEN:-/tmp/men}" \
    --out "$out" --seed "$seed" --total-steps "${STEPS:-53248000}" ${EXTRA:-} \
    >"$done_dir/$name/train.log" 2>&1
  status=$?
  cp "$out/metrics.jsonl" "$out/config.json" "$done_dir/$name/" 2>/dev/null
  [ "${KEEP:-0}" = 1 ] || [ "$status" != 0 ] || rm -rf "$out/checkpoints"
  echo "$name ended with exit status $status: $(tail -n 1 "$done_dir/$name/train.log")"
done
