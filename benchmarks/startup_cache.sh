#!/usr/bin/env bash
# Start-up of td3-jax train's programs per preset, each timed from its process launch, in one
# command on one GPU (GPU=k, default 0). MODES (default "floor plain cold warm cli") picks:
#   floor  - the bare physics jit(scan(vmap(env.step))), traced and compiled (no cache)
#   plain  - no caches: the programs traced and compiled as jitted functions
#   cold   - empty caches: traced, exported into DIR/programs, compiled into DIR
#   warm   - a second process on the same caches: programs and executables read back
#   cli    - `python3 -m td3_jax train --preset P` itself, on empty caches and again on the same
#            ones: seconds from launch until its first record is in metrics.jsonl
# floor..warm run benchmarks/startup.py; plain and warm then time LOOP_CHUNKS whole chunks
# (default 2; 0: none) for the loop's env steps/s.
# Usage: benchmarks/startup_cache.sh OUT PRESET [PRESET ...]; writes OUT/PRESET.jsonl.
set -uo pipefail
out=$1
shift
mkdir -p "$out"
export CUDA_VISIBLE_DEVICES=${GPU:-0}
loops=${LOOP_CHUNKS:-2}
modes=${MODES:-floor plain cold warm cli}
launch() {  # launch NAME ARGS...: one startup.py process, one JSON line (stderr in NAME.log)
  local name=$1
  shift
  TD3_LAUNCH=$(date +%s.%N) python3 benchmarks/startup.py "$@" 2> "$out/$name.log" | tail -n 1
}
first_record() {  # first_record NAME PRESET CACHE: the command's first record, from launch
  local name=$1 preset=$2 cache=$3 start pid seen end
  start=$(date +%s.%N)
  python3 -m td3_jax train --preset "$preset" --out "$out/runs/$name" --compile-cache "$cache" \
    --total-steps 1 --quiet > "$out/$name.log" 2>&1 &
  pid=$!
  while [ ! -s "$out/runs/$name/metrics.jsonl" ] && kill -0 $pid 2> /dev/null; do sleep 0.05; done
  seen=$(date +%s.%N)
  wait $pid
  local rc=$?
  end=$(date +%s.%N)
  python3 -c "print('{\"mode\": \"$name\", \"first_record_from_launch\": %.2f, \"process_s\": %.2f, \"rc\": $rc}' % ($seen - $start, $end - $start))"
}
for preset in "$@"; do
  cache=$(mktemp -d) cli_cache=$(mktemp -d)
  {
    [[ " $modes " == *" floor "* ]] && launch "${preset}_floor" --preset "$preset" --floor
    [[ " $modes " == *" plain "* ]] && launch "${preset}_plain" --preset "$preset" --loop-chunks "$loops"
    [[ " $modes " == *" cold "* ]] && launch "${preset}_cold" --preset "$preset" --cache "$cache"
    [[ " $modes " == *" warm "* ]] && launch "${preset}_warm" --preset "$preset" --cache "$cache" \
      --loop-chunks "$loops"
    if [[ " $modes " == *" cli "* ]]; then
      first_record "${preset}_cli_cold" "$preset" "$cli_cache"
      first_record "${preset}_cli_warm" "$preset" "$cli_cache"
    fi
  } | tee "$out/$preset.jsonl"
  du -sh "$cache" "$cache/programs" "$cli_cache" >> "$out/$preset.jsonl.sizes" 2> /dev/null
  rm -rf "$cache" "$cli_cache"
done
