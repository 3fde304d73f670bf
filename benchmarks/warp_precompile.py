"""How long a Playground robot's first MuJoCo Warp steps take with a cold Warp kernel cache,
with and without compiling Warp's kernels on several threads first
(:func:`td3_jax.envs.warp_kernels.precompile`). One JSON line on stdout (and in --out).

Each process uses its own empty kernel cache. On a GPU, one mode after the other (at once
they would share the CPU cores that compile):

    python -m benchmarks.warp_precompile --task T1JoystickFlatTerrain --workers 0 \\
        --out DIR/serial.json
    python -m benchmarks.warp_precompile --task T1JoystickFlatTerrain --workers 8 \\
        --out DIR/parallel.json

``--workers 0``: no precompile (each module compiles at its first launch, one at a time), as
with ``TD3_JAX_WARP_PRECOMPILE=0``; ``--workers N``: td3-jax's precompile on N threads (its
default is one per CPU core, at most 16). ``--optimization-level L`` compiles every module at
CUDA optimization level L (Warp's ``config.optimization_level``; its default is 3);
``--rate-steps N`` then times the physics with those kernels (the task's vmapped step in a
scan of N steps, third call); ``--listed-order`` compiles the modules in the order they were
listed, not the slowest first; ``--queries-in-listing`` has the listing answer MuJoCo Warp's
block-size queries for real (each compiles its module inside the listing, one at a time).
The row names the modules that took longest to compile.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

START = time.perf_counter()
# (Should two share one GPU, neither takes most of its memory up front, as JAX does.)
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# The task is made without td3-jax's own precompile; --workers runs it here, timed apart.
os.environ["TD3_JAX_WARP_PRECOMPILE"] = "0"


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="T1JoystickFlatTerrain")
    parser.add_argument("--menagerie", type=Path, help="a MuJoCo Menagerie root")
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--optimization-level", type=int, choices=range(4))
    parser.add_argument("--rate-steps", type=int, default=0)
    parser.add_argument("--listed-order", action="store_true")
    parser.add_argument("--queries-in-listing", action="store_true")
    parser.add_argument("--out", type=Path)
    return parser.parse_args()


def _compiles_named() -> list[tuple[str, float]]:
    """The names of the Warp modules compiled from now on, in order, each with its seconds
    (each compile counted and timed by :func:`robots._time_warp_compiles` too)."""
    from benchmarks.robots import _time_warp_compiles
    from td3_jax.common import upstream

    _time_warp_compiles()
    names: list[tuple[str, float]] = []
    module_class = upstream.warp_module_class()
    counted = module_class._compile

    def named(self, *args, **kwargs):
        start = time.perf_counter()
        compiled = counted(self, *args, **kwargs)
        if compiled:
            names.append((self.name, round(time.perf_counter() - start, 2)))
        return compiled

    module_class._compile = named
    return names


def _first_steps(env, envs: int) -> tuple[float, bool]:
    """Seconds of the task's first jitted reset and step of ``envs`` environments, and
    whether its observations came out finite."""
    import jax
    import jax.numpy as jnp

    begin = time.perf_counter()
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), envs))
    state = jax.jit(jax.vmap(env.step))(state, jnp.zeros((envs, env.action_size)))
    state = jax.block_until_ready(state)
    return time.perf_counter() - begin, bool(jnp.all(jnp.isfinite(state.obs["state"])))


def _set_variant(args: argparse.Namespace) -> None:
    """The precompile as ``--listed-order`` and ``--queries-in-listing`` ask."""
    from td3_jax.envs import warp_kernels

    if args.listed_order:
        warp_kernels.SLOW_FIRST = ()
    if args.queries_in_listing:
        listed = warp_kernels.listed_modules
        warp_kernels.listed_modules = lambda run, **_: listed(run, answer_queries=True)


def main() -> None:
    args = _arguments()
    import warp

    warp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="warp-cache-")
    warp.config.optimization_level = args.optimization_level
    import jax

    from benchmarks.robots import _WARP, raw_rate
    from td3_jax.common import upstream
    from td3_jax.envs import locomotion, warp_kernels
    from td3_jax.envs.base import EnvOptions

    names = _compiles_named()
    _set_variant(args)
    root = str(args.menagerie) if args.menagerie else None
    options = EnvOptions(menagerie=root, impl="warp", worlds=args.envs)
    env, config = locomotion.load(args.task, impl="warp", options=options)
    task = getattr(env, "unwrapped", env)
    row = {"task": args.task, "envs": args.envs, "workers": args.workers,
           "optimization_level": args.optimization_level,
           "device": jax.devices()[0].device_kind,
           "made_s": time.perf_counter() - START}  # fmt: skip
    if args.workers:
        model_options = upstream.mjx_warp_options(upstream.task_mjx_model(task))
        done = warp_kernels.precompile(task.mj_model, workers=args.workers,
                                       options=warp_kernels.static_options(model_options),
                                       **locomotion.precompile_sizes(config, options))  # fmt: skip
        row.update(pre_modules=done.modules, pre_s=done.seconds, pre_compiled=_WARP["n"])
    before = _WARP["n"]
    seconds, finite = _first_steps(env, args.envs)
    row.update(first_steps_s=seconds, later_compiled=_WARP["n"] - before, finite=finite,
               warp_compile_s=_WARP["s"], total_s=time.perf_counter() - START,
               later_names=[name for name, _ in names[before:][:10]],
               longest=sorted(names, key=lambda named: -named[1])[:8])  # fmt: skip
    if args.rate_steps:
        row.update(raw_rate(args.task, args.envs, args.rate_steps, root, "warp"))
    line = json.dumps(row)
    print(line, flush=True)
    if args.out:
        args.out.write_text(line + "\n")


if __name__ == "__main__":
    main()
