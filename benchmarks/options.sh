#!/usr/bin/env bash
# Issue 14: today's preset against the FastTD3-class options on one environment, one variant per
# GPU of one host (4 GPUs), each through benchmarks/compare.py with the same wall-clock budget
# (compile included), via benchmarks/variants.sh. Prints each variant's return over time.
#
# Usage: benchmarks/options.sh ENV BUDGET_S OUT      e.g. benchmarks/options.sh ant 300 /tmp/opt_ant
#   GPU 0: the preset as it is today
#   GPU 1: + distributional critic (C51, 101 atoms on [V_MIN, V_MAX])
#   GPU 2: + FastTD3's other options: wide networks, AdamW 0.1, per-env noise 0.001-0.4,
#          no target actor, bf16 matmuls
#   GPU 3: everything of 1 and 2 together
# V_MIN/V_MAX (environment variables) set the C51 support; the defaults cover Brax ant and
# humanoid discounted returns (rewards of a few units per step, discount 0.99).
set -u
env=$1 budget=$2 out=$3
vmin=${V_MIN:--200} vmax=${V_MAX:-1200}
c51="critic=distributional num_atoms=101 v_min=$vmin v_max=$vmax"
rest="actor_hidden_sizes=512,256,128 critic_hidden_sizes=1024,512,256 weight_decay=0.1"
rest="$rest expl_noise_min=0.001 expl_noise_max=0.4 target_actor=false precision=bfloat16"
exec "$(dirname "$0")/variants.sh" "$env" "$budget" "$out" "n_step=3" "$c51" "$rest" "$c51 $rest"
