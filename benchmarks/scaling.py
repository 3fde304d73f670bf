"""Data-parallel scaling of the full training loop over 1, 2, 4, 8 GPUs of one host.

One command measures, for every ``--env`` and every device count in ``--devices`` (those the
host has):

* weak scaling: each device keeps ``--envs-per-device`` environments and ``--batch-per-device``
  rows of every gradient batch, so D devices do D times the work of one;
* strong scaling: ``--global-envs`` environments and batch ``--global-batch`` whatever D.

Each (env, mode, devices) *point* runs in a fresh Python process that sees only the first D
GPUs (``CUDA_VISIBLE_DEVICES``), so no memory of an earlier point lingers and a point that fails
(out of memory, say) is recorded with its error while the others go on. A point builds the
environment's preset at its sizes (warm-up off, a ring of ``--buffer-steps`` steps per
environment, ``--replay-shards`` slices: by default the largest device count, so replay stays
on each device), compiles init and chunk ahead (seconds recorded), fills the ring with a short
chunk, then times a chunk of ``--iterations`` iterations that all update (compile excluded).
Speed-up and efficiency are against the 1-device point of the same env and mode:
``speedup = rate(D) / rate(1)``, ``efficiency = speedup / D`` for env steps/s and for samples/s
(updates/s times batch; weak scaling's batch grows with D, strong scaling's does not), so 1.0
is perfect in both modes. Each point also lists the collectives of its compiled chunk (from
the optimised HLO: kind, shapes, bytes) and, with ``--profile DIR``, writes a
``jax.profiler`` trace of one more chunk to ``DIR/<env>_<mode>_d<D>/``.

``--jobs K`` lets K points compile side by side (CPU work) while only one at a time runs on
the GPUs (a lock), with ``XLA_PYTHON_CLIENT_PREALLOCATE=false`` so compiling points hold no GPU
memory; compile seconds then include the contention. With K at least the number of points,
every point compiles first and none is measured until all have compiled (a barrier), so no
compile or GPU autotuning overlaps a measurement. Outputs in ``--out DIR``:
``scaling.json`` (meta + rows), ``scaling.csv``, ``scaling.md`` (date, device, versions,
commit, table). Robots' meshes: ``MENAGERIE_ROOT`` is passed through to every point.

  python -m benchmarks.scaling --env brax/ant playground/T1JoystickFlatTerrain \
      --devices 1 2 --iterations 50 --jobs 4 --out results/scaling
  XLA_FLAGS=--xla_force_host_platform_device_count=4 JAX_PLATFORMS=cpu \
      python -m benchmarks.scaling --env brax/inverted_pendulum --devices 1 2 4 --smoke --out /tmp/s
"""

from __future__ import annotations

import argparse
import ast
import csv
import dataclasses
import datetime
import fcntl
import importlib.metadata
import json
import math
import os
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

MODES = ("weak", "strong")
RESULT_MARK = "SCALING_POINT "
PACKAGES = ("jax", "jaxlib", "jax-cuda12-plugin", "jax-cuda13-plugin", "brax", "mujoco",
            "mujoco-mjx", "playground", "flax", "optax")  # fmt: skip
SMOKE = dict(envs_per_device=16, batch_per_device=64, global_envs=64, global_batch=256,
             iterations=4, buffer_steps=32)  # fmt: skip
CSV_FIELDS = ("env", "mode", "devices", "num_envs", "batch_size", "updates_per_iter",
              "replay_shards", "iterations", "env_steps_per_s", "updates_per_s",
              "samples_per_s", "speedup_env_steps", "efficiency_env_steps", "speedup_samples",
              "efficiency_samples", "chunk_s", "compile_chunk_s", "compile_init_s",
              "compile_round_s", "peak_gib_per_device", "error")  # fmt: skip


# --------------------------------------------------------------------------------------------
# The command (parent): plan the points, run each in its own process, write the results
# --------------------------------------------------------------------------------------------


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (``--point`` is the internal child mode)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", nargs="+", default=["brax/ant"])
    p.add_argument("--preset", help="preset for every --env (default: each env's own)")
    p.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4, 8])
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--envs-per-device", type=int, default=4096)
    p.add_argument("--batch-per-device", type=int, default=8192)
    p.add_argument("--global-envs", type=int, default=16384)
    p.add_argument("--global-batch", type=int, default=32768)
    p.add_argument("--iterations", type=int, default=50, help="iterations of the timed chunk")
    p.add_argument("--buffer-steps", type=int, default=256,
                   help="replay ring rows per environment")  # fmt: skip
    p.add_argument("--replay-shards", type=int, help="default: the largest device count")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="other TrainConfig fields, e.g. updates_per_iter=8")  # fmt: skip
    p.add_argument("--profile", type=Path, help="write a jax.profiler trace per point here")
    p.add_argument("--jobs", type=int, default=1, help="points compiling side by side")
    p.add_argument("--point-timeout-s", type=float, default=900.0)
    p.add_argument("--smoke", action="store_true", help="tiny sizes (a CPU check)")
    p.add_argument("--out", type=Path, default=Path("scaling-results"))
    p.add_argument("--point", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.smoke:
        for name, value in SMOKE.items():
            setattr(args, name, value)
    if args.jobs < 1 or args.iterations < 1:
        p.error("--jobs and --iterations must be at least 1")
    return args


def plan(args: argparse.Namespace, available: int) -> list[dict[str, Any]]:
    """Every (env, mode, devices) point to measure; device counts beyond ``available`` are
    dropped (with a note); the fewest devices come first."""
    counts = sorted({d for d in args.devices if 0 < d <= available})
    if not counts:
        raise SystemExit(f"scaling: none of --devices {args.devices} fits the {available} "
                         "devices here")  # fmt: skip
    skipped = sorted(set(args.devices) - set(counts))
    if skipped:
        print(f"scaling: {available} devices here, skipping --devices {skipped}", flush=True)
    shards = args.replay_shards or max(counts)
    points = []
    for env in args.env:
        for mode in args.modes:
            for d in counts:
                weak = mode == "weak"
                points.append({
                    "env": env, "preset": args.preset, "mode": mode, "devices": d,
                    "num_envs": args.envs_per_device * d if weak else args.global_envs,
                    "batch_size": args.batch_per_device * d if weak else args.global_batch,
                    "iterations": args.iterations, "buffer_steps": args.buffer_steps,
                    "replay_shards": shards, "set": list(args.set),
                    "profile": str(args.profile) if args.profile else None,
                })  # fmt: skip
    return points


def _probe_code() -> str:
    return ("import json, jax; d = jax.devices(); print(json.dumps({'platform': d[0].platform,"
            " 'count': len(d), 'kind': d[0].device_kind}))")  # fmt: skip


def probe() -> dict[str, Any]:
    """Platform, device count and kind, asked of a short-lived process (this one never starts
    a JAX backend, so it holds no GPU memory while the points run)."""
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    proc = subprocess.run([sys.executable, "-c", _probe_code()], env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    if proc.returncode != 0:
        raise SystemExit(f"scaling: could not list the devices:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def versions() -> dict[str, str]:
    """Installed versions of the packages that shape the numbers (absent ones left out)."""
    found = {}
    for name in PACKAGES:
        try:
            found[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            pass
    return found


def commit() -> str:
    """The checkout's commit (``+dirty`` with uncommitted changes), or ``unknown``."""
    root = Path(__file__).resolve().parent
    git = lambda *a: subprocess.run(["git", *a], cwd=root, capture_output=True, text=True)
    head = git("rev-parse", "HEAD")
    if head.returncode != 0:
        return "unknown"
    dirty = git("status", "--porcelain", "--untracked-files=no").stdout.strip()
    return head.stdout.strip() + ("+dirty" if dirty else "")


def visible_gpus(devices: int) -> str:
    """``CUDA_VISIBLE_DEVICES`` for the first ``devices`` GPUs (of those already visible)."""
    given = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [s for s in given.split(",") if s.strip()] if given else None
    ids = ids or [str(i) for i in range(devices)]
    return ",".join(ids[:devices])


def point_env(point: dict[str, Any], platform: str, jobs: int) -> dict[str, str]:
    """The environment of a point's process: only its GPUs visible; no preallocation when
    several points share the GPUs' memory while compiling."""
    env = dict(os.environ)
    if platform == "gpu":
        env["CUDA_VISIBLE_DEVICES"] = visible_gpus(point["devices"])
    if jobs > 1:
        env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    return env


def run_point(point: dict[str, Any], args: argparse.Namespace, platform: str) -> dict[str, Any]:
    """One point in its own process; its result row, or the point with an ``error``."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--point", json.dumps(point)]
    label = f"{point['env']} {point['mode']} d={point['devices']}"
    print(f"scaling: start {label}", flush=True)
    try:
        env = point_env(point, platform, args.jobs)
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True,
                              timeout=args.point_timeout_s)  # fmt: skip
    except subprocess.TimeoutExpired:
        return {**point, "error": f"timed out after {args.point_timeout_s:.0f} s"}
    lines = [x for x in proc.stdout.splitlines() if x.startswith(RESULT_MARK)]
    if lines:
        row = json.loads(lines[-1][len(RESULT_MARK) :])
    else:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-12:]
        row = {**point, "error": f"exit code {proc.returncode}: " + " | ".join(tail)[-1500:]}
    print(f"scaling: done {label}: " + (f"ERROR {row['error'][:300]}" if row.get("error") else
          f"{row['env_steps_per_s']:,.0f} env steps/s, {row['updates_per_s']:.1f} updates/s"),
          flush=True)  # fmt: skip
    return row


def run_all(points: list[dict[str, Any]], args: argparse.Namespace, platform: str) -> list:
    """Every point (``args.jobs`` processes at a time; one at a time on the devices)."""
    lock, barrier = args.out / ".device.lock", args.out / ".compiled"
    lock.touch()
    barrier.mkdir(exist_ok=True)
    for old in barrier.iterdir():
        old.unlink()
    together = args.jobs >= len(points) > 1  # all compile first, then all measure
    points = [{**p, "lock": str(lock), "barrier": str(barrier) if together else None,
               "barrier_size": len(points), "index": i} for i, p in enumerate(points)]  # fmt: skip
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        return list(pool.map(lambda p: run_point(p, args, platform), points))


def add_ratios(rows: list[dict[str, Any]]) -> None:
    """Speed-up and efficiency of each row against the 1-device row of its env and mode
    (``None`` where either failed)."""
    base = {(r["env"], r["mode"]): r for r in rows if r["devices"] == 1 and not r.get("error")}
    for r in rows:
        one = base.get((r["env"], r["mode"]))
        for what, key in (("env_steps", "env_steps_per_s"), ("samples", "samples_per_s")):
            ok = one is not None and not r.get("error")
            speedup = r[key] / one[key] if ok else None
            r[f"speedup_{what}"] = speedup
            r[f"efficiency_{what}"] = speedup / r["devices"] if ok else None


def _cell(value: Any, spec: str = "") -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return format(value, spec or ".3g")
    return str(value)


def markdown(meta: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    """The results as a markdown table, headed by where and with what they were measured."""
    soft = ", ".join(f"{k} {v}" for k, v in meta["versions"].items())
    head = [f"# Scaling, {meta['date']}", "",
            f"{meta['device_count']} x {meta['device_kind']} ({meta['platform']}); {soft}; "
            f"commit {meta['commit']}; {meta['iterations']} timed iterations per point; "
            f"jobs {meta['jobs']}.", "", f"Command: `{meta['command']}`", "",
            "| env | mode | GPUs | envs | batch | env steps/s | updates/s | speed-up (steps) "
            "| eff. (steps) | speed-up (samples) | eff. (samples) | compile s | peak GiB/dev |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
            "| ---: |"]  # fmt: skip
    for r in rows:
        if r.get("error"):
            head.append(f"| {r['env']} | {r['mode']} | {r['devices']} | {r['num_envs']} | "
                        f"{r['batch_size']} | failed: {r['error'][:160]} |||||||")  # fmt: skip
            continue
        cells = [r["env"], r["mode"], r["devices"], r["num_envs"], r["batch_size"],
                 _cell(r["env_steps_per_s"], ",.0f"), _cell(r["updates_per_s"], ",.1f"),
                 _cell(r["speedup_env_steps"], ".2f"), _cell(r["efficiency_env_steps"], ".2f"),
                 _cell(r["speedup_samples"], ".2f"), _cell(r["efficiency_samples"], ".2f"),
                 _cell(r["compile_chunk_s"], ".1f"),
                 _cell(r.get("peak_gib_per_device"), ".1f")]  # fmt: skip
        head.append("| " + " | ".join(map(str, cells)) + " |")
    return "\n".join(head) + "\n"


def write_outputs(out: Path, meta: dict[str, Any], rows: list[dict[str, Any]]) -> None:
    """``scaling.json`` (meta and rows), ``scaling.csv`` and ``scaling.md`` in ``out``."""
    (out / "scaling.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    with (out / "scaling.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (out / "scaling.md").write_text(markdown(meta, rows))


def main(argv: list[str] | None = None) -> None:
    args = parse(argv)
    if args.point:
        child_main(json.loads(args.point))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    devices = probe()
    meta = {"date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "platform": devices["platform"], "device_kind": devices["kind"],
            "device_count": devices["count"], "versions": versions(), "commit": commit(),
            "iterations": args.iterations, "jobs": args.jobs,
            "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
            "menagerie_root": os.environ.get("MENAGERIE_ROOT")}  # fmt: skip
    rows = run_all(plan(args, devices["count"]), args, devices["platform"])
    add_ratios(rows)
    meta["wall_s"] = round(time.perf_counter() - start, 1)
    write_outputs(args.out, meta, rows)
    print(markdown(meta, rows), flush=True)
    print(f"scaling: wrote {args.out}/scaling.{{json,csv,md}} in {meta['wall_s']} s", flush=True)


# --------------------------------------------------------------------------------------------
# One point (child process): build, compile ahead, fill, time, profile, report
# --------------------------------------------------------------------------------------------


def point_config(point: dict[str, Any]):
    """The point's TrainConfig: the env's preset at the point's sizes, warm-up off."""
    from td3_jax.config.presets import env_preset, preset
    from td3_jax.config.schema import TrainConfig

    name = point["preset"] or env_preset(point["env"])
    base = preset(name) if name else TrainConfig(env=point["env"])
    changes = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in point["set"])}
    n = point["num_envs"]
    return dataclasses.replace(
        base, env=point["env"], num_envs=n, batch_size=point["batch_size"], warmup_steps=0,
        eval_every=n * point["iterations"], total_steps=n * point["iterations"],
        buffer_size=n * point["buffer_steps"], replay_shards=point["replay_shards"], **changes,
    ), name  # fmt: skip


def fill_iterations(cfg) -> int:
    """Iterations after which every iteration updates: a batch stored and every slice holding
    a whole n-step run (see ``training.learning_started``), plus one."""
    return math.ceil(cfg.batch_size / cfg.num_envs) + cfg.n_step + 1


def abstract_inputs(compiled, program) -> tuple[Any, Any]:
    """Shapes, dtypes and shardings of the chunk's state and iteration count (no memory)."""
    import jax
    import jax.numpy as jnp

    state = jax.tree.map(
        lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s, weak_type=a.weak_type),
        program.abstract_state,
        compiled.shardings,
    )
    replicated = jax.tree.leaves(compiled.hyperparams)[0].sharding
    return state, jax.ShapeDtypeStruct((), jnp.int32, sharding=replicated)


def compile_point(cfg, devices: int) -> tuple[Any, dict[str, float]]:
    """``(programs, seconds)``: the run's :class:`~td3_jax.runner.programs.Programs` built,
    traced and compiled ahead, before any state exists (its ``chunk``, ``init`` and, with
    in-chunk evaluation, ``start_round`` compiled executables, which
    :meth:`~td3_jax.runner.programs.Programs.train_chunk` runs as a run does)."""
    from td3_jax.common import upstream
    from td3_jax.config.build import make_population, members
    from td3_jax.config.schema import validate
    from td3_jax.runner.programs import jitted
    from td3_jax.runner.sharding import make_mesh

    seconds, clock = {}, time.perf_counter()
    mesh = make_mesh(devices)
    validate(cfg, devices=mesh.size)
    program = make_population(cfg, members(cfg), devices=mesh.size, mesh=mesh)
    compiled = jitted(program, mesh)
    seconds["make_s"], clock = time.perf_counter() - clock, time.perf_counter()
    state, iterations = abstract_inputs(compiled, program)
    lowered = compiled.chunk.lower(compiled.hyperparams, state, iterations)
    seconds["trace_chunk_s"], clock = time.perf_counter() - clock, time.perf_counter()
    options = upstream.compile_options(mesh.devices.flat[0].platform, cfg.matmuls)
    chunk = lowered.compile(compiler_options=options)
    seconds["compile_chunk_s"], clock = time.perf_counter() - clock, time.perf_counter()
    init = compiled.init.lower().compile(compiler_options=options)
    seconds["compile_init_s"], clock = time.perf_counter() - clock, time.perf_counter()
    start_round = None
    if compiled.start_round is not None:  # (a program of its own, as in a run)
        start_round = compiled.start_round.lower(state).compile(compiler_options=options)
        seconds["compile_round_s"] = time.perf_counter() - clock
    return compiled._replace(chunk=chunk, init=init, start_round=start_round), seconds


def run_chunk(programs, state, iterations: int) -> tuple[Any, dict[str, Any], float]:
    """One chunk of the compiled ``programs`` (its round started first, as a run does),
    waited for: ``(state, metrics, seconds)``."""
    import jax
    import numpy as np

    start = time.perf_counter()
    state, metrics = programs.train_chunk(state, np.int32(iterations))
    jax.block_until_ready((state, metrics))
    return state, metrics, time.perf_counter() - start


def peak_gib_per_device() -> float | None:
    """The largest peak memory in use over the devices (GiB; ``None`` where not reported)."""
    import jax

    peaks = [(d.memory_stats() or {}).get("peak_bytes_in_use") for d in jax.local_devices()]
    peaks = [p for p in peaks if p is not None]
    return max(peaks) / 2**30 if peaks else None


_COLLECTIVE = re.compile(
    r"= (?P<shape>\(?[a-z0-9]+\[[^=]*?\]\S*\)?|\(.*?\)) (?P<op>all-reduce|all-gather|"
    r"reduce-scatter|all-to-all|collective-permute)(?P<start>-start)?\("
)
_ARRAY = re.compile(r"(?P<dtype>pred|[a-z]+(?P<bits>\d+))\[(?P<dims>[0-9,]*)\]")
_OP_NAME = re.compile(r'op_name="(?P<name>[^"]*)"')


def _bytes(shape: str, start: bool) -> int:
    """Bytes of the result arrays in an HLO shape (an async all-gather or permute start lists
    its operands, then its results: only the second half counts)."""
    sizes = []
    for array in _ARRAY.finditer(shape):
        dims = [int(x) for x in array.group("dims").split(",") if x]
        sizes.append(math.prod(dims) * int(array.group("bits") or 8) // 8)
    return sum(sizes[len(sizes) // 2 :] if start else sizes)


def collectives(hlo: str) -> list[dict[str, Any]]:
    """The cross-device collectives of an optimised HLO module: one entry per instruction with
    its kind, result shape, bytes and the JAX operations it reduces (``op_name``: a path with
    ``while/body/cond/branch_1_fun/while/body`` is inside the gradient updates' loop), in
    program order (async pairs counted once)."""
    found = []
    for line in hlo.splitlines():
        match = _COLLECTIVE.search(line)
        if not match:
            continue
        shape, op = match.group("shape"), match.group("op")
        start = bool(match.group("start")) and op in ("all-gather", "collective-permute")
        name = _OP_NAME.search(line)
        found.append({"op": op, "shape": shape[:200], "bytes": _bytes(shape, start),
                      "op_name": name.group("name")[:300] if name else None})  # fmt: skip
    return found


def summarize_collectives(found: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts and bytes per collective kind (each instruction counted once in the program text:
    those in the loop body run once per iteration or update)."""
    summary: dict[str, Any] = {}
    for item in found:
        entry = summary.setdefault(item["op"], {"count": 0, "bytes": 0})
        entry["count"] += 1
        entry["bytes"] += item["bytes"]
    return summary


def measure_point(point: dict[str, Any]) -> dict[str, Any]:
    """The point's numbers: compile seconds, then (holding the device lock) init, a filling
    chunk, the timed chunk and, when asked, a profiled one."""
    cfg, name = point_config(point)
    programs, seconds = compile_point(cfg, point["devices"])
    found = collectives(programs.chunk.as_text())
    arrive(point)
    wait_for_compiles(point)
    with open(point["lock"]) as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        state = programs.init()
        state, _, fill_s = run_chunk(programs, state, fill_iterations(cfg))
        state, metrics, chunk_s = run_chunk(programs, state, point["iterations"])
        if point["profile"]:
            profiled_s = profile_chunk(programs, state, point)
        peak = peak_gib_per_device()
    iters = point["iterations"]
    updates = iters * cfg.updates_per_iter
    return {**point, "preset": name, **{k: round(v, 2) for k, v in seconds.items()},
            "fill_s": round(fill_s, 3), "chunk_s": chunk_s,
            "profiled_chunk_s": profiled_s if point["profile"] else None,
            "updates_per_iter": cfg.updates_per_iter, "n_step": cfg.n_step,
            "env_steps_per_s": iters * cfg.env_steps_per_iter / chunk_s,
            "updates_per_s": updates / chunk_s, "samples_per_s": updates * cfg.batch_size / chunk_s,
            "updates_done": float(metrics["chunk_updates"][0]), "updates_expected": updates,
            "critic_loss": float(metrics["critic_loss"][0]), "peak_gib_per_device": peak,
            "collectives": summarize_collectives(found),
            "collective_list": found[:200]}  # fmt: skip


def arrive(point: dict[str, Any]) -> None:
    """Marks this point compiled (or failed) for the others waiting at the barrier."""
    if point.get("barrier"):
        (Path(point["barrier"]) / str(point["index"])).touch()


def wait_for_compiles(point: dict[str, Any], limit_s: float = 900.0) -> None:
    """With every point compiling at once (``--jobs`` >= points), waits until all have
    compiled, so no compile (GPU autotuning included) overlaps a measurement."""
    if not point.get("barrier"):
        return
    deadline = time.monotonic() + limit_s
    while len(list(Path(point["barrier"]).iterdir())) < point["barrier_size"]:
        if time.monotonic() > deadline:
            print("scaling: gave up waiting for the other points' compiles", file=sys.stderr)
            return
        time.sleep(0.5)


def profile_chunk(programs, state, point: dict[str, Any]) -> float:
    """One more timed chunk under ``jax.profiler.trace``; its seconds (profiler included)."""
    import jax

    name = f"{point['env'].replace('/', '_')}_{point['mode']}_d{point['devices']}"
    where = Path(point["profile"]) / name
    with jax.profiler.trace(str(where)):
        _, _, seconds = run_chunk(programs, state, point["iterations"])
    return seconds


def child_main(point: dict[str, Any]) -> None:
    """Measures ``point`` and prints its row after :data:`RESULT_MARK` (an ``error`` row on
    failure, exit code 1)."""
    try:
        row = measure_point(point)
    except Exception as err:  # e.g. out of memory: recorded, the command goes on
        row = {**point, "error": f"{type(err).__name__}: {err}"[:2000]}
        arrive(point)  # (again, if it failed after compiling: harmless)
    print(RESULT_MARK + json.dumps(row), flush=True)
    sys.exit(1 if row.get("error") else 0)


if __name__ == "__main__":
    main()
