"""The benchmark suite: td3-jax's runs of each task, the baselines where asked, and the tables
and figures of docs/benchmarks.md, from one command on a GPU machine.

    python -m benchmarks.suite --tasks t1 g1 --seeds 3 --out DIR [--baselines ppo]

Assumes the project installed with ``pip install -e '.[locomotion,warp]'`` (Brax's PPO and SAC
come with Brax). Each run is one process on one GPU (``CUDA_VISIBLE_DEVICES``); with several
GPUs, as many runs go at once, each on its own. Per task and seed:

* td3-jax: ``td3-jax train --preset TASK --seed S`` (the task's length, see
  :mod:`benchmarks.tasks`) into ``DIR/runs/TASK/sS``, its output timed from launch in
  ``DIR/logs/TASK-sS.log``. Run again (after a lost machine, say), the suite resumes each run
  from its run directory (``--resume``: exactly where its newest checkpoint left it), leaves a
  finished one alone, and moves a run that stopped before its first checkpoint aside
  (``sS.lost-N``) to start it again.
* baselines (``--baselines``): Playground's PPO recipe on MuJoCo Warp for the Playground
  robots, Brax's PPO and SAC recipes for the Brax tasks, through :mod:`benchmarks.compare`, each
  to its recipe's length (or ``--budget-s``), into ``DIR/baselines/TASK-ALGO-sS``; a baseline
  that did not finish starts again.

Then ``DIR/TASK.csv`` (every evaluation, :mod:`benchmarks.curves`), ``DIR/TASK.png`` and
``DIR/report.md`` (:mod:`benchmarks.report`): per task the start-up (first evaluation) and
steady env steps/s of every program beside its curve, returns at fixed env steps (IQM over
seeds), the time from launch to the reference returns. ``--report-only`` writes these from
what ``DIR`` holds, running nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import queue
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

from benchmarks import curves, report
from benchmarks.tasks import TASKS, Task

#: The programs a baseline name stands for: Playground's PPO recipe on the robots, Brax's
#: recipes on the Brax tasks.
BASELINE_PROGRAMS = {("ppo", True): "Playground PPO", ("ppo", False): "Brax PPO",
                     ("sac", False): "Brax SAC"}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Job:
    """One run of the suite: ``program`` (td3-jax or a baseline's name) on ``task``, one seed."""

    task: Task
    program: str
    seed: int
    out: Path

    @property
    def name(self) -> str:
        """``t1-s0``, ``t1-ppo-s0``: the run's name in the logs."""
        algo = "" if self.program == curves.TD3_JAX else f"-{self.algo}"
        return f"{self.task.name}{algo}-s{self.seed}"

    @property
    def algo(self) -> str:
        """``td3``, ``ppo`` or ``sac``."""
        return "td3" if self.program == curves.TD3_JAX else self.program.split()[-1].lower()


# --------------------------------------------------------------------------------------------
# What a rerun does with each run's folder
# --------------------------------------------------------------------------------------------

START, RESUME, DONE, RESTART = "start", "resume", "done", "restart"


@dataclasses.dataclass(frozen=True)
class RunState:
    """What a td3-jax run directory holds: whether it exists, its newest complete checkpoint
    (chunks done; None: none), its run's chunks (None: no readable config.json), and whether
    it holds a run's outputs (config.json, metrics.jsonl, ...)."""

    exists: bool
    newest_checkpoint: int | None = None
    chunks: int | None = None
    outputs: bool = False


def decide(state: RunState) -> str:
    """:data:`DONE` for a run whose newest checkpoint ends it, :data:`RESUME` for one with a
    checkpoint short of that, :data:`RESTART` for one that stopped before its first checkpoint
    (its outputs move aside), else :data:`START`."""
    if state.newest_checkpoint is not None:
        finished = state.chunks is not None and state.newest_checkpoint >= state.chunks
        return DONE if finished else RESUME
    return RESTART if state.outputs else START


def run_state(run_dir: Path) -> RunState:
    """:class:`RunState` of ``run_dir`` as the runner reads it (its checkpoints and config)."""
    from td3_jax.config.schema import ConfigError
    from td3_jax.runner import rundir

    if not run_dir.is_dir():
        return RunState(exists=run_dir.exists())
    steps = rundir.checkpoint_steps(run_dir)
    try:
        chunks = rundir.load_config(run_dir).num_chunks
    except (ConfigError, OSError, ValueError, TypeError):
        chunks = None
    return RunState(True, steps[-1] if steps else None, chunks,
                    bool(rundir.previous_outputs(run_dir)))  # fmt: skip


def baseline_state(job: Job) -> str:
    """:data:`DONE` for a baseline whose result says it finished, :data:`RESTART` for one that
    left anything else (a baseline cannot resume), else :data:`START`."""
    result = baseline_result(job)
    if result is not None and result.get("status") == "ok":
        return DONE
    return RESTART if job.out.exists() else START


def baseline_result(job: Job) -> dict | None:
    """The result :mod:`benchmarks.compare` wrote for ``job`` (None: none, or unreadable)."""
    found = sorted(job.out.glob(f"compare_*_parts/{job.algo}.json")) if job.out.is_dir() else []
    for candidate in found:
        try:
            return json.loads(candidate.read_text())
        except (OSError, ValueError):
            continue
    return None


def set_aside(folder: Path) -> Path:
    """Moves ``folder`` to ``NAME.lost-N`` (the first N free) and returns where it went."""
    n = 1
    while folder.with_name(f"{folder.name}.lost-{n}").exists():
        n += 1
    target = folder.with_name(f"{folder.name}.lost-{n}")
    folder.rename(target)
    return target


# --------------------------------------------------------------------------------------------
# The commands
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Settings:
    """What applies to every run of one suite command."""

    budget_s: float | None = None
    total_steps: int | None = None
    td3_flags: tuple[str, ...] = ()


def td3_command(job: Job, action: str, settings: Settings) -> list[str]:
    """``td3-jax train`` for ``job``: a fresh run of its task's preset and seed, or (``action``
    :data:`RESUME`) the resume of its run directory."""
    command = [sys.executable, "-m", "td3_jax", "train", "--out", str(job.out)]
    steps = settings.total_steps or job.task.total_steps
    if action == RESUME:
        command.append("--resume")
    else:
        command += ["--preset", job.task.preset, "--seed", str(job.seed), *settings.td3_flags]
    if steps:
        command += ["--total-steps", str(steps)]
    if settings.budget_s:
        command += ["--time-budget-s", f"{settings.budget_s:g}"]
    return command


def baseline_command(job: Job, settings: Settings) -> list[str]:
    """:mod:`benchmarks.compare` running ``job``'s baseline alone: its recipe's own number of
    evaluations, to its own length (or the budget), Playground's robots on MuJoCo Warp."""
    command = [sys.executable, "-m", "benchmarks.compare", "--env", job.task.env, "--algos",
               job.algo, "--out", str(job.out), "--seed", str(job.seed), "--num-evals", "0"]
    if settings.budget_s:
        command += ["--budget-s", f"{settings.budget_s:g}"]
    if job.task.robot:
        command += ["--impl", "warp"]
    return command


def plan(names: list[str], seeds: int, baselines: list[str], out: Path) -> list[Job]:
    """Every job of the command: per task, td3-jax's seeds, then each baseline's."""
    jobs = []
    for name in names:
        task = TASKS[name]
        jobs += [Job(task, curves.TD3_JAX, s, out / "runs" / name / f"s{s}") for s in range(seeds)]
        for algo in baselines:
            program = BASELINE_PROGRAMS[(algo, task.robot)]
            jobs += [Job(task, program, s, out / "baselines" / f"{name}-{algo}-s{s}")
                     for s in range(seeds)]  # fmt: skip
    return jobs


def check_baselines(names: list[str], baselines: list[str]) -> str | None:
    """Why ``baselines`` cannot run on the tasks ``names`` (None: they can)."""
    refused = [f"{algo} on {name}" for name in names for algo in baselines
               if (algo, TASKS[name].robot) not in BASELINE_PROGRAMS]  # fmt: skip
    if not refused:
        return None
    return (f"no baseline {', '.join(refused)}: the Playground robots have Playground's PPO "
            "recipe (ppo), the Brax tasks Brax's PPO and SAC (ppo, sac)")  # fmt: skip


# --------------------------------------------------------------------------------------------
# Running the jobs, one a GPU
# --------------------------------------------------------------------------------------------


def gpu_name(listed: str) -> str:
    """A short GPU name (``H200``) from nvidia-smi's (``NVIDIA H200``, ``NVIDIA H100 80GB
    HBM3``)."""
    words = listed.strip().removeprefix("NVIDIA").split()
    return words[0] if words else "GPU"


def visible_gpus(visible: str | None, listed: list[str]) -> list[tuple[str, str]]:
    """``(CUDA_VISIBLE_DEVICES value, short name)`` per GPU to use: those ``visible`` names
    (the caller's ``CUDA_VISIBLE_DEVICES``), else every GPU nvidia-smi ``listed``
    (``NAME`` per line); one ``("", "CPU")`` where there is none."""
    names = [gpu_name(line) for line in listed if line.strip()]
    if visible is not None and visible.strip():
        ids = [v.strip() for v in visible.split(",") if v.strip()]
        return [(v, names[int(v)] if v.isdigit() and int(v) < len(names) else "GPU")
                for v in ids]  # fmt: skip
    return [(str(i), name) for i, name in enumerate(names)] or [("", "CPU")]


def _listed_gpus() -> list[str]:
    try:
        done = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                              capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired):
        return []
    return done.stdout.splitlines() if done.returncode == 0 else []


def _copy_stamped(stream, log: Path, launch: float) -> None:
    """Copies a child's output into ``log``, each line after the seconds since its launch."""
    with log.open("a") as f:
        for line in stream:
            f.write(f"{time.perf_counter() - launch:9.1f}  {line}")
            f.flush()


def run_process(command: list[str], log: Path, gpu: str,
                watch: Path | None = None) -> tuple[int, float | None]:  # fmt: skip
    """Runs ``command`` on the GPU ``gpu`` (``CUDA_VISIBLE_DEVICES``), its output timed from
    launch into ``log``; returns its exit status and, where ``watch`` names a metrics.jsonl,
    the seconds from launch to the run's clock (:func:`benchmarks.curves.launch_offset`) once
    its first record appears."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if gpu:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as f:
        f.write("# " + shlex.join(command).replace("\n", "\\n") + "\n")  # (one line)
    launch = time.perf_counter()
    process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)  # fmt: skip
    copier = threading.Thread(target=_copy_stamped, args=(process.stdout, log, launch))
    copier.start()
    offset = None
    while process.poll() is None:
        if watch is not None and offset is None:
            offset = _first_offset(watch, time.perf_counter() - launch)
        time.sleep(0.5)
    copier.join()
    return process.returncode, offset


def _first_offset(metrics: Path, seen_s: float) -> float | None:
    try:
        found = curves.records(metrics) if metrics.is_file() else []
    except (OSError, ValueError):
        return None  # (a line half written: the next look reads it whole)
    return curves.launch_offset(seen_s, found[0]) if found else None


def _info_path(job: Job, out: Path) -> Path:
    return out / "logs" / f"{job.name}.json"


def read_info(job: Job, out: Path) -> dict:
    """What the suite noted about ``job`` (its GPU, the launch offset of its first process)."""
    try:
        return json.loads(_info_path(job, out).read_text())
    except (OSError, ValueError):
        return {}


def run_job(job: Job, gpu: tuple[str, str], out: Path, settings: Settings) -> tuple[str, bool]:
    """Runs (or resumes, or skips) ``job`` on ``gpu``; returns what it did, and whether it
    ended well."""
    td3 = job.program == curves.TD3_JAX
    action = decide(run_state(job.out)) if td3 else baseline_state(job)
    if action == DONE:
        return "finished before", True
    if action == RESTART:
        where = set_aside(job.out)
        print(f"{job.name}: stopped before its first checkpoint; moved to {where}", flush=True)
    job.out.parent.mkdir(parents=True, exist_ok=True)
    command = td3_command(job, action, settings) if td3 else baseline_command(job, settings)
    info = read_info(job, out) if action == RESUME else {}
    info.setdefault("gpu", gpu[1])
    code, offset = run_process(command, out / "logs" / f"{job.name}.log", gpu[0],
                               job.out / "metrics.jsonl" if td3 else None)  # fmt: skip
    if offset is not None and "launch_offset_s" not in info:
        info["launch_offset_s"] = offset
    info.setdefault("commands", []).append(command)
    _info_path(job, out).write_text(json.dumps(info, indent=1) + "\n")
    return f"{'resumed' if action == RESUME else 'ran'}, exit status {code}", code == 0


def run_all(jobs: list[Job], gpus: list[tuple[str, str]], out: Path, settings: Settings) -> bool:
    """Runs ``jobs`` with one at a time on each GPU of ``gpus``; True if every one ended well."""
    waiting: queue.Queue[Job] = queue.Queue()
    for job in jobs:
        waiting.put(job)
    failed: list[str] = []

    def worker(gpu: tuple[str, str]) -> None:
        while True:
            try:
                job = waiting.get_nowait()
            except queue.Empty:
                return
            print(f"{job.name}: {job.program} on {gpu[1]} {gpu[0]}".rstrip(), flush=True)
            ended, ok = run_job(job, gpu, out, settings)
            print(f"{job.name}: {ended}", flush=True)
            if not ok:
                failed.append(job.name)

    threads = [threading.Thread(target=worker, args=(gpu,)) for gpu in gpus]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if failed:
        print(f"these runs did not end well (their logs are in {out / 'logs'}): "
              f"{', '.join(sorted(failed))}", flush=True)  # fmt: skip
    return not failed


# --------------------------------------------------------------------------------------------
# The report
# --------------------------------------------------------------------------------------------


def baseline_label(job: Job, settings: Settings) -> str:
    """A baseline's settings as the tables name them: whose recipe, on which physics."""
    if job.task.robot:
        label = "Playground's recipe, MuJoCo Warp"
    elif job.algo == "ppo" and job.task.env.startswith("brax/"):
        label = "Brax's recipe"
    else:
        label = "Playground's recipe"
    return label + (f", {settings.budget_s:g}-s budget" if settings.budget_s else "")


def job_points(job: Job, out: Path, settings: Settings) -> list[curves.Point]:
    """Every evaluation ``job`` recorded (none for a run that has not recorded one)."""
    from benchmarks.humanoid_table import run_label

    info = read_info(job, out)
    gpu = info.get("gpu", "GPU")
    if job.program != curves.TD3_JAX:
        result = baseline_result(job) or {}
        return [curves.Point(job.program, baseline_label(job, settings), job.seed, gpu,
                             r["wall_s"], r["env_steps"], r["eval_return"],
                             r.get("eval_return_std"))
                for r in result.get("rows", [])]  # fmt: skip
    metrics = job.out / "metrics.jsonl"
    if not metrics.is_file():
        return []
    config = json.loads((job.out / "config.json").read_text())
    label = run_label(config) if config.get("preset") else job.task.preset
    return curves.from_records(curves.records(metrics), run=label, gpu=gpu,
                               launch_offset_s=info.get("launch_offset_s", 0.0))  # fmt: skip


def write_report(jobs: list[Job], out: Path, settings: Settings) -> list[str]:
    """``TASK.csv`` and ``TASK.png`` of every task with an evaluation, and ``report.md``;
    returns the names of the tasks reported."""
    sections, reported = [], []
    for task in dict.fromkeys(job.task for job in jobs):
        points = [p for job in jobs if job.task == task for p in job_points(job, out, settings)]
        if not points:
            continue
        curves.write(out / f"{task.name}.csv", points)
        report.plot(task, points, out / f"{task.name}.png")
        sections.append(report.task_markdown(task, points, f"{task.name}.png"))
        reported.append(task.name)
    if sections:
        (out / "report.md").write_text("\n".join(sections))
    return reported


# --------------------------------------------------------------------------------------------
# The command line
# --------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.suite", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("--tasks", nargs="+", required=True, choices=list(TASKS))
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0 to N-1 (default 3)")
    parser.add_argument("--out", type=Path, required=True, help="the suite's folder")
    parser.add_argument("--baselines", nargs="*", default=[], choices=["ppo", "sac"],
                        help="ppo: Playground's PPO recipe on the robots, Brax's on the Brax "
                        "tasks; sac: Brax's SAC (Brax tasks)")  # fmt: skip
    parser.add_argument("--gpus", type=int, default=None,
                        help="use this many GPUs (default: every visible one)")  # fmt: skip
    parser.add_argument("--budget-s", type=float, default=None,
                        help="stop each run after this many seconds (default: its length)")
    parser.add_argument("--total-steps", type=int, default=None,
                        help="td3-jax's env steps per run (default: the task's)")  # fmt: skip
    parser.add_argument("--td3-flags", default="",
                        help="more td3-jax train flags for every run, e.g. '--pushes on'")
    parser.add_argument("--report-only", action="store_true",
                        help="run nothing: the tables and figures of what --out holds")
    return parser


def check_args(args: argparse.Namespace) -> str | None:
    """Why the arguments cannot run (one line; None where they can)."""
    if args.seeds < 1:
        return f"--seeds {args.seeds}: at least one seed"
    for name in ("gpus", "budget_s", "total_steps"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            return f"--{name.replace('_', '-')} {value}: must be positive"
    if args.out.exists() and not args.out.is_dir():
        return f"--out {args.out} is a file, not a folder"
    for flag in ("--out", "--seed", "--preset", "--resume"):
        if flag in shlex.split(args.td3_flags):
            return f"--td3-flags may not set {flag}: the suite sets it for each run"
    return check_baselines(args.tasks, args.baselines)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    problem = check_args(args)
    if problem:
        parser.error(problem)
    settings = Settings(args.budget_s, args.total_steps, tuple(shlex.split(args.td3_flags)))
    jobs = plan(args.tasks, args.seeds, args.baselines, args.out)
    ok = True
    if not args.report_only:
        gpus = visible_gpus(os.environ.get("CUDA_VISIBLE_DEVICES"), _listed_gpus())
        ok = run_all(jobs, gpus[: args.gpus or len(gpus)], args.out, settings)
    reported = write_report(jobs, args.out, settings)
    if not reported:
        print(f"no evaluation to report in {args.out}", file=sys.stderr)
        return 1
    print(f"wrote {args.out / 'report.md'} ({', '.join(reported)})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
