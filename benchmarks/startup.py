"""Where the start-up of a run goes, stage by stage, against the bare-physics floor.

Usage::

    TD3_LAUNCH=$(date +%s.%N) python -m benchmarks.startup --preset ant [--set KEY=VALUE ...]
    TD3_LAUNCH=$(date +%s.%N) python -m benchmarks.startup --preset ant --floor

The first form times what ``td3-jax train`` does before its first evaluation, from process
launch (``TD3_LAUNCH``, the shell's clock at launch; without it, from the script's first line):
imports, the accelerator's start-up, environment creation, tracing each program and compiling
it in a thread while the next is traced (as the command does:
:func:`td3_jax.runner.programs.compile_ahead`), the init, the first chunk (the early part of it, as
the command runs it) and the first evaluation. ``--sequential`` compiles each program in turn
instead, to see each one's cost.

``--floor`` times the same environment's bare physics instead: ``jit(scan(vmap(env.step)))``
over the preset's environments, traced and compiled once (the least any training program on
this environment can compile), then its raw env steps/s from its third call.

``--cache DIR`` turns on what ``td3-jax train`` turns on by default: JAX's persistent
compilation cache in DIR and the traced programs in DIR/programs (a second identical process
then makes no environment, traces nothing and compiles nothing; ``programs`` in the output
says whether they were ``stored`` or ``traced``). Run each measurement in its own process.
Prints one JSON line of seconds.
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

from td3_jax import envs  # noqa: E402
from td3_jax.common import upstream  # noqa: E402
from td3_jax.common.runtime import enable_compile_cache  # noqa: E402
from td3_jax.config import build  # noqa: E402
from td3_jax.config.build import make_population, members  # noqa: E402
from td3_jax.config.presets import preset  # noqa: E402
from td3_jax.envs import physics  # noqa: E402
from td3_jax.runner import program_cache, programs  # noqa: E402
from td3_jax.runner.sharding import make_mesh  # noqa: E402

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
    parser.add_argument(
        "--loop-chunks", type=int, default=0, help="then time this many chunks, one more evaluation"
    )
    parser.add_argument("--devices", type=int, default=None,
                        help="devices to split the run over (default: as td3-jax train, one GPU "
                        "for MuJoCo Warp physics, else every device)")  # fmt: skip
    return parser.parse_args()


def run_devices(cfg, devices: int | None) -> int | None:
    """The device count ``td3-jax train`` would take for ``cfg`` given ``--devices devices``:
    one GPU for MuJoCo Warp physics on a host of several, else ``devices`` (None: all)."""
    if devices is not None or not cfg.env.startswith("playground/"):
        return devices
    asked = cfg.impl or ("warp" if cfg.env_backend == "warp" else None)  # (as train resolves it)
    return 1 if physics.resolve(asked) == "warp" else None


def floor(cfg, clock: Clock) -> dict[str, float]:
    """Trace and compile time, and raw env steps/s, of ``jit(scan(vmap(env.step)))``."""
    env = build.make_env(cfg)
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


def run_start(cfg, clock: Clock, sequential: bool, program_dir, loop_chunks: int = 0,
              devices: int | None = None) -> dict:  # fmt: skip
    """The command's start-up over ``devices`` (None: all): environment (or stored programs),
    programs, init, first chunk, first evaluation."""
    population = members(cfg)
    mesh = make_mesh(devices)
    if sequential:
        env = build.make_env(cfg)
        clock.lap("make_env")
        program = make_population(cfg, population, devices=mesh.size, env=env, mesh=mesh)
        options = upstream.compile_options(mesh.devices.flat[0].platform, cfg.matmuls)
        compiled = _compile_in_turn(programs.jitted(program, mesh), program, clock, options)
        stored = False
    else:
        source = programs.find(cfg, population, mesh, program_dir)
        stored = source.stored is not None
        clock.lap("load_programs" if stored else "make_env")
        if stored:  # when each part of compile_all ends (seconds since it began)
            _time_parts(source, clock)
        compiled = programs.compiled(source)
        clock.lap("compile_all" if stored else "trace_and_compile_all")
    state = jax.block_until_ready(compiled.init())
    clock.lap("init_run")
    # The command's first call: the early part of the first chunk (all of it without one).
    first = cfg.early_iterations or cfg.iters_per_chunk
    state, metrics = compiled.train_chunk(state, np.int32(first))
    jax.block_until_ready(metrics)
    clock.lap("first_chunk")
    jax.block_until_ready(compiled.evaluate(state))
    clock.lap("first_evaluation")
    out = {"programs": "stored" if stored else "traced"}
    if loop_chunks:
        start = time.perf_counter()
        for _ in range(loop_chunks):
            state, metrics = compiled.train_chunk(state, np.int32(cfg.iters_per_chunk))
        jax.block_until_ready(metrics)
        steps = loop_chunks * cfg.steps_per_chunk
        out["loop_env_steps_per_s"] = round(steps / (time.perf_counter() - start))
        start = time.perf_counter()  # an evaluation after the first (no one-time costs)
        jax.block_until_ready(compiled.evaluate(state))
        out["loop_evaluation_s"] = round(time.perf_counter() - start, 2)
    return out


def _time_parts(source, clock: Clock) -> None:
    """Records in ``clock.times`` when the stored trees are unpickled and each stored program
    is compiled (read back from the compilation cache), in seconds from now."""
    start, compile_flat = time.time(), program_cache.compile_flat
    since = lambda: round(time.time() - start, 2)

    def timed(program, mesh, options=None):
        executable = compile_flat(program, mesh, options)
        clock.times[f"compile_all_{len(program.out_specs)}_outputs_done"] = since()
        return executable

    program_cache.compile_flat = timed
    source.trees.add_done_callback(lambda _: clock.times.update(compile_all_trees=since()))


def _compile_in_turn(compiled, program, clock: Clock, options: dict):
    """Each program traced then compiled (with the run's compile ``options``), one at a time."""
    hp_spec, state_spec, iterations = programs.chunk_argument_specs(program, compiled.shardings)
    done = {}
    steps = (("init", ()), ("chunk", (hp_spec, state_spec, iterations)),
             ("start_round", (state_spec,)), ("evaluate", (state_spec,)))  # fmt: skip
    for name, args in steps:
        if getattr(compiled, name) is None:  # (no evaluation round without eval_in_chunk)
            continue
        lowered = getattr(compiled, name).lower(*args)
        clock.lap(f"{name}_trace")
        done[name] = lowered.compile(compiler_options=options)
        clock.lap(f"{name}_compile")
    return compiled._replace(**done)


def main() -> None:
    args = parse()
    clock = Clock()
    clock.lap("imports")
    jax.devices()
    clock.lap("backend_init")
    program_dir = enable_compile_cache(args.cache) if args.cache else None
    changes = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}
    cfg = dataclasses.replace(preset(args.preset), **changes)
    extra = (
        floor(cfg, clock)
        if args.floor
        else run_start(cfg, clock, args.sequential, program_dir, args.loop_chunks,
                       run_devices(cfg, args.devices))
    )
    total = round(time.time() - float(os.environ.get("TD3_LAUNCH", _SCRIPT_START)), 2)
    mode = "floor" if args.floor else ("sequential" if args.sequential else "ahead")
    print(json.dumps({"mode": mode, "preset": args.preset, **changes, **clock.times, **extra,
                      "total_from_launch": total, "cache": bool(args.cache),
                      "device": jax.devices()[0].device_kind}), flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
