"""How XLA compile options change the time to compile a preset's training chunk, and its speed.

Usage::

    python -m benchmarks.compile_options --preset t1 \\
        --variant default \\
        --variant no-fusion-autotuner:xla_gpu_experimental_enable_fusion_autotuner=false

The environment is made and the chunk traced and lowered once; then, for ``--rounds`` rounds,
each variant's options (on top of the run's own, e.g. the preset's ``matmuls``) compile that same
lowered program again (JAX's in-memory and persistent caches are not used; XLA keeps its GPU
autotuning results for the whole process, so the untimed compile that runs the warm-up first
leaves autotuning out of every timed one: compare autotuning in processes of their own), and
the compiled
chunk runs ``--iterations`` iterations to give its env steps/s. The state runs past the
warm-up first and goes on from one variant to the next (each timed call after one untimed).
With in-chunk evaluation the start of the chunk's evaluation round is a program of its own, as
in a run: each variant compiles it too (``round_compile_s``), and a round starts before each
call of the chunk. A variant is ``NAME`` (the run's options alone) or
``NAME:KEY=VALUE[,KEY=VALUE...]`` with XLA ``DebugOptions`` fields (``true``/``false``, numbers,
or text). Prints one JSON line per compile, then one summary line per variant.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import time

import jax
import numpy as np

from td3_jax.common import upstream
from td3_jax.config import build
from td3_jax.config.build import make_population, members
from td3_jax.config.presets import preset
from td3_jax.runner import programs
from td3_jax.runner.sharding import make_mesh


def option_value(text: str) -> bool | int | float | str:
    """``true``/``false`` as booleans, numbers as numbers, anything else as the text."""
    text = text.strip()
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def parse_variant(text: str) -> tuple[str, dict]:
    """``"NAME:K=V,K2=V2"`` -> ``("NAME", {"K": V, "K2": V2})``; ``"NAME"`` -> ``("NAME", {})``."""
    name, _, options = text.partition(":")
    pairs = [item.split("=", 1) for item in options.split(",") if item]
    if not name or any(len(pair) != 2 or not pair[0] for pair in pairs):
        raise SystemExit(f"compile_options: --variant {text!r} is not NAME[:KEY=VALUE,...]")
    return name, {key.strip(): option_value(value) for key, value in pairs}


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="t1")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME[:K=V,...]")
    parser.add_argument("--rounds", type=int, default=2, help="each variant this many times")
    parser.add_argument("--iterations", type=int, default=200, help="timed chunk iterations")
    args = parser.parse_args()
    args.variants = [parse_variant(v) for v in args.variant or ["default"]]
    return args


def lowered_chunk(cfg, devices: int = 1):
    """The preset's chunk lowered once, its jitted (not yet compiled) programs, and the run's
    own compile options. (With ``eval_in_chunk`` the chunk is its iterations: the program that
    starts its evaluation round, :func:`lowered_round`, compiles apart.)"""
    mesh = make_mesh(devices)
    env = build.make_env(cfg)
    program = make_population(cfg, members(cfg), devices=mesh.size, env=env, mesh=mesh)
    jitted = programs.jitted(program, mesh)
    specs = programs.chunk_argument_specs(program, jitted.shardings)
    base = upstream.compile_options(mesh.devices.flat[0].platform, cfg.matmuls)
    return jitted.chunk.lower(*specs), jitted, base


def lowered_round(jitted):
    """The program that starts a chunk's evaluation round, lowered (``None`` without one)."""
    if jitted.start_round is None:
        return None
    return jitted.start_round.lower(programs.with_sharding(jitted.abstract_state,
                                                           jitted.shardings))


def timed_compile(lowered, options: dict) -> tuple[object, float]:
    """``lowered`` compiled with ``options`` again (not read back from JAX's caches), and the
    seconds it took."""
    jax.clear_caches()
    start = time.perf_counter()
    executable = lowered.compile(compiler_options=dict(options))
    return executable, time.perf_counter() - start


def loop_rate(programs, state, iterations: int, steps_per_iteration: int):
    """Env steps/s of ``iterations`` chunk iterations of ``programs`` (its compiled chunk, and
    the start of its evaluation round where there is one, run as a run runs them:
    :meth:`~td3_jax.runner.programs.Programs.train_chunk`) from ``state`` (donated; after one
    untimed call), and the state they end in."""
    state, metrics = programs.train_chunk(state, np.int32(1))
    jax.block_until_ready(metrics)
    start = time.perf_counter()
    state, metrics = programs.train_chunk(state, np.int32(iterations))
    jax.block_until_ready((state, metrics))
    return iterations * steps_per_iteration / (time.perf_counter() - start), state


def past_warmup(lowered, base: dict, jitted, cfg, start_round=None):
    """The initial state run past the warm-up (random actions, no updates), so that every
    timed iteration learns; compiled with the run's own options (not timed). ``start_round``:
    the compiled start of an evaluation round, run first as a run does."""
    state = jax.block_until_ready(jitted.init())
    executable = lowered.compile(compiler_options=dict(base))
    iterations = -(-cfg.warmup_steps // cfg.env_steps_per_iter) + 1
    programs = jitted._replace(chunk=executable, start_round=start_round)
    state, metrics = programs.train_chunk(state, np.int32(iterations))
    jax.block_until_ready(metrics)
    return state


def main() -> None:
    args = parse()
    jax.config.update("jax_enable_compilation_cache", False)  # (none read back from disk)
    changes = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}
    cfg = dataclasses.replace(preset(args.preset), **changes)
    start = time.perf_counter()
    lowered, jitted, base = lowered_chunk(cfg)
    print(json.dumps({"made_and_lowered_s": round(time.perf_counter() - start, 1),
                      "base_options": base}), flush=True)  # fmt: skip
    round_program = lowered_round(jitted)
    start_round = None if round_program is None else round_program.compile(
        compiler_options=dict(base))
    state = past_warmup(lowered, base, jitted, cfg, start_round)
    steps = cfg.env_steps_per_iter
    results: dict[str, list] = {name: [] for name, _ in args.variants}
    for round_index in range(args.rounds):
        for name, options in args.variants:
            executable, seconds = timed_compile(lowered, {**base, **options})
            compiled = jitted._replace(chunk=executable, start_round=start_round)
            rate, state = loop_rate(compiled, state, args.iterations, steps)
            results[name].append((round(seconds, 1), round(rate)))
            row = {"round": round_index, "variant": name, "options": options,
                   "compile_s": round(seconds, 1), "env_steps_per_s": round(rate)}
            if round_program is not None:  # (compiled beside the chunk in a run)
                row["round_compile_s"] = round(timed_compile(round_program,
                                                             {**base, **options})[1], 1)
            print(json.dumps(row), flush=True)
            del executable, compiled
    for name, rows in results.items():
        print(json.dumps({"variant": name, "compile_s": [r[0] for r in rows],
                          "env_steps_per_s": [r[1] for r in rows]}), flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
