#!/usr/bin/env bash
# Long GPU jobs across several device commands, without splitting a run by --time-budget-s and
# --resume: a process started with `setsid nohup` outlives the device command that started it
# (seen 2026-11-25 on nvidia-h100-x1), as long as the machine stays held (a command in flight,
# or one started within its idle release). Staged outside the checkout, which each command
# replaces.
#   bash benchmarks/chain.sh start NAME CMD...   run CMD in the background; log /root/chains/NAME.log
#   bash benchmarks/chain.sh wait NAME SECONDS   until NAME ends or SECONDS pass; prints its exit
#                                                status once ended, and the log's tail
#   bash benchmarks/chain.sh alive NAME          exit 0 while NAME runs
#   bash benchmarks/chain.sh stop NAME           SIGTERM to NAME's whole process group (its
#                                                own, from setsid: the command and its children)
# A job has ended once its exit status is written (NAME.rc), or its process is gone: `pgrep -f
# NAME` also matches the device command's own shell, whose command line names NAME, and never
# says the job ended; `kill -0` alone still answers for a zombie nobody reaped.
set -uo pipefail
dir=/root/chains
mkdir -p "$dir"
what=${1:?start, wait, alive or stop}
name=${2:?a job name}
pidfile=$dir/$name.pid
rcfile=$dir/$name.rc
alive() { [ -f "$pidfile" ] && [ ! -f "$rcfile" ] && kill -0 "$(cat "$pidfile")" 2>/dev/null; }
case $what in
  start)
    shift 2
    [ $# -gt 0 ] || { echo "chain: start $name needs a command"; exit 2; }
    if alive; then echo "chain: $name runs already (pid $(cat "$pidfile"))"; exit 2; fi
    rm -f "$rcfile"
    echo "=== $(date -u +%FT%TZ) chain start: $*" >>"$dir/$name.log"
    # shellcheck disable=SC2016
    setsid nohup bash -c '"${@:2}"; echo $? >"$1"' chain "$rcfile" "$@" >>"$dir/$name.log" 2>&1 </dev/null &
    echo $! >"$pidfile"
    echo "chain: $name started (pid $!), log $dir/$name.log" ;;
  wait)
    deadline=$(( $(date +%s) + ${3:?seconds} ))
    while alive && [ "$(date +%s)" -lt "$deadline" ]; do sleep 2; done
    if alive; then echo "chain: $name still running"
    elif [ -f "$rcfile" ]; then echo "chain: $name ended with exit status $(cat "$rcfile")"
    else echo "chain: $name is gone without an exit status (killed?)"; fi
    tail -n 5 "$dir/$name.log" ;;
  alive) alive ;;
  stop)
    if alive; then kill -TERM -- "-$(cat "$pidfile")" && echo "chain: $name stopped"
    else echo "chain: $name is not running"; fi ;;
  *) echo "chain: start, wait, alive or stop, not $what"; exit 2 ;;
esac
