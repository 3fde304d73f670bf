"""Data-parallel scaling of the full training loop over 1..D devices of one host.

Weak scaling: each device keeps ``--envs-per-device`` environments and ``--batch-per-device``
rows of every gradient batch, so D devices run D times the work of one. Reports, for each
device count, env steps/s and gradient updates/s of the compiled chunk (second call, compile
excluded) and the speed-up over one device measured in the same command.

Usage: python benchmarks/scaling.py --preset ant --devices 1 2 4 [--replay-shards 1] --out F
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import numpy as np

from td3_jax.config import preset
from td3_jax.population import compile_for_mesh, make_population, members
from td3_jax.sharding import make_mesh


def measure(cfg, num_devices: int) -> tuple[float, float]:
    mesh = make_mesh(num_devices)
    program = make_population(cfg, members(cfg), devices=mesh.size)
    compiled = compile_for_mesh(program, mesh)
    chunk = lambda s: compiled.chunk(compiled.hyperparams, s, np.int32(cfg.iters_per_chunk))
    state = compiled.init()
    state, metrics = chunk(state)  # compile + warm
    jax.block_until_ready(metrics)
    start = time.perf_counter()
    state, metrics = chunk(state)
    jax.block_until_ready(metrics)
    seconds = time.perf_counter() - start
    steps = cfg.iters_per_chunk * cfg.env_steps_per_iter
    updates = cfg.iters_per_chunk * cfg.updates_per_iter
    return steps / seconds, updates / seconds


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="ant")
    parser.add_argument("--devices", type=int, nargs="*", default=None)
    parser.add_argument("--envs-per-device", type=int, default=4096)
    parser.add_argument("--batch-per-device", type=int, default=8192)
    parser.add_argument("--iters", type=int, default=200)
    parser.add_argument(
        "--replay-shards",
        type=int,
        default=None,
        help="replay slices (default: the largest device count, so sampling is device-local)",
    )
    parser.add_argument("--out", default="scaling.jsonl")
    args = parser.parse_args()
    counts = args.devices or [n for n in (1, 2, 4, 8) if n <= jax.device_count()]
    base = preset(args.preset)
    shards = args.replay_shards or max(counts)
    rows, single = [], None
    for d in counts:
        n = args.envs_per_device * d
        cfg = dataclasses.replace(
            base,
            num_envs=n,
            batch_size=args.batch_per_device * d,
            warmup_steps=0,
            eval_every=n * args.iters,
            buffer_size=n * args.iters * 2,
            replay_shards=shards,
        )
        steps_per_s, updates_per_s = measure(cfg, d)
        single = single or (steps_per_s, updates_per_s)
        row = {
            "env": cfg.env,
            "devices": d,
            "num_envs": n,
            "batch_size": cfg.batch_size,
            "updates_per_iter": cfg.updates_per_iter,
            "replay_shards": shards,
            "env_steps_per_s": steps_per_s,
            "updates_per_s": updates_per_s,
            "speedup_env_steps": steps_per_s / single[0],
            "speedup_samples": updates_per_s * cfg.batch_size / (single[1] * args.batch_per_device),
            "device": jax.devices()[0].device_kind,
            "jax": jax.__version__,
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    with open(args.out, "a") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
