"""How long a Playground robot's first MuJoCo Warp steps take with a cold Warp kernel cache,
with and without compiling Warp's kernels on several threads first
(:func:`td3_jax.envs.warp_kernels.precompile`). One JSON line on stdout (and in --out).

Each process uses its own empty kernel cache. On the GPU machine, two at once, one per mode:

    python benchmarks/warp_precompile.py --task T1JoystickFlatTerrain --menagerie $MEN \\
        --workers 0 --out $OUT/serial.json &
    python benchmarks/warp_precompile.py --task T1JoystickFlatTerrain --menagerie $MEN \\
        --workers 8 --out $OUT/parallel.json; wait

``--workers 0``: no precompile (each module compiles at its first launch, one at a time), as
with ``TD3_JAX_WARP_PRECOMPILE=0``; ``--workers N``: td3-jax's precompile on N threads (its
default is one per CPU core, at most 8).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

START = time.perf_counter()
# Two of these share one GPU: neither may take most of its memory up front, as JAX does.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# The task is made without td3-jax's own precompile; --workers runs it here, timed apart.
os.environ["TD3_JAX_WARP_PRECOMPILE"] = "0"
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="T1JoystickFlatTerrain")
    parser.add_argument("--menagerie", type=Path)
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    import warp

    warp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="warp-cache-")
    import jax
    import jax.numpy as jnp
    import robots
    from robots import _WARP, _time_warp_compiles, unpack

    from td3_jax import upstream
    from td3_jax.envs import locomotion, warp_kernels
    from td3_jax.envs.base import EnvOptions

    _time_warp_compiles()
    names: list[str] = []
    from warp._src.context import Module

    counted = Module._compile

    def named(self, *a, **k):
        compiled = counted(self, *a, **k)
        if compiled:
            names.append(self.name)
        return compiled

    Module._compile = named
    root = str(unpack(args.menagerie)) if args.menagerie else None
    options = EnvOptions(menagerie=root, impl="warp", worlds=args.envs)
    env, config = locomotion.load(args.task, impl="warp", options=options)
    task = getattr(env, "unwrapped", env)
    row = {
        "task": args.task,
        "envs": args.envs,
        "workers": args.workers,
        "device": jax.devices()[0].device_kind,
        "made_s": time.perf_counter() - START,
    }
    if args.workers:
        opts = warp_kernels.static_options(upstream.task_mjx_model(task).opt._impl)
        done = warp_kernels.precompile(
            task.mj_model,
            options=opts,
            njmax=int(config.njmax),
            naconmax=max(1, int(config.naconmax) // 8192),
            workers=args.workers,
        )
        row.update(pre_modules=done.modules, pre_s=done.seconds, pre_compiled=_WARP["n"])
    keys = jax.random.split(jax.random.PRNGKey(0), args.envs)
    begin, before = time.perf_counter(), _WARP["n"]
    state = jax.block_until_ready(jax.jit(jax.vmap(env.reset))(keys))
    zeros = jnp.zeros((args.envs, env.action_size))
    state = jax.block_until_ready(jax.jit(jax.vmap(env.step))(state, zeros))
    row.update(
        first_steps_s=time.perf_counter() - begin,
        later_compiled=_WARP["n"] - before,
        warp_compile_s=_WARP["s"],
        total_s=time.perf_counter() - START,
        finite=bool(jnp.all(jnp.isfinite(state.obs["state"]))),
        later_names=names[len(names) - (_WARP["n"] - before) :][:10],
    )
    line = json.dumps(row)
    print(line, flush=True)
    if args.out:
        args.out.write_text(line + "\n")
    del robots


if __name__ == "__main__":
    main()
