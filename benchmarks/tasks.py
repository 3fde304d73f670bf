"""The benchmark tasks: what td3-jax runs on each, what it is compared with, and what its tables
report.

Each :class:`Task` names the environment and the td3-jax preset, how long the runs are, the env
steps (or seconds from launch) at which the tables give returns, the reference returns whose
time from launch they give, the baselines the suite can run beside it (``ppo``, ``sac``), and
the published results shown beside the measured ones.

Published figures (other people's runs, on other hardware):

* FlashSAC (arXiv 2604.04539; its repository's ``results/stateRL_gpusim``): final returns at
  50M env steps, 5 seeds, on the four Playground humanoid tasks, beside FastTD3's and PPO's
  (:data:`FINALS_AT_50M`).
* FastTD3 (Seo et al. 2025, arXiv 2505.22642): its learning curves on one A100, with wall-clock
  (``benchmarks/published/fasttd3_playground.csv``, :func:`fasttd3_curve`).
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

PUBLISHED_CURVES = Path(__file__).parent / "published" / "fasttd3_playground.csv"

#: Final returns at 50M env steps (5 seeds) in FlashSAC's table: FlashSAC, FastTD3, PPO.
FINALS_AT_50M: dict[str, dict[str, float]] = {
    "T1JoystickFlatTerrain": {"FlashSAC": 38.5, "FastTD3": 35.0, "PPO": 34.5},
    "T1JoystickRoughTerrain": {"FlashSAC": 34.6, "FastTD3": 30.6, "PPO": 18.7},
    "G1JoystickFlatTerrain": {"FlashSAC": 39.9, "FastTD3": 31.5, "PPO": 23.4},
    "G1JoystickRoughTerrain": {"FlashSAC": 34.1, "FastTD3": 27.9, "PPO": 19.3},
}


@dataclasses.dataclass(frozen=True)
class Reference:
    """A return whose time from launch the tables give: ``value``, or (``value`` None) the last
    return of ``program``'s run in the same data (e.g. Brax PPO's final): the run named
    ``run`` where there is one, else its only run."""

    label: str
    value: float | None = None
    program: str | None = None
    run: str | None = None


@dataclasses.dataclass(frozen=True)
class Task:
    """One benchmark task (see the module docstring)."""

    name: str
    title: str
    env: str
    preset: str
    #: ``--total-steps`` of the td3-jax runs (None: the preset's own).
    total_steps: int | None
    #: Where the tables give returns: env steps, or seconds from launch where ``by_time``.
    points: tuple[int, ...]
    by_time: bool = False
    references: tuple[Reference, ...] = ()
    #: The baselines ``--baselines`` may ask for on this task.
    baselines: tuple[str, ...] = ()
    #: td3-jax runs shown in the task's table beside the preset's: those whose name starts
    #: with one of these (e.g. ``t1 --pushes on``); the others are in its table of settings.
    shown: tuple[str, ...] = ()
    #: Where the table of settings gives returns (default: ``points``).
    settings_points: tuple[int, ...] = ()

    def in_main_table(self, run: str) -> bool:
        """Whether the td3-jax run ``run`` is a row of the task's table (else of its table of
        settings): the preset's own, or one that :attr:`shown` names."""
        return run == self.preset or any(run.startswith(prefix) for prefix in self.shown)

    @property
    def task_id(self) -> str:
        """The environment's name without its source (``T1JoystickFlatTerrain``)."""
        return self.env.partition("/")[2]

    @property
    def robot(self) -> bool:
        """A Playground robot (its PPO baseline is Playground's recipe), else a Brax task."""
        return self.task_id in FINALS_AT_50M


def fasttd3_curve(task_id: str, path: Path = PUBLISHED_CURVES) -> list[tuple[float, int, float]]:
    """FastTD3's published curve for ``task_id``: ``(wall_s, env_steps, return)`` in order (the
    files' (0, 0) placeholder rows left out); empty for a task it did not publish."""
    with Path(path).open(newline="") as f:
        rows = [r for r in csv.DictReader(f)
                if r["task"] == task_id and r["algorithm"] == "FastTD3"]  # fmt: skip
    points = [(float(r["wall_clock_min"]) * 60, int(r["env_steps"]), float(r["eval_return_mean"]))
              for r in rows]  # fmt: skip
    return [p for p in points if (p[0], p[2]) != (0.0, 0.0)]


def _shown_robot_runs(preset: str) -> tuple[str, ...]:
    """A robot's td3-jax runs in its main table besides the preset's: pushes on, two GPUs (one
    process, or one per GPU), and the runs timed beside Playground's PPO on the other GPU of one
    command (named with a comma after the preset's name: ``t1, 300-s budget, beside
    Playground PPO``)."""
    return (f"{preset} --pushes on", f"{preset} --devices 2", f"{preset} --local-processes 2",
            f"{preset}, ")  # fmt: skip


def _robot(name: str, title: str, env: str) -> Task:
    """A Playground humanoid: 53.2M env steps (13 evaluations of 4.096M), returns at 12.3M,
    24.6M and 53.2M, the times to FastTD3's and FlashSAC's finals, Playground's PPO."""
    task_id = env.partition("/")[2]
    fast = fasttd3_curve(task_id)[-1][2]
    flash = FINALS_AT_50M[task_id]["FlashSAC"]
    return Task(name, title, env, preset=name, total_steps=53_248_000,
                points=(12_288_000, 24_576_000, 53_248_000),
                references=(Reference(f"FastTD3's final {fast:.1f}", fast),
                            Reference(f"FlashSAC's final {flash:.1f}", flash)),
                baselines=("ppo",), shown=_shown_robot_runs(name))  # fmt: skip


def _brax(name: str, title: str, env: str, ppo_run: str = "Brax's recipe") -> Task:
    """A Brax task against Brax PPO and SAC: each program to its own run length, returns at
    60, 120 and 180 s from launch, the time to Brax PPO's final return."""
    return Task(name, title, env, preset=name, total_steps=None, points=(60, 120, 180),
                by_time=True,
                references=(Reference("Brax PPO's final", program="Brax PPO", run=ppo_run),),
                baselines=("ppo", "sac"), shown=(f"{name} (",),
                settings_points=(60, 90, 120))  # fmt: skip


TASKS: dict[str, Task] = {
    task.name: task
    for task in (
        _robot("t1", "T1 flat", "playground/T1JoystickFlatTerrain"),
        _robot("g1", "G1 flat", "playground/G1JoystickFlatTerrain"),
        _robot("t1-rough", "T1 rough", "playground/T1JoystickRoughTerrain"),
        _robot("g1-rough", "G1 rough", "playground/G1JoystickRoughTerrain"),
        _brax("ant", "Ant", "brax/ant"),
        _brax("humanoid", "Humanoid", "brax/humanoid"),
        _brax("halfcheetah", "HalfCheetah", "brax/halfcheetah"),
        _brax("cheetah-run", "CheetahRun", "playground/CheetahRun", "Playground's recipe"),
    )
}

__all__ = ["FINALS_AT_50M", "TASKS", "Reference", "Task", "fasttd3_curve"]
