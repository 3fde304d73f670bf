#!/usr/bin/env bash
# Start-up (benchmarks/startup.py, cold compile cache, timed from launch) and full-loop throughput
# (benchmarks/throughput.py --skip all but full) of one preset under several XLA_FLAGS variants,
# one after the other on one GPU (GPU=k, default 0), in one command (compile time depends on
# the host).
# Usage: benchmarks/startup_flags.sh OUT PRESET NAME='FLAGS' [NAME='FLAGS' ...]
#   e.g. benchmarks/startup_flags.sh $OUT ant default= \
#          force16='--xla_gpu_force_compilation_parallelism=16'
# Each variant's XLA_FLAGS is exactly what is measured (unknown flags are fatal: check them on the
# jaxlib in use first). Writes OUT/PRESET_NAME_{startup.json,
# throughput.jsonl,*.log}; prints one line per variant. SKIP_THROUGHPUT=1: start-up only.
set -uo pipefail
out=$1 preset=$2
shift 2
mkdir -p "$out"
env_name=$(python3 -c "from td3_jax.config.presets import preset; print(preset('$preset').env)") || exit 1
for variant in "$@"; do
  name=${variant%%=*} flags=${variant#*=}
  base="$out/${preset}_${name}"
  export XLA_FLAGS="$flags" CUDA_VISIBLE_DEVICES=${GPU:-0}
  TD3_LAUNCH=$(date +%s.%N) python3 benchmarks/startup.py --preset "$preset" \
    > "$base.startup.json" 2> "$base.startup.log"
  [ -n "${SKIP_THROUGHPUT:-}" ] || python3 benchmarks/throughput.py --env "$env_name" --preset "$preset" --envs --batches \
    --skip raw raw_random wrapped wrapped_random loop updates \
    --out "$base.throughput.jsonl" > "$base.throughput.log" 2>&1
  echo "== $preset $name XLA_FLAGS='$flags'"
  tail -n 1 "$base.startup.json"
  tail -n 1 "$base.throughput.jsonl" 2>/dev/null
done
