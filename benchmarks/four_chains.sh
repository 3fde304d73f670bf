#!/usr/bin/env bash
# 50M-step robot runs on a machine of several GPUs (nvidia-h100-x4: four), one chain of
# benchmarks/runs_50m.sh per GPU, started in the background (benchmarks/chain.sh) from a copy
# of the checkout in /root/code, after benchmarks/warp_gpu.sh installed Warp and unpacked the
# robots into /tmp/men (and exported MEN=/tmp/men). Device time counts a machine's held time,
# not its GPUs: four chains cost what one does.
#   bash benchmarks/four_chains.sh start CHAIN...  chain k runs on GPU k; a CHAIN is segments
#        separated by ';', each 'PRESET:SEED ...' with '@FLAGS' for train flags of its own
#   bash benchmarks/four_chains.sh collect         $OUT/runs.tgz: every finished run, the
#        metrics of those in progress, the chains' logs; then each run's last two lines
# The runs live only as long as the lease: a host goes back when idle (30 s after a call ends,
# on 2026-11-28), so the call that waits for them (benchmarks/chain.sh wait gpuK SECONDS, then
# collect) must follow the one that started them at once; on 2026-11-28 a late one found a fresh
# host and four G1 runs were lost at 24.6M steps.
# Segment s of chain k lands in /root/done/k-s/PRESET-sSEED (runs in /root/runs/k-s); a start
# that would reuse such a folder is refused, as are more chains than GPUs. FLAGS are split at
# spaces as runs_50m.sh's EXTRA is (no value with a space in it). The tenth session's four
# chains ("rb": FlashSAC's return scaling; `g1` had the plain critics then: today add
# --critic-network mlp --critic-hidden-sizes 1024 512 256 --weight-decay 0.1 to repeat them):
#   rb='--return-bound 5 --v-min -5 --v-max 5'
#   bash benchmarks/four_chains.sh start 't1:2 g1:1' "g1:0 g1:1@$rb" "g1:2; g1:2@$rb" \
#     't1-rough:1 t1-rough:2'
set -uo pipefail
segment_command() {  # segment_command CHAIN SEGMENT TEXT: the shell command of one segment
  local runs=${3%%@*} flags=""
  [[ $3 == *@* ]] && flags=${3#*@}
  printf "DONE=/root/done/%s-%s RUNS=/root/runs/%s-%s EXTRA=%q bash benchmarks/runs_50m.sh %s" \
    "$1" "$2" "$1" "$2" "$flags" "$runs"
}
check() {  # check CHAIN...: as many chains as GPUs at most, no earlier run's folders
  local gpus
  gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU')
  if [ "$#" -gt "$gpus" ]; then echo "four_chains: $# chains for $gpus GPUs"; exit 2; fi
  if compgen -G "/root/done/*" >/dev/null || compgen -G "/root/runs/*" >/dev/null; then
    echo "four_chains: /root/done or /root/runs holds an earlier start's runs; move them away"
    exit 2
  fi
}
start() {  # start CHAIN...: chain k in the background on GPU k
  cd /root/code || { echo "four_chains: copy the checkout to /root/code first"; exit 2; }
  check "$@"
  local k=0 s segments command
  for chain in "$@"; do
    IFS=';' read -ra segments <<<"$chain"
    command=""
    for s in "${!segments[@]}"; do
      command+="$(segment_command "$k" "$s" "${segments[$s]}"); "
    done
    CUDA_VISIBLE_DEVICES=$k bash benchmarks/chain.sh start "gpu$k" bash -c "$command"
    k=$((k + 1))
  done
}
case ${1:?start or collect} in
  start)
    shift
    [ $# -gt 0 ] || { echo "four_chains: start needs a chain per GPU"; exit 2; }
    start "$@" ;;
  collect)
    cd /root || exit 2
    shopt -s nullglob
    files=(done chains/*.log runs/*/*/metrics.jsonl runs/*/*/config.json)
    [ -d done ] || files=("${files[@]:1}")
    if [ ${#files[@]} -gt 0 ]; then tar -czf "$OUT/runs.tgz" "${files[@]}"; else echo "nothing yet"; fi
    for log in done/*/*/train.log; do echo "== $log"; tail -n 2 "$log"; done
    nvidia-smi --query-gpu=index,name,utilization.gpu,memory.used --format=csv,noheader ;;
  *) echo "four_chains: start or collect, not $1"; exit 2 ;;
esac
