#!/usr/bin/env bash
# Runs td3-jax settings variants side by side, one queue of variants per GPU of one host, each
# through benchmarks/compare.py (td3 only, compile included, same budget), and prints a summary.
#
# Usage: benchmarks/variants.sh ENV BUDGET_S OUT "FLAGS OF GPU0 VARIANT 1;FLAGS ..." "GPU1 ..." ...
#   e.g. benchmarks/variants.sh ant 90 /tmp/v "n_step=1;n_step=3" "n_step=3 tau=0.01"
# FIRST_GPU=k starts the queues at GPU k. Each quoted argument is one GPU's queue: variants separated by ';', each a list of
# KEY=VALUE td3-jax settings (applied on top of the env's preset).
set -u
env=$1 budget=$2 out=$3
shift 3
mkdir -p "$out"
gpu=${FIRST_GPU:-0}
for queue in "$@"; do
  (
    IFS=';' read -ra variants <<<"$queue"
    for flags in "${variants[@]}"; do
      name=$(echo "$flags" | tr ' =' '_-')
      # shellcheck disable=SC2086
      CUDA_VISIBLE_DEVICES=$gpu python3 benchmarks/compare.py --env "$env" --budget-s "$budget" \
        --algos td3 --td3-flag total_steps=1000000000 $flags --out "$out/$name" \
        >"$out/$name.log" 2>&1
      echo "== $flags (GPU $gpu, exit $?)"
      grep '^\[td3\] ' "$out/$name.log" | tail -n 12
    done
  ) >"$out/gpu$gpu.txt" &
  gpu=$((gpu + 1))
done
wait
cat "$out"/gpu*.txt
