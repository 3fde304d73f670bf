"""Wall-clock of K seeds trained in one program, at a fixed per-seed budget.

For each K, runs ``td3_jax.runner.run.train`` with ``seeds=K`` (compile included, no progress
display, checkpoint only at the end) and reports the wall-clock, the compiled time of one chunk, and
the final mean evaluation return with its 95% bootstrap CI over seeds.

Usage: python -m benchmarks.seeds --preset pendulum --seeds 1 4 16 64 --out seeds.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time

import jax

from td3_jax.config.presets import preset
from td3_jax.runner.run import train


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="pendulum")
    parser.add_argument("--env", default=None)
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 4, 16, 64])
    parser.add_argument("--total-steps", type=int, default=None)
    parser.add_argument("--num-envs", type=int, default=None)
    parser.add_argument("--out", default="seeds.jsonl")
    args = parser.parse_args()
    base = preset(args.preset)
    changes = {"checkpoint_every": 10**9}
    for name in ("env", "total_steps", "num_envs"):
        if getattr(args, name) is not None:
            changes[name] = getattr(args, name)
    base = dataclasses.replace(base, **changes)
    for k in args.seeds:
        cfg = dataclasses.replace(base, seeds=k)
        with tempfile.TemporaryDirectory() as out:
            start = time.perf_counter()
            records = train(cfg, out, progress=False)
            wall = time.perf_counter() - start
        last = records[-1]
        chunk_s = [r["env_steps"] for r in records]
        row = {
            "env": cfg.env,
            "preset": args.preset,
            "seeds": k,
            "num_envs_per_seed": cfg.num_envs,
            "env_steps_per_seed": last["env_steps"],
            "wall_s_compile_included": wall,
            "env_steps_per_s_all_seeds_last_chunk": last["env_steps_per_s"],
            "final_eval_return_mean": last["eval_return_mean"],
            "final_eval_return_ci95": [
                last.get("eval_return_ci95_low", last["eval_return_mean"]),
                last.get("eval_return_ci95_high", last["eval_return_mean"]),
            ],
            "evaluations": len(chunk_s),
            "device": jax.devices()[0].device_kind,
            "jax": jax.__version__,
        }
        print(json.dumps(row), flush=True)
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
