"""The host side of the benchmark suite (benchmarks.suite): what a rerun does with each run's
folder, the jobs and commands it plans, its argument errors, GPUs, a child's launch offset, and
the report it writes from hand-made run folders. No training runs here: where the suite starts
a process, a short Python script stands in for td3-jax."""

from __future__ import annotations

import dataclasses
import json
import sys
import textwrap
from pathlib import Path

import pytest

from benchmarks import curves, suite
from benchmarks.suite import DONE, RESTART, RESUME, START, RunState
from benchmarks.tasks import TASKS
from td3_jax.config.presets import preset


@pytest.mark.parametrize(("state", "action"), [
    (RunState(exists=False), START),
    (RunState(exists=True), START),  # an empty folder (or only a lock)
    (RunState(True, None, 13, outputs=True), RESTART),  # lost before its first checkpoint
    (RunState(True, 4, 13, outputs=True), RESUME),
    (RunState(True, 4, None, outputs=True), RESUME),  # (config.json unreadable: resume says)
    (RunState(True, 13, 13, outputs=True), DONE),
])  # fmt: skip
def test_a_rerun_resumes_restarts_or_leaves_each_run(state, action):
    assert suite.decide(state) == action


def _config(folder: Path, name: str = "t1", **changes) -> dict:
    config = {**json.loads(json.dumps(dataclasses.asdict(preset(name)))), "preset": name,
              **changes}  # fmt: skip
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.json").write_text(json.dumps(config))
    return config


def test_the_state_of_a_run_folder_is_read_as_the_runner_reads_it(tmp_path):
    run = tmp_path / "s0"
    assert suite.run_state(run) == RunState(exists=False)
    run.mkdir()
    assert suite.run_state(run) == RunState(exists=True)
    _config(run, total_steps=53_248_000)  # 13 chunks of 4,096,000
    assert suite.run_state(run) == RunState(True, None, 13, outputs=True)
    for chunk in ("4", "9", "tmp-10"):  # (a checkpoint being written is not one)
        (run / "checkpoints" / chunk).mkdir(parents=True)
    assert suite.run_state(run) == RunState(True, 9, 13, outputs=True)


def test_a_run_set_aside_keeps_every_earlier_one(tmp_path):
    for expected in ("s0.lost-1", "s0.lost-2"):
        (tmp_path / "s0").mkdir()
        assert suite.set_aside(tmp_path / "s0") == tmp_path / expected
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s0.lost-1", "s0.lost-2"]


def test_a_baseline_is_done_only_where_its_result_says_it_finished(tmp_path):
    (job,) = [j for j in suite.plan(["ant"], 1, ["sac"], tmp_path) if j.algo == "sac"]
    assert suite.baseline_state(job) == START
    parts = job.out / "compare_ant_parts"
    parts.mkdir(parents=True)
    (parts / "sac.json").write_text(json.dumps({"status": "failed", "rows": []}))
    assert suite.baseline_state(job) == RESTART
    (parts / "sac.json").write_text(json.dumps({"status": "ok", "rows": []}))
    assert suite.baseline_state(job) == DONE


def test_the_plan_runs_every_seed_of_td3_jax_then_of_each_baseline(tmp_path):
    jobs = suite.plan(["t1", "ant"], 2, ["ppo"], tmp_path)
    assert [(j.name, j.program) for j in jobs] == [
        ("t1-s0", "td3-jax"), ("t1-s1", "td3-jax"),
        ("t1-ppo-s0", "Playground PPO"), ("t1-ppo-s1", "Playground PPO"),
        ("ant-s0", "td3-jax"), ("ant-s1", "td3-jax"),
        ("ant-ppo-s0", "Brax PPO"), ("ant-ppo-s1", "Brax PPO"),
    ]  # fmt: skip
    assert jobs[1].out == tmp_path / "runs" / "t1" / "s1"
    assert jobs[2].out == tmp_path / "baselines" / "t1-ppo-s0"


def test_the_commands_of_a_fresh_run_a_resume_and_a_baseline(tmp_path):
    t1, _, ppo = suite.plan(["t1"], 2, ["ppo"], tmp_path)[1:4]
    settings = suite.Settings(budget_s=600.0, td3_flags=("--pushes", "on"))
    fresh = suite.td3_command(t1, START, settings)
    assert fresh[1:] == ["-m", "td3_jax", "train", "--out", str(t1.out), "--preset", "t1",
                         "--seed", "1", "--pushes", "on", "--total-steps", "53248000",
                         "--time-budget-s", "600"]  # fmt: skip
    resumed = suite.td3_command(t1, RESUME, suite.Settings())
    assert resumed[1:] == ["-m", "td3_jax", "train", "--out", str(t1.out), "--resume",
                           "--total-steps", "53248000"]  # fmt: skip
    baseline = suite.baseline_command(ppo, suite.Settings())
    assert baseline[1:] == ["-m", "benchmarks.compare", "--env",
                            "playground/T1JoystickFlatTerrain", "--algos", "ppo", "--out",
                            str(ppo.out), "--seed", "1", "--num-evals", "0", "--impl", "warp"]


@pytest.mark.parametrize(("args", "message"), [
    (["--seeds", "0"], "--seeds 0: at least one seed"),
    (["--gpus", "0"], "--gpus 0: must be positive"),
    (["--budget-s", "-5"], "--budget-s -5.0: must be positive"),
    (["--td3-flags", "--seed 3"], "--td3-flags may not set --seed"),
    (["--baselines", "sac"], "no baseline sac on t1: the Playground robots have Playground's "
                             "PPO recipe (ppo)"),
    (["--tasks", "t2"], "argument --tasks: invalid choice: 't2'"),
])  # fmt: skip
def test_bad_arguments_are_one_line_and_exit_2(tmp_path, capsys, args, message):
    argv = ["--tasks", "t1", "--out", str(tmp_path / "out"), *args]
    with pytest.raises(SystemExit) as stopped:
        suite.main(argv)
    assert stopped.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith("python -m benchmarks.suite: error: ") and message in error


def test_an_out_that_is_a_file_is_refused(tmp_path, capsys):
    (tmp_path / "f").write_text("")
    with pytest.raises(SystemExit):
        suite.main(["--tasks", "t1", "--out", str(tmp_path / "f")])
    assert "is a file, not a folder" in capsys.readouterr().err


@pytest.mark.parametrize(("visible", "listed", "expected"), [
    (None, [], [("", "CPU")]),
    (None, ["NVIDIA H200", "NVIDIA H100 80GB HBM3"], [("0", "H200"), ("1", "H100")]),
    ("1", ["NVIDIA H200", "NVIDIA H100 80GB HBM3"], [("1", "H100")]),
    ("GPU-5f3a, 0", ["NVIDIA H200"], [("GPU-5f3a", "GPU"), ("0", "H200")]),
])  # fmt: skip
def test_each_run_gets_a_gpu_of_its_own(visible, listed, expected):
    assert suite.visible_gpus(visible, listed) == expected


_FAKE_RUN = textwrap.dedent("""
    import json, sys, time
    from pathlib import Path
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    print("compiling", flush=True)
    time.sleep(0.3)
    record = {"seed": 0, "env_steps": 100, "wall_time_s": 0.25, "eval_return_mean": 1.0}
    (out / "metrics.jsonl").write_text(json.dumps(record) + "\\n")
    print("first record", flush=True)
    time.sleep(1.2)
""")


def test_a_child_is_timed_from_its_launch_and_its_clock_offset_found(tmp_path):
    log = tmp_path / "logs" / "x.log"
    command = [sys.executable, "-c", _FAKE_RUN, str(tmp_path / "run")]
    code, offset = suite.run_process(command, log, "", tmp_path / "run" / "metrics.jsonl")
    assert code == 0
    # the record was seen between its writing (0.3 s after the launch, and Python's start)
    # and the next look half a second later: wall_time_s 0.25 puts the clock's start 0.05 s
    # or more after the launch
    assert 0.05 <= offset < 0.25 + 5.0
    lines = log.read_text().splitlines()
    assert lines[0].startswith("# ") and lines[0].endswith(str(tmp_path / "run"))  # one line
    stamps = [float(line.split()[0]) for line in lines[1:]]
    assert [line.split(maxsplit=1)[1] for line in lines[1:]] == ["compiling", "first record"]
    # (read times, to 0.1 s: "first record" cannot be read before the child's 0.3 s sleep,
    # while "compiling" may be read late on a busy machine, so their gap is not bounded below)
    assert stamps == sorted(stamps) and stamps[1] >= 0.25


def _metrics(folder: Path, rows: list[tuple[int, float, float]]) -> None:
    lines = [json.dumps({"seed": 0, "env_steps": s, "wall_time_s": w, "eval_return_mean": v,
                         "eval_return_std": 1.0, "env_steps_per_s": 50_000.0})
             for s, w, v in rows]  # fmt: skip
    (folder / "metrics.jsonl").write_text("\n".join(lines) + "\n")


def test_the_report_is_written_from_the_run_folders(tmp_path):
    out = tmp_path / "out"
    jobs = suite.plan(["t1"], 1, ["ppo"], out)
    run, baseline = jobs
    _config(run.out, total_steps=53_248_000, pushes="on")
    _metrics(run.out, [(4_096_000, 80.0, 0.5), (8_192_000, 120.0, 20.0)])
    (out / "logs").mkdir()
    (out / "logs" / "t1-s0.json").write_text(json.dumps({"gpu": "H200",
                                                         "launch_offset_s": 20.0}))
    parts = baseline.out / "compare_T1JoystickFlatTerrain_parts"
    parts.mkdir(parents=True)
    rows = [{"wall_s": 150.0, "env_steps": 0, "eval_return": 0.1, "eval_return_std": 0.0}]
    (parts / "ppo.json").write_text(json.dumps({"status": "ok", "rows": rows}))
    assert suite.write_report(jobs, out, suite.Settings()) == ["t1"]
    points = curves.read(out / "t1.csv")
    assert points == [
        curves.Point("Playground PPO", "Playground's recipe, MuJoCo Warp", 0, "GPU", 150.0, 0,
                     0.1, 0.0, None),
        curves.Point("td3-jax", "t1 --pushes on", 0, "H200", 100.0, 4_096_000, 0.5, 1.0, 50_000),
        curves.Point("td3-jax", "t1 --pushes on", 0, "H200", 140.0, 8_192_000, 20.0, 1.0,
                     50_000),
    ]  # fmt: skip
    text = (out / "report.md").read_text()
    assert text.startswith("## T1 flat") and "![T1 flat" in text and (out / "t1.png").is_file()


def test_the_suite_runs_each_job_once_and_a_rerun_leaves_finished_runs(tmp_path, monkeypatch,
                                                                      capsys):  # fmt: skip
    """Two seeds through run_all with a stand-in for td3-jax that writes a finished run; the
    second command finds both finished and only writes the report."""
    started = []
    script = textwrap.dedent("""
        import json, sys
        from pathlib import Path
        out, config, seed = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
        (out / "checkpoints" / "13").mkdir(parents=True)
        (out / "config.json").write_text(config)
        record = {"seed": seed, "env_steps": 53248000, "wall_time_s": 9.0,
                  "eval_return_mean": 40.0}
        (out / "metrics.jsonl").write_text(json.dumps(record) + "\\n")
    """)
    config = json.dumps({**json.loads(json.dumps(dataclasses.asdict(preset("t1")))),
                         "preset": "t1", "total_steps": 53_248_000})  # fmt: skip

    def fake(job, action, settings):
        started.append((job.name, action))
        return [sys.executable, "-c", script, str(job.out), config, str(job.seed)]

    monkeypatch.setattr(suite, "td3_command", fake)
    monkeypatch.setattr(suite, "_listed_gpus", lambda: ["NVIDIA H200", "NVIDIA H200"])
    argv = ["--tasks", "t1", "--seeds", "2", "--out", str(tmp_path)]
    assert suite.main(argv) == 0
    assert sorted(started) == [("t1-s0", START), ("t1-s1", START)]
    assert suite.main(argv) == 0
    assert len(started) == 2
    assert capsys.readouterr().out.count("finished before") == 2
    assert {p.seed for p in curves.read(tmp_path / "t1.csv")} == {0, 1}
    assert TASKS["t1"].preset == "t1"
