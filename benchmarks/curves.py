"""Learning curves as one CSV per task: every evaluation of every run a table or figure cites.

A row is one evaluation of one run: which program made it (``td3-jax``, ``Brax PPO``, ...),
the run's settings (``run``: the preset's name, or what differs from it), the seed and GPU,
the seconds from the program's launch (start-up and compiles included), the env steps trained
when the return was known, the mean and standard deviation of the evaluation episodes'
returns, and, for td3-jax, its loop's env steps/s (``metrics.jsonl``'s ``env_steps_per_s``:
the chunk's training without the evaluation).

    program,run,seed,gpu,wall_s,env_steps,return,return_std,loop_env_steps_per_s
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import NamedTuple

FIELDS = ("program", "run", "seed", "gpu", "wall_s", "env_steps", "return", "return_std",
          "loop_env_steps_per_s")  # fmt: skip

TD3_JAX = "td3-jax"


class Point(NamedTuple):
    """One evaluation of one run (a CSV row)."""

    program: str
    run: str
    seed: int
    gpu: str
    wall_s: float
    env_steps: int
    value: float
    std: float | None = None
    loop_rate: float | None = None

    @property
    def key(self) -> tuple[str, str]:
        """``(program, run)``: the row of a table this point belongs to."""
        return self.program, self.run


def _cell(value: float | None, digits: int) -> str:
    return "" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def _number(text: str) -> float | None:
    return float(text) if text.strip() else None


def write(path: Path, points: Iterable[Point]) -> None:
    """Writes ``points`` to ``path`` as CSV, sorted by program, run, seed and env steps."""
    rows = sorted(points, key=lambda p: (p.program, p.run, p.seed, p.env_steps, p.wall_s))
    with Path(path).open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(FIELDS)
        for p in rows:
            writer.writerow([p.program, p.run, p.seed, p.gpu, _cell(p.wall_s, 1),
                             p.env_steps, _cell(p.value, 3), _cell(p.std, 3),
                             _cell(p.loop_rate, 0)])  # fmt: skip


def read(path: Path) -> list[Point]:
    """The points of a curves CSV (:func:`write`'s format); a missing column is a ValueError
    naming it."""
    with Path(path).open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [name for name in FIELDS if name not in (reader.fieldnames or ())]
        if missing:
            raise ValueError(f"{path}: not a curves CSV (no column {', '.join(missing)})")
        return [Point(row["program"], row["run"], int(row["seed"]), row["gpu"],
                      float(row["wall_s"]), int(row["env_steps"]), float(row["return"]),
                      _number(row["return_std"]), _number(row["loop_env_steps_per_s"]))
                for row in reader]  # fmt: skip


def records(metrics: Path) -> list[dict]:
    """The evaluation records of a run's ``metrics.jsonl`` (lines without a return left out)."""
    lines = Path(metrics).read_text().splitlines()
    found = [json.loads(line) for line in lines if line.strip()]
    return [r for r in found if r.get("eval_return_mean") is not None]


def from_records(found: list[dict], *, run: str, gpu: str, launch_offset_s: float,
                 program: str = TD3_JAX) -> list[Point]:  # fmt: skip
    """td3-jax's evaluation records as points: ``wall_s`` is the run's own clock
    (``wall_time_s``, which starts after the process's imports) plus ``launch_offset_s``, the
    seconds from the launch to that clock's start."""
    return [Point(program, run, int(r["seed"]), gpu, float(r["wall_time_s"]) + launch_offset_s,
                  int(r["env_steps"]), float(r["eval_return_mean"]), r.get("eval_return_std"),
                  r.get("env_steps_per_s"))
            for r in found]  # fmt: skip


def launch_offset(first_seen_s: float, first_record: dict) -> float:
    """Seconds from a process's launch to the start of its run's clock: ``first_seen_s`` (when,
    counted from the launch, its first record was seen) less that record's ``wall_time_s``."""
    return first_seen_s - float(first_record["wall_time_s"])


__all__ = ["FIELDS", "TD3_JAX", "Point", "from_records", "launch_offset", "read", "records",
           "write"]  # fmt: skip
