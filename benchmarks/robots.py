"""MuJoCo Playground locomotion on one GPU: per task and number of environments, the compile
time and env steps/s of the raw physics and of the full training loop (one chunk trained).

  raw   the task's own ``jax.vmap(env.step)`` in a ``lax.scan`` of --steps steps, zero actions
        (the ceiling); timed on the third call (the first two compile: reset and step states
        differ in type), compile = first two calls minus two timed ones.
  loop  td3-jax's compiled chunk (collect + 2 or 8 updates of batch 32768 per step, the task's
        preset: t1/g1/go1, else t1's for humanoids and go1's for quadrupeds) of --iters
        iterations; the first call compiles and fills the ring, the second is timed with every
        iteration updating. ``critic_loss`` of the timed chunk is reported (finite: it trained).

Usage (the robots' assets from the ``locomotion`` extra, or ``--menagerie`` a MuJoCo Menagerie
root holding the robot folders, as ``MENAGERIE_ROOT`` does)::

  python -m benchmarks.robots --impl warp --tasks T1JoystickFlatTerrain --envs 1024 4096 \\
      --out DIR

Results: ``DIR/robots.jsonl`` (a line per measurement, written as they come) and a table at the
end.

Order: each physics in turn (all of the first --impl's cells before the next one's), then the
number of environments, then the task, so a command cut short loses the slowest cells (JAX
physics at the most environments). A line with the seconds since start is printed as each part
begins, so a cell cut off by a time limit still says how long it ran. With Warp, the seconds its
kernels spent compiling (``warp_compile_s``, modules compiled: ``warp_modules``; cached ones
cost nothing here) are counted apart from the compile seconds that include them. td3-jax
compiles Warp's modules when it makes the task (``td3_jax.envs.warp_kernels``, on several
threads), so the raw compile seconds do not include the modules it lists (``warp_compile_s``
still sums every module's compile, over threads that overlap); ``TD3_JAX_WARP_PRECOMPILE=0``
leaves each module to compile at its first launch instead.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from td3_jax.common import upstream
from td3_jax.config import build
from td3_jax.config.presets import ENV_PRESETS, preset, robot_preset
from td3_jax.envs import locomotion
from td3_jax.envs.base import EnvOptions

_WARP = {"s": 0.0, "n": 0}


def _time_warp_compiles() -> None:
    """Counts the seconds and modules of MuJoCo Warp's kernel compiles (``Module._compile``
    when it compiled, not when its cache had the module), apart from XLA's compile."""
    try:
        from warp._src.context import Module
    except ImportError:
        return
    compile_ = Module._compile

    def timed(self, *args, **kwargs):
        start = time.perf_counter()
        compiled = compile_(self, *args, **kwargs)
        if compiled:
            _WARP["s"] += time.perf_counter() - start
            _WARP["n"] += 1
        return compiled

    Module._compile = timed


def _seconds(fn, *args) -> tuple[float, object]:
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - start, out


def raw_rate(task: str, num_envs: int, steps: int, root: str | None, impl: str) -> dict:
    """The task's own vmapped step in a scan: env steps/s (third call) and compile seconds
    (with Warp: XLA's and Warp's kernels' together)."""
    options = EnvOptions(menagerie=root, impl=impl, worlds=num_envs)
    env, _ = locomotion.load(task, impl=impl, options=options)
    keys = jax.random.split(jax.random.PRNGKey(0), num_envs)
    state = jax.jit(jax.vmap(env.reset))(keys)
    zeros = jnp.zeros((num_envs, env.action_size))

    @jax.jit
    def run(state):
        return jax.lax.scan(lambda s, _: (jax.vmap(env.step)(s, zeros), None), state, None,
                            length=steps)[0]  # fmt: skip

    first, state = _seconds(run, state)
    second, state = _seconds(run, state)
    third, state = _seconds(run, state)
    return {"raw_env_steps_per_s": num_envs * steps / third,
            "raw_compile_s": max(0.0, first + second - 2 * third)}  # fmt: skip


def loop_config(
    task: str,
    num_envs: int,
    iters: int,
    root: str | None,
    batch: int | None,
    impl: str = "jax",
    precision: str = "float32",
    updates: int | None = None,
):
    """The task's preset (or its kind's) at ``num_envs`` environments, one chunk of ``iters``
    (``batch``: another batch size, for a smoke test on a CPU) with ``precision`` matmuls and
    ``updates`` updates per iteration (default: the preset's). The
    preset's evaluation inside the chunk is off: a chunk this short holds no episode."""
    name = ENV_PRESETS.get(f"playground/{task}") or robot_preset(f"playground/{task}")
    cfg = preset(name)
    cfg = dataclasses.replace(cfg, batch_size=batch or cfg.batch_size)
    return dataclasses.replace(
        cfg, env=f"playground/{task}", num_envs=num_envs, eval_every=num_envs * iters,
        buffer_size=max(num_envs * iters * 2, cfg.batch_size), warmup_steps=0,
        total_steps=num_envs * iters, menagerie=root, impl=impl, precision=precision,
        eval_in_chunk=False, updates_per_iter=updates or cfg.updates_per_iter,
    ), name  # fmt: skip


def loop_rate(task: str, num_envs: int, args, root: str | None) -> dict:
    """td3-jax's training chunk: env steps/s of the second call, compile seconds of the first."""
    cfg, name = loop_config(
        task,
        num_envs,
        args.iters,
        root,
        args.batch,
        args.impl_now,
        args.precision_now,
        args.updates_now,
    )
    start = time.perf_counter()
    trainer = build.make_trainer(cfg)
    make_s = time.perf_counter() - start
    init_s, state = _seconds(jax.jit(trainer.init), jax.random.PRNGKey(0))
    # Compiled as the command line compiles its programs (upstream.compile_options).
    options = upstream.compile_options(jax.devices()[0].platform, cfg.matmuls)
    start = time.perf_counter()  # tracing and compiling, as the first call of a jitted chunk
    lowered = jax.jit(trainer.chunk, donate_argnums=0).lower(state)
    chunk = lowered.compile(compiler_options=options)
    compile_s = time.perf_counter() - start
    first, (state, _) = _seconds(chunk, state)
    first += compile_s
    second, (state, metrics) = _seconds(chunk, state)
    env = trainer.env
    return {
        "preset": name, "make_s": make_s, "init_s": init_s,
        "loop_env_steps_per_s": cfg.steps_per_chunk / second,
        "loop_compile_s": max(0.0, first - second), "chunk_s": second,
        "updates_per_chunk": float(metrics["chunk_updates"]),
        "critic_loss": float(metrics["critic_loss"]),
        "physics_overflow": float(metrics["physics_overflow"]),
        "actor_obs": env.observation_size, "critic_obs": env.critic_observation_size,
        "row": env.row_size, "actions": env.action_size,
    }  # fmt: skip


def measure(task: str, num_envs: int, args, root: str | None) -> dict:
    """One row of results (an ``error`` entry instead of a crash: the next task still runs)."""
    row = {"task": task, "num_envs": num_envs, "impl": args.impl_now,
           "precision": args.precision_now, "updates_per_iter": args.updates_now,
           "device": jax.devices()[0].device_kind}  # fmt: skip
    for kind, fn in (("raw", lambda: raw_rate(task, num_envs, args.steps, root, args.impl_now)),
                     ("loop", lambda: loop_rate(task, num_envs, args, root))):  # fmt: skip
        if kind in args.skip:
            continue
        begin, warp_s, warp_n = time.perf_counter(), _WARP["s"], _WARP["n"]
        print(f"[{begin - args.start:.0f} s] {task} {args.impl_now} {num_envs} {kind}: start",
              flush=True)  # fmt: skip
        try:
            row.update(fn())
        except Exception as err:  # reported per task, the sweep goes on
            row[f"{kind}_error"] = f"{type(err).__name__}: {err}"[:300]
        row[f"{kind}_s"] = time.perf_counter() - begin
        if args.impl_now == "warp":
            row[f"{kind}_warp_compile_s"] = _WARP["s"] - warp_s
            row[f"{kind}_warp_modules"] = _WARP["n"] - warp_n
    return row


def table(rows: list[dict]) -> str:
    head = (
        f"{'task':38} {'impl':4} {'prec':8} {'envs':>5} {'raw/s':>10} {'raw comp':>9} "
        f"{'loop/s':>10} {'loop comp':>9}"
    )
    lines = [head]
    fmt = lambda v, spec: format(v, spec) if isinstance(v, float) else "-"
    for r in rows:
        lines.append(
            f"{r['task']:38} {r['impl']:4} {r.get('precision', 'float32'):8} {r['num_envs']:>5} "
            f"{fmt(r.get('raw_env_steps_per_s'), '10.0f')} "
            f"{fmt(r.get('raw_compile_s'), '9.1f')} {fmt(r.get('loop_env_steps_per_s'), '10.0f')} "
            f"{fmt(r.get('loop_compile_s'), '9.1f')}"
            + ("  ERROR" if any(k.endswith("_error") for k in r) else "")
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="*", default=locomotion.names())
    parser.add_argument("--envs", type=int, nargs="*", default=[1024, 4096])
    parser.add_argument("--steps", type=int, default=200, help="raw: steps per timed scan")
    parser.add_argument("--iters", type=int, default=64, help="loop: iterations per chunk")
    parser.add_argument("--batch", type=int, help="loop: batch size (default: the preset's)")
    parser.add_argument("--skip", nargs="*", default=[], choices=["raw", "loop"])
    parser.add_argument("--impl", nargs="*", default=["jax"], choices=["jax", "warp"],
                        help="physics to measure, each in turn")  # fmt: skip
    parser.add_argument("--precision", nargs="*", default=["float32"],
                        choices=["float32", "bfloat16"],
                        help="loop: the networks' matmul precision, each in turn")  # fmt: skip
    parser.add_argument("--updates", type=int, nargs="*", default=[0],
                        help="loop: updates per iteration, each in turn (0: preset's)")  # fmt: skip
    parser.add_argument("--menagerie", type=Path, help="a MuJoCo Menagerie root (robot folders)")
    parser.add_argument("--budget-s", type=float, default=540.0,
                        help="start no new measurement after this many seconds")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("."))
    args = parser.parse_args()
    start = args.start = time.perf_counter()
    if "warp" in args.impl:
        _time_warp_compiles()
    root = args.menagerie
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    cells = [(i, n, t, p, u) for i in args.impl for n in args.envs for t in args.tasks
             for p in args.precision for u in args.updates]  # fmt: skip
    for impl, n, task, precision, updates in cells:
        if time.perf_counter() - start > args.budget_s:
            print(f"budget spent: {task} ({impl}, {precision}) at {n} envs not measured",
                  flush=True)  # fmt: skip
            continue
        args.impl_now, args.precision_now, args.updates_now = impl, precision, updates or None
        skip = args.skip
        if (precision, updates) != (
            args.precision[0],
            args.updates[0],
        ):  # the raw physics has no networks: measured once
            args.skip = [*skip, "raw"]
        rows.append(measure(task, n, args, str(root) if root else None))
        args.skip = skip
        with (args.out / "robots.jsonl").open("a") as f:
            f.write(json.dumps(rows[-1]) + "\n")
        print(json.dumps(rows[-1]), flush=True)
    print(table(rows))


if __name__ == "__main__":
    main()
