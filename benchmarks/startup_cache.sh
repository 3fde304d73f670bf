#!/usr/bin/env bash
# Start-up of td3-jax train's programs per preset, each timed from its process launch
# (benchmarks/startup.py), in one command on one GPU (GPU=k, default 0):
#   floor  - the bare physics jit(scan(vmap(env.step))), traced and compiled (no cache)
#   plain  - no caches: the programs traced and compiled as jitted functions
#   cold   - empty caches: traced, exported into DIR/programs, compiled into DIR
#   warm   - a second process on the same caches: programs and executables read back
# plain and warm then time LOOP_CHUNKS whole chunks (default 2; 0: none) for the loop's rate.
# Usage: benchmarks/startup_cache.sh OUT PRESET [PRESET ...]; writes OUT/PRESET.jsonl.
set -uo pipefail
out=$1
shift
mkdir -p "$out"
export CUDA_VISIBLE_DEVICES=${GPU:-0}
loops=${LOOP_CHUNKS:-2}
launch() {  # launch NAME ARGS...: one process, one JSON line (its stderr in NAME.log)
  local name=$1
  shift
  TD3_LAUNCH=$(date +%s.%N) python3 benchmarks/startup.py "$@" 2> "$out/$name.log" | tail -n 1
}
for preset in "$@"; do
  cache=$(mktemp -d)
  {
    launch "${preset}_floor" --preset "$preset" --floor
    launch "${preset}_plain" --preset "$preset" --loop-chunks "$loops"
    launch "${preset}_cold" --preset "$preset" --cache "$cache"
    launch "${preset}_warm" --preset "$preset" --cache "$cache" --loop-chunks "$loops"
  } | tee "$out/$preset.jsonl"
  du -sh "$cache" "$cache/programs" >> "$out/$preset.jsonl.sizes"
  rm -rf "$cache"
done
