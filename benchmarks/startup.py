"""Where the start-up of a run goes, stage by stage, against the bare-physics floor.

Usage::

    TD3_LAUNCH=$(date +%s.%N) python benchmarks/startup.py --preset ant [--set KEY=VALUE ...]
    TD3_LAUNCH=$(date +%s.%N) python benchmarks/startup.py --preset ant --floor

The first form times what ``td3-jax train`` does before its first evaluation, from process
launch (``TD3_LAUNCH``, the shell's clock at launch; without it, from the script's first line):
imports, the accelerator's start-up, environment creation, tracing each program and compiling
it in a thread while the next is traced (as the command does:
:func:`td3_jax.population.compile_ahead`), the init, the first chunk (the early part of it, as
the command runs it) and the first evaluation. ``--sequential`` compiles each program in turn
instead, to see each one's cost.

``--floor`` times the same environment's bare physics instead: ``jit(scan(vmap(env.step)))``
over the preset's environments, traced and compiled once (the least any training program on
this environment can compile), then its raw env steps/s from its third call.

``--cache DIR`` turns JAX's persistent compilation cache on (a second identical process then
compiles nothing). Run each measurement in its own process. Prints one JSON line of seconds.
"""

from __future__ import annotations

import time

_SCRIPT_START = time.time()

import argparse  # noqa: E402
import ast  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from td3_jax import envs, training  # noqa: E402
from td3_jax.config import preset  # noqa: E402
from td3_jax.population import compile_ahead, compile_for_mesh, make_population, members  # noqa: E402
from td3_jax.sharding import make_mesh  # noqa: E402

FLOOR_STEPS = 100


class Clock:
    """Laps in seconds since the previous lap; the first lap starts at process launch."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self.last = float(os.environ.get("TD3_LAUNCH", _SCRIPT_START))

    def lap(self, name: str) -> None:
        now = time.time()
        self.times[name] = round(now - self.last, 2)
        self.last = now


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="ant")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--floor", action="store_true", help="time the bare physics instead")
    parser.add_argument("--sequential", action="store_true", help="compile programs in turn")
    parser.add_argument("--cache", default=None, help="persistent compilation cache directory")
    return parser.parse_args()


def floor(cfg, clock: Clock) -> dict[str, float]:
    """Trace and compile time, and raw env steps/s, of ``jit(scan(vmap(env.step)))``."""
    env = training.make_env(cfg)
    clock.lap("make_env")
    reset = jax.jit(lambda key: envs.reset(env, key, cfg.num_envs)).lower(jax.random.PRNGKey(0))
    clock.lap("reset_trace")
    reset = reset.compile()
    clock.lap("reset_compile")
    state = reset(jax.random.PRNGKey(0))
    action = jnp.zeros((cfg.num_envs, env.action_size), jnp.float32)

    def physics(inner):
        step = lambda s, _: (jax.vmap(env.step_fn)(s, action, state.key)[0], None)
        return jax.lax.scan(step, inner, None, length=FLOOR_STEPS)[0]

    lowered = jax.jit(physics).lower(state.inner)
    clock.lap("floor_trace")
    compiled = lowered.compile()
    clock.lap("floor_compile")
    inner = state.inner
    for _ in range(3):
        start = time.perf_counter()
        inner = jax.block_until_ready(compiled(inner))
    seconds = time.perf_counter() - start
    return {"raw_env_steps_per_s": round(cfg.num_envs * FLOOR_STEPS / seconds)}


def run_start(cfg, clock: Clock, sequential: bool) -> None:
    """The command's start-up: environment, programs, init, first chunk, first evaluation."""
    env = training.make_env(cfg)
    clock.lap("make_env")
    population = members(cfg)
    mesh = make_mesh(None)
    program = make_population(cfg, population, devices=mesh.size, env=env)
    compiled = compile_for_mesh(program, mesh)
    clock.lap("make_population")
    if sequential:
        compiled = _compile_in_turn(compiled, program, clock)
    else:
        compiled = compile_ahead(compiled, program)
        clock.lap("trace_and_compile_all")
    state = jax.block_until_ready(compiled.init())
    clock.lap("init_run")
    # The command's first call: the early part of the first chunk (all of it without one).
    first = cfg.early_iterations or cfg.iters_per_chunk
    state, metrics = compiled.chunk(compiled.hyperparams, state, np.int32(first))
    jax.block_until_ready(metrics)
    clock.lap("first_chunk")
    jax.block_until_ready(compiled.evaluate(state))
    clock.lap("first_evaluation")


def _compile_in_turn(compiled, program, clock: Clock):
    from td3_jax.population import _with_sharding

    state_spec = _with_sharding(program.abstract_state, compiled.shardings)
    hp = compiled.hyperparams
    abstract = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding)
    hp_spec = jax.tree.map(abstract, hp)
    iterations = abstract(jnp.zeros((), jnp.int32, device=jax.tree.leaves(hp)[0].sharding))
    done = {}
    programs = (("init", ()), ("chunk", (hp_spec, state_spec, iterations)),
                ("evaluate", (state_spec,)))  # fmt: skip
    for name, args in programs:
        lowered = getattr(compiled, name).lower(*args)
        clock.lap(f"{name}_trace")
        done[name] = lowered.compile()
        clock.lap(f"{name}_compile")
    return compiled._replace(**done)


def main() -> None:
    args = parse()
    clock = Clock()
    clock.lap("imports")
    jax.devices()
    clock.lap("backend_init")
    if args.cache:
        jax.config.update("jax_compilation_cache_dir", args.cache)
    changes = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}
    cfg = dataclasses.replace(preset(args.preset), **changes)
    extra = floor(cfg, clock) if args.floor else run_start(cfg, clock, args.sequential) or {}
    total = round(time.time() - float(os.environ.get("TD3_LAUNCH", _SCRIPT_START)), 2)
    mode = "floor" if args.floor else ("sequential" if args.sequential else "ahead")
    print(json.dumps({"mode": mode, "preset": args.preset, **changes, **clock.times, **extra,
                      "total_from_launch": total, "cache": bool(args.cache),
                      "device": jax.devices()[0].device_kind}), flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
