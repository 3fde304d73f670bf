"""How many constraints and contacts Playground's robots need per environment on MuJoCo Warp.

Steps each task on Warp with large buffers (``--njmax``, ``--nconmax`` per environment) under
uniform random actions in [-1, 1] (the warm-up policy of a td3-jax run), with auto-reset, and
reports per step the largest constraint count of any environment (``nefc``, sized by
``njmax``) and the contacts of all environments (``nacon``, sized by ``nconmax`` times the
number of environments), then their maxima and 99.9th percentiles over the run, beside the
task's own settings. On a GPU with MuJoCo Warp installed (``pip install -e '.[warp]'``)::

  python -m benchmarks.warp_buffers --tasks G1JoystickFlatTerrain T1JoystickFlatTerrain \\
      --envs 4096 --steps 3000 --out DIR
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from td3_jax import envs
from td3_jax.envs import locomotion
from td3_jax.envs.base import EnvOptions


def counts_per_step(name: str, options: EnvOptions, num_envs: int, steps: int, seed: int):
    """``(nefc max over environments [steps], nacon [steps], overflowed steps)`` of a run under
    random actions."""
    env = envs.make(f"playground/{name}", options=options)

    def one(carry, key):
        state = carry
        action = jax.random.uniform(key, (num_envs, env.action_size), minval=-1.0, maxval=1.0)
        state, result = envs.step(env, state, action)
        warp = state.inner.data._impl
        return state, (jnp.max(warp.nefc), jnp.max(warp.nacon), jnp.sum(result.overflow))

    @jax.jit
    def rollout(key):
        state = envs.reset(env, key, num_envs)
        return jax.lax.scan(one, state, jax.random.split(key, steps))[1]

    return jax.tree.map(np.asarray, rollout(jax.random.PRNGKey(seed)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["G1JoystickFlatTerrain"])
    parser.add_argument("--envs", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--njmax", type=int, default=400)
    parser.add_argument("--nconmax", type=int, default=64)
    parser.add_argument("--menagerie", default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    for task in args.tasks:
        options = EnvOptions(menagerie=args.menagerie, impl="warp", worlds=args.envs,
                             njmax=args.njmax, nconmax=args.nconmax)  # fmt: skip
        start = time.perf_counter()
        nefc, nacon, overflowed = counts_per_step(task, options, args.envs, args.steps, 0)
        seconds = time.perf_counter() - start
        config = locomotion.load(task, impl="jax", options=EnvOptions(menagerie=args.menagerie))[1]
        row = {
            "task": task, "envs": args.envs, "steps": args.steps,
            "task_njmax": int(config.njmax), "task_naconmax_per_env": int(config.naconmax) // 8192,
            "nefc_max": int(nefc.max()), "nefc_p999": float(np.percentile(nefc, 99.9)),
            "contacts_per_env_max": float(nacon.max()) / args.envs,
            "contacts_per_env_p999": float(np.percentile(nacon, 99.9)) / args.envs,
            "overflowed_env_steps": int(overflowed.sum()),
            "seconds_make_compile_run": round(seconds, 1),
        }  # fmt: skip
        print(json.dumps(row), flush=True)
        if args.out:
            args.out.mkdir(parents=True, exist_ok=True)
            with open(args.out / "warp_buffers.jsonl", "a") as f:
                f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
