"""Tables and figures of a task's learning curves (:mod:`benchmarks.curves`), as
docs/benchmarks.md shows them and the suite writes them.

Per task, :func:`task_table` gives one row per program and settings: the GPUs and seeds, the
first evaluation after launch (the program's start-up: imports, environment, compiles), td3-jax's
loop env steps/s and every program's steady env steps/s, the return at the task's env steps (or
seconds from launch) as IQM [min, max] over seeds, and the seconds from launch to each
reference return; the published results follow. :func:`settings_table` gives every td3-jax
setting measured on the task; :func:`plot` draws return against wall-clock and env steps.

    python -m benchmarks.report --data docs/benchmarks --out docs/benchmarks [--tasks t1 g1]
"""

from __future__ import annotations

import argparse
import statistics
import textwrap
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from benchmarks import tasks as tasks_module
from benchmarks.curves import TD3_JAX, Point, read
from benchmarks.tasks import FINALS_AT_50M, Reference, Task, fasttd3_curve
from td3_jax.core.stats import iqm

#: a legend label's longest line, in characters (three columns fit the figure's width)
LEGEND_WIDTH = 48
#: a space that a legend label is not wrapped at
NO_BREAK = "\u00a0"

Runs = dict[tuple[str, str], dict[int, list[Point]]]


def by_run(points: Iterable[Point]) -> Runs:
    """``{(program, run): {seed: its points in order}}``."""
    found: Runs = defaultdict(lambda: defaultdict(list))
    for p in sorted(points, key=lambda p: (p.seed, p.env_steps, p.wall_s)):
        found[p.key][p.seed].append(p)
    return {key: dict(seeds) for key, seeds in found.items()}


def at_point(curve: Sequence[Point], point: int, by_time: bool) -> Point | None:
    """The evaluation a table shows at ``point``: the last at or before ``point`` seconds from
    launch (``by_time``), else the last at or before ``point`` env steps of a run that got
    that far (``None`` for one that stopped short, or before any evaluation)."""
    if not by_time and (not curve or curve[-1].env_steps < point):
        return None
    position = (lambda p: p.wall_s) if by_time else (lambda p: p.env_steps)
    before = [p for p in curve if position(p) <= point]
    return before[-1] if before else None


def time_to(curve: Sequence[Point], target: float) -> float | None:
    """Seconds from launch of the first evaluation at or above ``target`` (None: never)."""
    return next((p.wall_s for p in curve if p.value >= target), None)


def steady_rate(curve: Sequence[Point]) -> float | None:
    """Env steps/s between the second and the last evaluation (start-up and first compiles
    left out; evaluations included); None with fewer than three evaluations."""
    if len(curve) < 3 or curve[-1].wall_s <= curve[1].wall_s:
        return None
    return (curve[-1].env_steps - curve[1].env_steps) / (curve[-1].wall_s - curve[1].wall_s)


def loop_rate(curve: Sequence[Point]) -> float | None:
    """The median of td3-jax's loop rate over the evaluations after the first (whose chunk
    holds the warm-up); None where the curve has none."""
    rates = [p.loop_rate for p in curve[1:] if p.loop_rate is not None]
    return statistics.median(rates) if rates else None


def number(value: float, scale: float) -> str:
    """A return rounded as the task's returns need: no decimals from 100 up (``scale``: the
    largest return of the table), else one."""
    return f"{value:.0f}" if scale >= 100 else f"{value:.1f}"


def spread(values: Sequence[float], scale: float) -> str:
    """``IQM [min, max]`` over seeds; the value alone for one seed; ``-`` for none."""
    if not values:
        return "-"
    if len(values) == 1:
        return number(values[0], scale)
    low, high = number(min(values), scale), number(max(values), scale)
    return f"{number(iqm(values), scale)} [{low}, {high}]"


def seconds(values: Sequence[float | None]) -> str:
    """Seconds over seeds (``239-261 s``, or ``not reached``), with ``(k of n seeds)`` where
    only some seeds got there."""
    got = sorted(v for v in values if v is not None)
    if not got:
        return "not reached" if values else "-"
    text = f"{got[0]:.0f} s" if len(got) == 1 else f"{got[0]:.0f}-{got[-1]:.0f} s"
    return text if len(got) == len(values) else f"{text} ({len(got)} of {len(values)} seeds)"


def rate(value: float | None) -> str:
    """Env steps/s as ``73.5K`` or ``1.52M`` (below a thousand as is; ``-`` for None)."""
    if value is None:
        return "-"
    if value < 1e3:
        return f"{value:.0f}"
    return f"{value / 1e6:.2f}M" if value >= 1e6 else f"{value / 1e3:.1f}K"


def gpus(seeds: dict[int, list[Point]]) -> str:
    """The GPUs a run's seeds ran on: ``H200``, or ``H100 x2, H200``."""
    counts = Counter(curve[0].gpu for curve in seeds.values())
    return ", ".join(f"{gpu} x{n}" if n > 1 and len(counts) > 1 else gpu
                     for gpu, n in sorted(counts.items()))  # fmt: skip


def reference_value(ref: Reference, runs: Runs) -> float | None:
    """A reference's return: its value, or the last return of its program's run (the median
    over that run's seeds), None where the data has no such run."""
    if ref.value is not None:
        return ref.value
    keys = [key for key in runs if key[0] == ref.program]
    key = (ref.program, ref.run) if (ref.program, ref.run) in runs else None
    key = key or (keys[0] if len(keys) == 1 else None)
    if key is None:
        return None
    return statistics.median(curve[-1].value for curve in runs[key].values())


def point_label(task: Task, point: int) -> str:
    """A column's position: ``12.3M`` (or ``2,000``) env steps, or ``60 s`` from launch."""
    if task.by_time:
        return f"{point} s"
    return f"{point / 1e6:.1f}M" if point >= 1e6 else f"{point:,}"


def _scale(runs: Runs) -> float:
    return max((abs(p.value) for seeds in runs.values() for c in seeds.values() for p in c),
               default=0.0)  # fmt: skip


def measured_row(task: Task, key: tuple[str, str], seeds: dict[int, list[Point]],
                 targets: Sequence[float | None], scale: float) -> list[str]:  # fmt: skip
    """A table row of one program and settings (see the module docstring)."""
    curves = list(seeds.values())
    loops = [r for r in map(loop_rate, curves) if r is not None]
    steadies = [r for r in map(steady_rate, curves) if r is not None]
    settings = f"`{key[1]}`" if key[0] == TD3_JAX else key[1]
    cells = [key[0], settings, gpus(seeds), ", ".join(map(str, seeds)),
             seconds([c[0].wall_s for c in curves]),
             rate(statistics.median(loops)) if loops else "-",
             rate(statistics.median(steadies)) if steadies else "-"]  # fmt: skip
    for point in task.points:
        found = [at_point(c, point, task.by_time) for c in curves]
        cells.append(spread([p.value for p in found if p is not None], scale))
    cells += [seconds([time_to(c, t) for c in curves]) if t is not None else "-" for t in targets]
    return cells


def published_rows(task: Task, targets: Sequence[float | None]) -> list[list[str]]:
    """The published results of a Playground humanoid: FastTD3's curve (A100) with its times
    to the references, and FlashSAC's table of finals at 50M (FlashSAC, FastTD3, PPO)."""
    finals = FINALS_AT_50M.get(task.task_id)
    if not finals:
        return []
    empty = ["-"] * (len(task.points) - 1)
    curve = fasttd3_curve(task.task_id)
    rows = []
    for program, final in finals.items():
        timed = program == "FastTD3" and curve
        row = [f"{program} (published)", "at 50M env steps", "A100" if timed else "-", "5",
               "-", "-", "-", *empty, f"{final:.1f}"]  # fmt: skip
        if timed:
            steady = (curve[-1][1] - curve[0][1]) / (curve[-1][0] - curve[0][0])
            row[6] = rate(steady)
            times = [next((t for t, _, v in curve if v >= target), None) for target in targets]
            row += [seconds([t]) if target is not None else "-"
                    for t, target in zip(times, targets, strict=True)]  # fmt: skip
        else:
            row += ["-"] * len(targets)
        rows.append(row)
    return rows


def _ordered(task: Task, runs: Runs) -> list[tuple[str, str]]:
    """The table's rows: td3-jax's preset, its other runs shown (every td3-jax run where none
    is the preset's or shown), then the baselines."""
    mine = sorted(k for k in runs if k[0] == TD3_JAX and task.in_main_table(k[1]))
    mine = mine or sorted(k for k in runs if k[0] == TD3_JAX)
    mine.sort(key=lambda k: k[1] != task.preset)
    return mine + sorted(k for k in runs if k[0] != TD3_JAX)


def _markdown(header: Sequence[str], rows: Sequence[Sequence[str]], left: int) -> str:
    """A Markdown table whose first ``left`` columns are text (the others right-aligned)."""
    align = ["---"] * left + ["---:"] * (len(header) - left)
    lines = [header, align, *rows]
    return "\n".join("| " + " | ".join(line) + " |" for line in lines)


def task_table(task: Task, points: Iterable[Point]) -> str:
    """The task's table (see the module docstring) as Markdown."""
    runs = by_run(points)
    targets = [reference_value(ref, runs) for ref in task.references]
    scale = _scale(runs)
    header = ["program", "settings", "GPU", "seeds", "first evaluation",
              "loop env steps/s", "steady env steps/s",
              *(f"return at {point_label(task, p)}" for p in task.points),
              *(f"to {ref.label}" + (f" ({number(t, scale)})" if ref.value is None and t else "")
                for ref, t in zip(task.references, targets, strict=True))]  # fmt: skip
    rows = [measured_row(task, key, runs[key], targets, scale) for key in _ordered(task, runs)]
    return _markdown(header, rows + published_rows(task, targets), left=4)


def settings_table(task: Task, points: Iterable[Point]) -> str:
    """Every td3-jax setting measured on the task (the preset first): its seeds and returns at
    the task's settings points (IQM [min, max])."""
    runs = {k: v for k, v in by_run(points).items() if k[0] == TD3_JAX}
    at = task.settings_points or task.points
    scale = _scale(runs)
    keys = sorted(runs, key=lambda k: (k[1] != task.preset, k[1]))
    header = ["settings", "GPU", "seeds", *(f"return at {point_label(task, p)}" for p in at)]
    rows = []
    for key in keys:
        curves = list(runs[key].values())
        values = [[p.value for p in (at_point(c, x, task.by_time) for c in curves) if p]
                  for x in at]  # fmt: skip
        rows.append([f"`{key[1]}`", gpus(runs[key]), ", ".join(map(str, runs[key])),
                     *(spread(v, scale) for v in values)])  # fmt: skip
    return _markdown(header, rows, left=3)


def _legend_lines(labels: Sequence[str], columns: int) -> int:
    """The text lines of the tallest column of a legend of ``columns`` columns: matplotlib
    splits the labels in order as ``numpy.array_split`` does (the first ``len % columns``
    columns one longer) and stacks each column on its own."""
    import numpy as np  # lazy, as matplotlib

    heights = [label.count("\n") + 1 for label in labels]
    return max(int(column.sum()) for column in np.array_split(heights, columns))


def _legend_below(fig: Any, handles: list, labels: list[str]) -> None:
    """The legend under the plots, its labels wrapped at :data:`LEGEND_WIDTH` (whole words
    and flags), in up to three columns; the figure grows to hold it."""
    labels = [textwrap.fill(label, LEGEND_WIDTH, break_on_hyphens=False,
                            break_long_words=False) for label in labels]  # fmt: skip
    columns = max(1, min(3, len(labels)))
    fig.legend(handles, labels, loc="lower center", ncol=columns, fontsize=8)
    legend_in = 0.15 * _legend_lines(labels, columns) + 0.3
    fig.set_figheight(4.2 + legend_in)
    fig.tight_layout(rect=(0, legend_in / (4.2 + legend_in), 1, 1))


def plot(task: Task, points: Iterable[Point], path: Path) -> None:
    """Return against minutes from launch and against env steps: each seed of the runs of
    :func:`task_table`, FastTD3's published curve (A100) and FlashSAC's final at 50M."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = by_run(points)
    fig, (by_wall, by_steps) = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    colors = iter(plt.rcParams["axes.prop_cycle"].by_key()["color"] * 3)
    for key in _ordered(task, runs):
        gpu = gpus(runs[key]).replace(" ", NO_BREAK)  # ("H200 x2" kept on one line)
        color, label = next(colors), f"{key[0]} ({key[1]}), {gpu}"
        for i, curve in enumerate(runs[key].values()):
            shown = dict(color=color, linewidth=1.2, alpha=0.85, label=None if i else label)
            by_wall.plot([p.wall_s / 60 for p in curve], [p.value for p in curve], **shown)
            by_steps.plot([p.env_steps / 1e6 for p in curve], [p.value for p in curve], **shown)
    published = fasttd3_curve(task.task_id) if task.robot else []
    if published:
        style = dict(color="black", linestyle=":", marker="x", markersize=4,
                     label="FastTD3 (published, A100)")  # fmt: skip
        by_wall.plot([t / 60 for t, _, _ in published], [v for *_, v in published], **style)
        by_steps.plot([s / 1e6 for _, s, _ in published], [v for *_, v in published], **style)
        flash = FINALS_AT_50M[task.task_id]["FlashSAC"]
        by_steps.plot([50], [flash], "k*", markersize=9, label="FlashSAC at 50M (published)")
    by_wall.set_xlabel("minutes from launch (start-up and compiles included)")
    by_steps.set_xlabel("env steps (millions)")
    by_wall.set_ylabel("evaluation return")
    for ax in (by_wall, by_steps):
        ax.grid(alpha=0.3)
    fig.suptitle(f"{task.title} ({task.env})")
    _legend_below(fig, *by_steps.get_legend_handles_labels())
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


def task_markdown(task: Task, points: Sequence[Point], figure: str | None = None) -> str:
    """A task's section: its table, its figure (``figure``: the PNG's path as the page links
    it) and its table of settings."""
    parts = [f"## {task.title}", "", task_table(task, points), ""]
    if figure:
        parts += [f"![{task.title}: return against wall-clock and env steps]({figure})", ""]
    parts += ["Settings measured on this task:", "", settings_table(task, points), ""]
    return "\n".join(parts)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.report",
                                     description=__doc__.split("\n\n")[0])  # fmt: skip
    parser.add_argument("--data", type=Path, required=True,
                        help="the folder of the tasks' curves (TASK.csv)")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="where TASK.png go")
    parser.add_argument("--tasks", nargs="+", choices=list(tasks_module.TASKS),
                        help="default: every task with a CSV in --data")  # fmt: skip
    parser.add_argument("--markdown", type=Path,
                        help="write the tables to this file (default: print them)")
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    names = args.tasks or [n for n in tasks_module.TASKS if (args.data / f"{n}.csv").is_file()]
    missing = [n for n in names if not (args.data / f"{n}.csv").is_file()]
    if not names or missing:
        parser.error(f"no curves in {args.data} for {', '.join(missing) or 'any task'} "
                     "(TASK.csv, as benchmarks.suite writes them)")  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    sections = []
    for name in names:
        task, points = tasks_module.TASKS[name], read(args.data / f"{name}.csv")
        plot(task, points, args.out / f"{name}.png")
        sections.append(task_markdown(task, points, f"{name}.png"))
    if args.markdown:
        args.markdown.write_text("\n".join(sections))
    else:
        print("\n".join(sections))


if __name__ == "__main__":
    main()
