"""The benchmark tables (benchmarks.report) and their curves' CSV (benchmarks.curves), on
hand-made evaluations whose IQMs, rates and times are worked out by hand."""

from __future__ import annotations

import json

import pytest

from benchmarks import curves, report
from benchmarks.curves import Point
from benchmarks.tasks import TASKS, Reference, Task, fasttd3_curve

TOY = Task("toy", "Toy", "brax/toy", preset="toy", total_steps=None, points=(100, 200),
           references=(Reference("five", 5.0), Reference("PPO's final", program="Brax PPO")),
           shown=("toy --pushes",))  # fmt: skip


def _curve(run: str, seed: int, rows: list[tuple[float, int, float]], program: str = "td3-jax",
           gpu: str = "H200", loop: float | None = 1000.0) -> list[Point]:  # fmt: skip
    """Points of one seed from ``(wall_s, env_steps, return)`` rows."""
    return [Point(program, run, seed, gpu, w, s, v, 0.5, loop) for w, s, v in rows]


#: td3-jax's preset on three seeds: returns 1, 2 and 10 at 100 env steps (IQM 3.1667: a
#: third of the distribution each, [0.25, 0.75] keeps 1/12 of 1, 1/3 of 2, 1/12 of 10, so
#: (1/12 + 2/3 + 10/12) / (1/2) = 3.1667); seed 2 stops at 100 steps.
PRESET = [
    *_curve("toy", 0, [(10.0, 50, 0.0), (20.0, 100, 1.0), (30.0, 200, 6.0)]),
    *_curve("toy", 1, [(12.0, 50, 0.0), (22.0, 100, 2.0), (32.0, 200, 4.0)], gpu="H100"),
    *_curve("toy", 2, [(14.0, 50, 0.0), (24.0, 100, 10.0)]),
]
#: A PPO-like baseline: first evaluation at 40 s, its final return 3.0 at 60 s.
PPO = _curve("Brax's recipe", 1, [(40.0, 0, -1.0), (50.0, 100, 2.0), (60.0, 300, 3.0)],
             program="Brax PPO", loop=None)  # fmt: skip
VARIANT = _curve("toy --n-step 1", 0, [(10.0, 50, 0.0), (20.0, 100, 0.5), (30.0, 200, 2.5)])
PUSHES = _curve("toy --pushes on", 0, [(11.0, 50, 0.0), (21.0, 100, 0.7), (31.0, 200, 1.5)])


def _row(table: str, start: str) -> list[str]:
    line = next(line for line in table.splitlines() if line.startswith(f"| {start}"))
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_the_task_table_gives_iqm_and_spread_times_and_rates_per_program():
    table = report.task_table(TOY, PRESET + PPO + VARIANT + PUSHES)
    header = _row(table, "program")
    assert header[-2:] == ["to five", "to PPO's final (3.0)"]
    row = dict(zip(header, _row(table, "td3-jax | `toy`"), strict=True))
    assert row["GPU"] == "H100, H200 x2" and row["seeds"] == "0, 1, 2"
    assert row["first evaluation"] == "10-14 s"
    assert row["loop env steps/s"] == "1.0K"
    # steady: seeds 0 and 1 go from 100 to 200 steps in 10 s (10/s); seed 2 has 2 evaluations
    assert row["steady env steps/s"] == "10"
    assert row["return at 100"] == "3.2 [1.0, 10.0]"
    assert row["return at 200"] == "5.0 [4.0, 6.0]"  # seed 2 stopped short: not counted
    assert row["to five"] == "24-30 s (2 of 3 seeds)"  # seed 1 never gets there
    assert row["to PPO's final (3.0)"] == "24-32 s"
    ppo = dict(zip(header, _row(table, "Brax PPO"), strict=True))
    assert ppo["first evaluation"] == "40 s" and ppo["loop env steps/s"] == "-"
    assert ppo["steady env steps/s"] == "20"  # (300 - 100) / (60 - 50)
    assert ppo["return at 100"] == "2.0" and ppo["return at 200"] == "2.0"
    assert ppo["to five"] == "not reached"
    # the rows: the preset, the shown run, the baseline; the variant only in the settings
    programs = [line.split("|")[1:3] for line in table.splitlines()[2:]]
    assert [" ".join(c.strip() for c in p) for p in programs] == [
        "td3-jax `toy`", "td3-jax `toy --pushes on`", "Brax PPO Brax's recipe"]


def test_the_settings_table_lists_every_td3_jax_setting_the_preset_first():
    table = report.settings_table(TOY, PRESET + PPO + VARIANT + PUSHES)
    rows = [line.split("|")[1].strip() for line in table.splitlines()[2:]]
    assert rows == ["`toy`", "`toy --n-step 1`", "`toy --pushes on`"]
    assert _row(table, "`toy --n-step 1`")[3:] == ["0.5", "2.5"]


@pytest.mark.parametrize(("point", "by_time", "expected"), [
    (100, False, 2.0), (150, False, 2.0), (300, False, 3.0), (301, False, None),
    (55, True, 2.0), (39, True, None), (1000, True, 3.0),
])  # fmt: skip
def test_a_table_shows_the_last_evaluation_at_or_before_its_point(point, by_time, expected):
    found = report.at_point(PPO, point, by_time)
    assert (found and found.value) == expected


def test_spread_rounds_as_the_returns_need():
    assert report.spread([], 1.0) == "-"
    assert report.spread([41.83], 40.0) == "41.8"
    # IQM of three: (2900.2 / 12 + 3100.4 / 3 + 3500.6 / 12) / (1 / 2) = 3133.7
    assert report.spread([3100.4, 3500.6, 2900.2], 3500.0) == "3134 [2900, 3501]"
    assert report.seconds([]) == "-" and report.seconds([None]) == "not reached"
    assert report.rate(1_521_000) == "1.52M" and report.rate(73_450) == "73.5K"


def test_a_reference_is_a_value_or_the_final_return_of_a_named_run():
    runs = report.by_run(PRESET + PPO)
    assert report.reference_value(Reference("x", 7.0), runs) == 7.0
    assert report.reference_value(Reference("x", program="Brax PPO"), runs) == 3.0
    assert report.reference_value(Reference("x", program="Brax SAC"), runs) is None


def test_a_robot_table_adds_the_published_results():
    task = TASKS["t1"]
    fasttd3 = fasttd3_curve(task.task_id)
    assert fasttd3[0] == (pytest.approx(5.61 * 60), 5_120_000, 17.498)  # first row: no (0, 0)
    points = _curve("t1", 0, [(100.0, 4_096_000, 0.1), (400.0, 53_248_000, 40.0)])
    table = report.task_table(task, points)
    flash = _row(table, "FlashSAC (published)")
    assert flash[3] == "5" and flash[-3] == "38.5"
    fast = _row(table, "FastTD3 (published)")
    assert fast[-3] == "35.0"
    assert fast[-2] == "3028 s"  # FastTD3's final 34.8 on its own curve: 50.46 minutes
    assert fast[-1] == "not reached"  # (38.5)


@pytest.mark.parametrize(("run", "shown"), [
    ("t1", True), ("t1 --pushes on", True), ("t1 --devices 2 --replay-shards 2", True),
    ("t1 --local-processes 2 --replay-shards 2", True),
    ("t1, 300-s budget, beside Playground PPO, new host", True),
    ("t1, 330-s budget, beside Playground PPO", True),
    ("t1 --num-envs 8192 --eval-every 8192000", False), ("t1-rough, 300-s budget", False),
    ("g1, 300-s budget", False),
])  # fmt: skip
def test_a_robot_table_shows_the_preset_its_variants_and_the_runs_timed_beside_ppo(run, shown):
    """T1's main table: the preset, pushes, two GPUs and every run named with a comma after
    the preset's name (those timed beside PPO); other settings only in the settings table."""
    assert TASKS["t1"].in_main_table(run) is shown


def test_curves_round_trip_through_csv(tmp_path):
    path = tmp_path / "toy.csv"
    points = [*PRESET, *PPO]
    curves.write(path, points)
    back = curves.read(path)
    assert sorted(back) == sorted(points)
    assert path.read_text().splitlines()[0] == ",".join(curves.FIELDS)
    (tmp_path / "bad.csv").write_text("program,run,seed\n")
    with pytest.raises(ValueError, match="no column gpu, wall_s"):
        curves.read(tmp_path / "bad.csv")


def test_records_become_points_timed_from_launch(tmp_path):
    metrics = tmp_path / "metrics.jsonl"
    rows = [{"seed": 3, "env_steps": 10, "wall_time_s": 5.0, "eval_return_mean": 1.5,
             "eval_return_std": 0.5, "env_steps_per_s": 99.0},
            {"seed": 3, "env_steps": 20, "wall_time_s": 9.0, "eval_return_mean": None}]  # fmt: skip
    metrics.write_text("\n".join(json.dumps(r) for r in rows) + "\n\n")
    found = curves.records(metrics)
    assert len(found) == 1  # (a record without a return is not an evaluation)
    offset = curves.launch_offset(17.5, found[0])  # first seen 17.5 s after launch
    assert offset == 12.5
    (point,) = curves.from_records(found, run="t1", gpu="H200", launch_offset_s=offset)
    assert point == Point("td3-jax", "t1", 3, "H200", 17.5, 10, 1.5, 0.5, 99.0)


def test_a_legend_is_as_tall_as_its_tallest_column():
    # matplotlib's columns, as numpy.array_split makes them: 5 labels in 3 columns are
    # (0, 1), (2, 3), (4); 4 labels are (0, 1), (2), (3)
    assert report._legend_lines(["a", "b\nb\nb", "c", "d\nd", "e"], 3) == 1 + 3
    assert report._legend_lines(["a\na", "b\nb", "c\nc\nc\nc\nc", "d"], 3) == 5
    assert report._legend_lines(["a", "b\nb\nb", "c", "d\nd", "e"], 1) == 1 + 3 + 1 + 2 + 1
    assert report._legend_lines(["a"], 1) == 1


def test_the_legend_stays_inside_the_figure_and_below_the_plots(tmp_path, monkeypatch):
    long = ("toy --devices 2 --replay-shards 2 --num-envs 8192 --updates-per-iter 16 "
            "--buffer-size 16777216 --no-eval-in-chunk")  # (hyphen breaks: "--buffer-")
    points = [*PRESET, *_curve(long, 0, [(10.0, 50, 0.0), (20.0, 100, 1.0)], gpu="H200 x2"),
              *PPO]  # fmt: skip
    task = Task("toy", "Toy", "brax/toy", preset="toy", total_steps=None, points=(100,),
                references=(), shown=(long,))  # fmt: skip
    from matplotlib.figure import Figure

    seen = {}
    real_savefig = Figure.savefig

    def savefig(fig, path, **kwargs):
        renderer = fig.canvas.get_renderer()
        fig.canvas.draw()
        seen["legend"] = fig.legends[0].get_window_extent(renderer)
        seen["figure"] = fig.bbox
        seen["plots"] = min(ax.get_tightbbox(renderer).y0 for ax in fig.axes)
        seen["labels"] = [t.get_text() for t in fig.legends[0].get_texts()]
        return real_savefig(fig, path, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    report.plot(task, points, tmp_path / "toy.png")
    legend, figure = seen["legend"], seen["figure"]
    assert (tmp_path / "toy.png").stat().st_size > 0
    assert figure.x0 <= legend.x0 and legend.x1 <= figure.x1
    assert figure.y0 <= legend.y0 and legend.y1 <= seen["plots"]
    wrapped = next(label for label in seen["labels"] if "--buffer-size" in label)
    assert wrapped.count("\n") >= 1
    assert not any(line.endswith("-") for line in wrapped.splitlines())  # flags kept whole
    assert wrapped.endswith(f"H200{report.NO_BREAK}x2")  # the GPUs on one line
