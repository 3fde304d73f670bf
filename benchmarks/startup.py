"""Where the start-up of a run goes: environment, tracing, compiling, first chunk and evaluation.

Usage: python benchmarks/startup.py --preset ant [--mode ahead|sequential] [--set KEY=VALUE ...]

``ahead`` is what ``td3-jax train`` does (trace the init, chunk and evaluation one after the
other, then compile them in parallel threads, :func:`td3_jax.population.compile_ahead`);
``sequential`` traces and compiles each in turn, as jit does at first calls. Run each mode in
its own process (compiled code is cached within a process). Prints one JSON line of seconds.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import time

import jax

from td3_jax import envs
from td3_jax.config import preset
from td3_jax.population import compile_ahead, compile_for_mesh, make_population, members
from td3_jax.sharding import make_mesh


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="ant")
    parser.add_argument("--mode", choices=["ahead", "sequential"], default="ahead")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    changes = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}
    cfg = dataclasses.replace(preset(args.preset), **changes)
    times: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        times[name] = round(now - clock, 2)
        clock = now

    envs.make(cfg.env, backend=cfg.env_backend, episode_length=cfg.episode_length)
    lap("make_env")
    population = members(cfg)
    mesh = make_mesh(None)
    program = make_population(cfg, population, devices=mesh.size)
    lap("make_population")
    compiled = compile_for_mesh(program, mesh)
    hp = compiled.hyperparams
    if args.mode == "ahead":
        compiled = compile_ahead(compiled, program)
        lap("trace_and_compile_all")
        state = jax.block_until_ready(compiled.init())
        lap("init_run")
    else:
        state = jax.block_until_ready(compiled.init())
        lap("init_compile_and_run")
        chunk = compiled.chunk.lower(hp, state)
        lap("chunk_trace")
        chunk = chunk.compile()
        lap("chunk_compile")
        evaluate = compiled.evaluate.lower(state)
        lap("evaluate_trace")
        evaluate = evaluate.compile()
        lap("evaluate_compile")
        compiled = compiled._replace(chunk=chunk, evaluate=evaluate)
    state, metrics = compiled.chunk(hp, state)
    jax.block_until_ready(metrics)
    lap("first_chunk")
    jax.block_until_ready(compiled.evaluate(state))
    lap("first_evaluation")
    times["total"] = round(sum(times.values()), 2)
    print(json.dumps({"mode": args.mode, "preset": args.preset, **changes, **times}), flush=True)


if __name__ == "__main__":
    main()
