#!/usr/bin/env bash
# The tenth session's 50M-step runs on a four-GPU machine (nvidia-h100-x4), one chain of
# benchmarks/runs_50m.sh per GPU, started in the background (benchmarks/chain.sh) from a copy
# of the checkout in /root/code, after benchmarks/warp_gpu.sh installed Warp and unpacked the
# robots into /tmp/men. Each chain's finished runs land in /root/done/CHAIN/PRESET-sSEED.
#   bash benchmarks/four_chains.sh start     start the four chains
#   bash benchmarks/four_chains.sh collect   $OUT/runs.tgz: every finished run and the
#                                            metrics of those in progress, the chains' logs
# Return scaling ("rb") as FlashSAC: --return-bound 5 on a [-5, 5] C51 support.
set -uo pipefail
rb='--return-bound 5 --v-min -5 --v-max 5'
chain() {  # chain GPU NAME CMD: CMD on GPU, its runs in /root/done/NAME and /root/runs/NAME
  local gpu=$1 name=$2
  shift 2
  CUDA_VISIBLE_DEVICES=$gpu bash benchmarks/chain.sh start "$name" bash -c "$*"
}
case ${1:?start or collect} in
  start)
    cd /root/code || exit 2
    chain 0 a "DONE=/root/done/a RUNS=/root/runs/a bash benchmarks/runs_50m.sh t1:2 g1:1"
    chain 1 b "DONE=/root/done/b RUNS=/root/runs/b EXTRA='$rb' bash benchmarks/runs_50m.sh g1:0 g1:1"
    chain 2 c "DONE=/root/done/c RUNS=/root/runs/c bash benchmarks/runs_50m.sh g1:2;
      DONE=/root/done/c-rb RUNS=/root/runs/c-rb EXTRA='$rb' bash benchmarks/runs_50m.sh g1:2"
    chain 3 d "DONE=/root/done/d RUNS=/root/runs/d bash benchmarks/runs_50m.sh t1-rough:1 t1-rough:2" ;;
  collect)
    cd /root || exit 2
    tar -czf "$OUT/runs.tgz" done chains/*.log $(ls runs/*/*/metrics.jsonl runs/*/*/config.json 2>/dev/null)
    for log in done/*/*/train.log; do echo "== $log"; tail -n 2 "$log"; done
    nvidia-smi --query-gpu=index,name,utilization.gpu,memory.used --format=csv,noheader ;;
  *) echo "start or collect"; exit 2 ;;
esac
