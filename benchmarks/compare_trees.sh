#!/usr/bin/env bash
# Start-up and full-loop throughput of two source trees side by side, each on its own GPU of one
# host (one after the other on a one-GPU host), in one command (GPU hosts differ; compare only
# within one run). Usage, from the repo root:
#   benchmarks/compare_trees.sh BEFORE_DIR [PRESET]   (BEFORE_DIR holds td3_jax/ and benchmarks/)
# Writes $OUT/{before,after}_{startup.json,throughput.jsonl,*.log}; prints a short table.
set -uo pipefail
before=$1; preset=${2:-ant}; out=${OUT:-.}
site=${SITE:-/tmp/site}
measure() {  # name tree gpu
  local name=$1 tree=$2 gpu=$3
  (
    cd "$tree" || exit 1
    export CUDA_VISIBLE_DEVICES=$gpu PYTHONPATH=$site:$PWD
    t0=$(date +%s.%N)
    python3 benchmarks/startup.py --preset "$preset" > "$out/${name}_startup.json" 2> "$out/${name}_startup.log"
    t1=$(date +%s.%N)
    python3 -c "print({\"process_wall_s\": round($t1 - $t0, 2)})" >> "$out/${name}_startup.json"
    python3 benchmarks/throughput.py --preset "$preset" --envs --batches \
      --skip raw raw_random wrapped wrapped_random loop updates \
      --out "$out/${name}_throughput.jsonl" > "$out/${name}_throughput.log" 2>&1
  )
}
if [ "$(nvidia-smi -L | wc -l)" -ge 2 ]; then
  measure before "$before" 0 & measure after "$PWD" 1 & wait
else  # one GPU: one after the other
  measure before "$before" 0; measure after "$PWD" 0
fi
for name in before after; do
  echo "== $name"; cat "$out/${name}_startup.json"; cat "$out/${name}_throughput.jsonl"
done
