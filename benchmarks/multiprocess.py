"""Rehearsal of a multi-host run on one host: N processes x M devices against 1 x N*M.

Starts the same ``td3-jax train`` configuration twice from the same seed:

* *multi*: N processes through ``jax.distributed`` (coordinator on a free localhost port,
  ``--coordinator-address/--num-processes/--process-id``), each driving M devices (M forced host
  devices on a CPU; GPUs ``i*M .. i*M+M-1`` on a GPU host, through ``CUDA_VISIBLE_DEVICES``);
* *single*: one process driving N*M devices (``--devices N*M``).

Both runs use the same global sizes (and, on GPUs, XLA's deterministic ops unless ``XLA_FLAGS``
says otherwise), so every record of ``metrics.jsonl`` (losses, Q, targets,
evaluation returns) should agree; the comparison reports the largest absolute and relative
difference per quantity and whether all are within ``--rtol``/``--atol``. Outputs in ``--out``:
``multi/`` and ``single/`` (the run directories), ``comparison.json`` and ``comparison.md``.
Flags after ``--`` (or unknown ones) go to ``td3-jax train`` and replace the default tiny
Pendulum configuration (:data:`TINY`).

  python -m benchmarks.multiprocess --processes 2 --devices-per-process 2 --out /tmp/mp  # CPU
  python -m benchmarks.multiprocess --processes 2 --devices-per-process 4 --out DIR/mp \
      -- --env brax/ant --num-envs 8192 --batch-size 16384 --total-steps 4194304 \
      --eval-every 2097152 --replay-shards 8 --warmup-steps 0                               # GPU
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from td3_jax.cli.local_processes import free_port

TINY = ["--env", "gymnax/Pendulum-v1", "--num-envs", "8", "--total-steps", "512",
        "--eval-every", "256", "--warmup-steps", "64", "--batch-size", "64",
        "--updates-per-iter", "2", "--hidden-sizes", "32", "32", "--eval-envs", "4",
        "--buffer-size", "512"]  # fmt: skip
COMPARED = ("critic_loss", "actor_loss", "q_mean", "target_mean", "eval_return_mean",
            "eval_return_min", "eval_return_max")  # fmt: skip
EXACT = ("env_steps", "updates", "devices")
DETERMINISTIC = "--xla_gpu_deterministic_ops=true"  # unless XLA_FLAGS sets it (e.g. =false)


def parse(argv: list[str] | None = None) -> tuple[argparse.Namespace, list[str]]:
    """The rehearsal's own flags, and the ``td3-jax train`` flags (default :data:`TINY`)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--devices-per-process", type=int, default=2)
    p.add_argument("--platform", choices=["auto", "cpu", "gpu"], default="auto")
    p.add_argument("--rtol", type=float, default=1e-4)
    p.add_argument("--atol", type=float, default=1e-5)
    p.add_argument("--timeout-s", type=float, default=1200.0, help="per run")
    p.add_argument("--side-by-side", action="store_true",
                   help="CPU only: run single and multi at once")  # fmt: skip
    p.add_argument("--out", type=Path, default=Path("multiprocess-rehearsal"))
    args, rest = p.parse_known_args(argv)
    rest = [a for a in rest if a != "--"]
    if args.processes < 2 or args.devices_per_process < 1:
        p.error("--processes must be at least 2 and --devices-per-process at least 1")
    return args, rest or list(TINY)


def platform(choice: str) -> str:
    """``cpu`` or ``gpu``: the choice, or for ``auto`` the platform JAX finds first."""
    if choice != "auto":
        return choice
    code = "import jax; print(jax.devices()[0].platform)"
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    return "gpu" if proc.returncode == 0 and "gpu" in proc.stdout else "cpu"


def process_env(kind: str, devices: list[int], **extra: str) -> dict[str, str]:
    """A process's environment: ``len(devices)`` forced host devices on a CPU, the GPUs
    ``devices`` on a GPU host; ``extra`` added."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COORDINATOR")}
    for name in ("JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        env.pop(name, None)
    if kind == "cpu":
        flags = [f for f in env.get("XLA_FLAGS", "").split() if "device_count" not in f]
        env["XLA_FLAGS"] = " ".join([*flags, f"--xla_force_host_platform_device_count="
                                     f"{len(devices)}"])  # fmt: skip
        env["JAX_PLATFORMS"] = "cpu"
    else:
        # GPU reductions (scatter-adds, NCCL's sums) are not bit-deterministic by default, and
        # RL amplifies a last-bit difference within a few updates; deterministic ops make the
        # two runs comparable exactly (measured: equal to the bit on 2 H200s; without them,
        # returns 75% apart after 64 iterations).
        flags = env.get("XLA_FLAGS", "").split()
        if not any("xla_gpu_deterministic_ops" in f for f in flags):
            env["XLA_FLAGS"] = " ".join([*flags, DETERMINISTIC])
        given = os.environ.get("CUDA_VISIBLE_DEVICES")
        ids = [s for s in given.split(",") if s.strip()] if given else None
        ids = ids or [str(i) for i in range(max(devices) + 1)]
        env["CUDA_VISIBLE_DEVICES"] = ",".join(ids[i] for i in devices)
    env.update(extra)
    return env


def train_command(flags: list[str], out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "td3_jax", "train", *flags, "--quiet", "--out", str(out),
            *extra]  # fmt: skip


def wait_all(procs: list[subprocess.Popen], timeout_s: float) -> list[int]:
    """Waits for every process; when one fails or time runs out, stops the others (they would
    wait for it at the next collective). Returns the exit codes."""
    deadline = time.monotonic() + timeout_s
    while any(p.poll() is None for p in procs):
        failed = any(p.returncode not in (None, 0) for p in procs)
        if failed or time.monotonic() > deadline:
            for p in procs:
                if p.poll() is None:
                    p.kill()
            break
        time.sleep(0.5)
    return [p.wait() for p in procs]


def launch(cmds: list[list[str]], envs: list[dict], log_dir: Path, timeout_s: float) -> float:
    """Runs the commands side by side (output to ``log_dir/<i>.log``); their wall seconds.
    ``RuntimeError`` with the end of the failed ones' output when one fails."""
    log_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    procs, logs = [], [log_dir / f"{i}.log" for i in range(len(cmds))]
    for cmd, env, log in zip(cmds, envs, logs, strict=True):
        with log.open("w") as f:
            procs.append(subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT))
    codes = wait_all(procs, timeout_s)
    failed = [f"process {i} (exit code {c}, {logs[i]}): {logs[i].read_text()[-3000:]}"
              for i, c in enumerate(codes) if c != 0]  # fmt: skip
    if failed:
        raise RuntimeError("\n".join(failed))
    return time.perf_counter() - start


def multi_commands(args: argparse.Namespace, kind: str, flags: list[str]) -> tuple[list, list]:
    """Commands and environments of the N processes of the run into ``out/multi``."""
    n, m, port = args.processes, args.devices_per_process, free_port()
    cmds, envs = [], []
    for i in range(n):
        cmds.append(train_command(flags, args.out / "multi", "--coordinator-address",
                                  f"localhost:{port}", "--num-processes", str(n),
                                  "--process-id", str(i)))  # fmt: skip
        envs.append(process_env(kind, list(range(i * m, (i + 1) * m))))
    return cmds, envs


def single_command(args: argparse.Namespace, kind: str, flags: list[str]) -> tuple[list, dict]:
    """Command and environment of the one-process run over all N*M devices (``out/single``)."""
    total = args.processes * args.devices_per_process
    cmd = train_command(flags, args.out / "single", "--devices", str(total))
    return cmd, process_env(kind, list(range(total)))


def run_both(args: argparse.Namespace, kind: str, flags: list[str]) -> dict[str, float]:
    """The multi run, then the single one (side by side with ``--side-by-side``); wall s."""
    cmds, envs = multi_commands(args, kind, flags)
    cmd, env = single_command(args, kind, flags)
    logs = args.out / "logs"
    if args.side_by_side:
        return {"together_wall_s": launch([*cmds, cmd], [*envs, env], logs, args.timeout_s)}
    return {"multi_wall_s": launch(cmds, envs, logs / "multi", args.timeout_s),
            "single_wall_s": launch([cmd], [env], logs / "single", args.timeout_s)}  # fmt: skip


def records(run_dir: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]


def _difference(a: Any, b: Any) -> tuple[float, float]:
    """``(absolute, relative)`` difference of two numbers (NaN/None on both sides: 0)."""
    if a is None or b is None or math.isnan(a) or math.isnan(b):
        same = (a is None or math.isnan(a)) and (b is None or math.isnan(b))
        return (0.0, 0.0) if same else (math.inf, math.inf)
    diff = abs(a - b)
    return diff, diff / max(abs(a), abs(b), 1e-12)


def compare(multi: list[dict], single: list[dict], rtol: float, atol: float) -> dict[str, Any]:
    """Largest differences per quantity over the records; ``equal`` when the counts agree
    exactly and every quantity within ``atol + rtol * |value|``."""
    result: dict[str, Any] = {"records": [len(multi), len(single)], "quantities": {}}
    counts_equal = len(multi) == len(single) and all(
        a.get(k) == b.get(k) for a, b in zip(multi, single, strict=False) for k in EXACT
    )
    within = counts_equal
    for key in COMPARED:
        pairs = [(a.get(key), b.get(key)) for a, b in zip(multi, single, strict=False)]
        diffs = [_difference(a, b) for a, b in pairs]
        # (a diverged side logs null: inf difference, never within tolerance)
        ok = all(d == 0.0 or (math.isfinite(d) and d <= atol + rtol * max(abs(a), abs(b)))
                 for (d, _), (a, b) in zip(diffs, pairs, strict=True))  # fmt: skip
        result["quantities"][key] = {"max_abs_diff": max((d for d, _ in diffs), default=0.0),
                                     "max_rel_diff": max((r for _, r in diffs), default=0.0),
                                     "multi": [a for a, _ in pairs],
                                     "single": [b for _, b in pairs], "within": ok}  # fmt: skip
        within = within and ok
    result["counts_equal"] = counts_equal
    result["max_abs_diff"] = max(q["max_abs_diff"] for q in result["quantities"].values())
    result["equal"] = within
    return result


def markdown(meta: dict[str, Any], result: dict[str, Any]) -> str:
    lines = [f"# Multi-process rehearsal, {meta['date']}", "",
             f"{meta['processes']} processes x {meta['devices_per_process']} {meta['platform']} "
             f"devices against 1 x {meta['processes'] * meta['devices_per_process']}; "
             f"train flags: `{' '.join(meta['train_flags'])}`; wall: "
             + ", ".join(f"{k[:-7]} {v:.1f} s" for k, v in meta.items() if k.endswith("_wall_s"))
             + ".", "",
             f"Equal within rtol {meta['rtol']:g} / atol {meta['atol']:g}: **{result['equal']}**"
             f" (counts equal: {result['counts_equal']}; max abs diff "
             f"{result['max_abs_diff']:.3g}).", "",
             "| quantity | max abs diff | max rel diff | within |",
             "| --- | ---: | ---: | --- |"]  # fmt: skip
    for key, q in result["quantities"].items():
        lines.append(f"| {key} | {q['max_abs_diff']:.3g} | {q['max_rel_diff']:.3g} | "
                     f"{q['within']} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    args, flags = parse(argv)
    kind = platform(args.platform)
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "platform": kind,
            "processes": args.processes, "devices_per_process": args.devices_per_process,
            "train_flags": flags, "rtol": args.rtol, "atol": args.atol}  # fmt: skip
    if args.side_by_side and kind != "cpu":
        sys.exit("multiprocess: --side-by-side is for CPU devices (the runs would share GPUs)")
    try:
        meta.update(run_both(args, kind, flags))
    except RuntimeError as err:
        sys.exit(f"multiprocess: a run failed:\n{err}")
    result = compare(records(args.out / "multi"), records(args.out / "single"),
                     args.rtol, args.atol)  # fmt: skip
    (args.out / "comparison.json").write_text(json.dumps({"meta": meta, **result}, indent=1))
    (args.out / "comparison.md").write_text(markdown(meta, result))
    print(markdown(meta, result), flush=True)


if __name__ == "__main__":
    main()
