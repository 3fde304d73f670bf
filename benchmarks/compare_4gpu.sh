#!/usr/bin/env bash
# The side-by-side comparisons of BENCHMARKS.md on one host with 4 GPUs: every (env, algorithm)
# run of benchmarks/compare.py gets a GPU of its own (one run per GPU at a time, so no run shares
# a GPU), then --merge writes one CSV/plot/JSON/table per environment.
#
# Usage: benchmarks/compare_4gpu.sh OUT PART
#   PART a: ant, humanoid and CheetahRun with PPO, SAC and td3-jax (+ halfcheetah td3 variants
#           given as extra arguments, run as benchmarks/variants.sh queues on GPUs 1 and 2)
#   PART b: halfcheetah with PPO, SAC and td3-jax
set -u
out=$1 part=$2
shift 2
cmp() {  # GPU ENV BUDGET ALGOS...
  local gpu=$1 env=$2 budget=$3
  shift 3
  CUDA_VISIBLE_DEVICES=$gpu timeout $((budget * 2 + 150)) python3 benchmarks/compare.py \
    --env "$env" --budget-s "$budget" --algos "$@" --td3-flag total_steps=1000000000 \
    --out "$out/$env" >"$out/$env-$(echo "$@" | tr ' ' '-').log" 2>&1
}
mkdir -p "$out"
if [ "$part" = a ]; then
  (cmp 0 ant 120 ppo sac; cmp 0 humanoid 180 sac) &
  (cmp 1 ant 120 td3; cmp 1 CheetahRun 120 td3; [ $# -ge 1 ] && FIRST_GPU=1 \
    benchmarks/variants.sh halfcheetah 90 "$out/variants1" "$1" >"$out/variants1.txt") &
  (cmp 2 humanoid 180 ppo; cmp 2 CheetahRun 120 ppo; [ $# -ge 2 ] && FIRST_GPU=2 \
    benchmarks/variants.sh halfcheetah 90 "$out/variants2" "$2" >"$out/variants2.txt") &
  (cmp 3 humanoid 180 td3; cmp 3 CheetahRun 120 sac) &
  wait
  envs="ant humanoid CheetahRun"
else
  cmp 0 halfcheetah 120 ppo &
  cmp 1 halfcheetah 120 sac &
  cmp 2 halfcheetah 120 td3 &
  wait
  envs="halfcheetah"
fi
for env in $envs; do
  budget=120
  [ "$env" = humanoid ] && budget=180
  python3 benchmarks/compare.py --env "$env" --budget-s "$budget" --out "$out/$env" --merge \
    >"$out/$env-merge.log" 2>&1
  tail -n 12 "$out/$env-merge.log"
done
cat "$out"/variants*.txt 2>/dev/null
exit 0
