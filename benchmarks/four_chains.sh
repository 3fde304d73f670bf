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
#   bash benchmarks/four_chains.sh watch SECONDS   collect every 40 s until the chains end or
#        SECONDS pass (each call after the start: `watch 590`, issued at once)
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
here=$(cd "$(dirname "$0")" && pwd)
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
pack() {  # $OUT/runs.tgz: every finished run, the metrics of those in progress, the logs
  (
    cd /root || exit 2
    shopt -s nullglob
    files=(done chains/*.log runs/*/*/metrics.jsonl runs/*/*/config.json)
    [ -d done ] || files=("${files[@]:1}")
    [ ${#files[@]} -gt 0 ] || exit 1
    tar -czf "$OUT/runs.tgz.part" "${files[@]}"
    rc=$?  # (1: a file changed while read, as logs do: the archive is still good)
    if [ $rc -le 1 ]; then mv "$OUT/runs.tgz.part" "$OUT/runs.tgz"; else rm -f "$OUT/runs.tgz.part"; exit 2; fi
  )
}
any_alive() {  # exit 0 while a chain started here still runs
  local pid
  for pid in /root/chains/gpu*.pid; do
    [ -e "$pid" ] || continue
    bash "$here/chain.sh" alive "$(basename "$pid" .pid)" && return 0
  done
  return 1
}
case ${1:?start, collect or watch} in
  start)
    shift
    [ $# -gt 0 ] || { echo "four_chains: start needs a chain per GPU"; exit 2; }
    start "$@" ;;
  collect)
    pack || echo "nothing yet"
    cd /root || exit 2
    for log in done/*/*/train.log; do echo "== $log"; tail -n 2 "$log"; done
    nvidia-smi --query-gpu=index,name,utilization.gpu,memory.used --format=csv,noheader ;;
  watch)
    # watch SECONDS: until every chain has ended or SECONDS pass, $OUT/runs.tgz is packed anew
    # every 40 s, so a call stopped at its limit (or by the session's device time) still
    # brings back the runs' records up to 40 s before; then a collect. Make each following
    # call this at once (the host goes back 30 s after a call ends).
    deadline=$(( $(date +%s) + ${2:?seconds} )) packed=0
    if ! compgen -G "/root/chains/gpu*.pid" >/dev/null; then
      echo "four_chains: no chain was started on this host (a fresh host: the runs were lost?)"
      exit 2
    fi
    while any_alive && [ "$(date +%s)" -lt "$deadline" ]; do
      sleep 2
      if [ $(( $(date +%s) - packed )) -ge 40 ]; then pack >/dev/null 2>&1; packed=$(date +%s); fi
    done
    any_alive && echo "four_chains: chains still running" || echo "four_chains: every chain ended"
    bash "$here/four_chains.sh" collect ;;
  *) echo "four_chains: start, collect or watch, not $1"; exit 2 ;;
esac
