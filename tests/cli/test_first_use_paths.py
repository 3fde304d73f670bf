"""What a new user meets first: flag errors, help text, the console lines of a run, what
config.json records and where TensorBoard and W&B place evaluation returns."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import re
import signal
import sys
import types
import warnings
from pathlib import Path

import pytest
from rich.console import Console
from support import (
    TINY_FLAGS,
    assert_one_line_error,
    main,
    restored_logging,  # noqa: F401  (a fixture)
)
from test_cli import tensorboard_scalars

from td3_jax.common import runtime
from td3_jax.config.schema import TrainConfig
from td3_jax.runner.checkpoint import _all_corrupt, _unusable
from td3_jax.runner.logger import MetricsLogger
from td3_jax.runner.run import RunCompleteWarning, _Progress
from td3_jax.runner.rundir import config_changes, load_config, save_config
from td3_jax.runner.tracking import Tracker

# --------------------------------------------------------------------------------------------
# flags and help
# --------------------------------------------------------------------------------------------


def test_a_flag_of_numbers_given_text_is_one_clear_line(capsys):
    code, _, err = main(["train", "--actor-lr", "abc", "--out", "unused"], capsys)
    assert_one_line_error(code, err, "--actor-lr takes a number, got 'abc'")
    code, _, err = main(["train", "--num-envs=x"], capsys)
    assert_one_line_error(code, err, "--num-envs takes a whole number, got 'x'")
    code, _, err = main(["train", "--hidden-sizes", "64", "x", "--quiet"], capsys)
    assert_one_line_error(code, err, "--hidden-sizes takes whole numbers, got 'x' (of 64 x)")


def test_an_unknown_environment_is_the_only_output(capsys, tmp_path):
    code, out, err = main(["train", "--env", "playground/CheetahRunn", "--out",
                           str(tmp_path / "run")], capsys)  # fmt: skip
    assert out == ""  # (no "physics: ..." line before the error)
    assert_one_line_error(code, err, "unknown environment 'playground/CheetahRunn'",
                          "did you mean playground/CheetahRun?")  # fmt: skip
    assert not (tmp_path / "run").exists()


def test_an_out_below_a_file_is_refused_before_the_environment_is_made(
    capsys, tmp_path, monkeypatch
):
    from td3_jax.runner import run as run_module

    made = []
    monkeypatch.setattr(run_module.programs, "find", lambda *a, **k: made.append(a))
    (tmp_path / "notes.txt").write_text("mine\n")
    out = tmp_path / "notes.txt" / "run"
    code, stdout, err = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)
    assert_one_line_error(code, err, f"--out {out}: cannot create it (Not a directory)")
    assert stdout == ""  # (no "using the traced programs stored in ..." before it)
    assert made == []  # neither a stored program read nor the environment made and traced
    assert (tmp_path / "notes.txt").read_text() == "mine\n"


@pytest.mark.parametrize(("args", "flag"), [
    (["train", "--out", ""], "--out"), (["train", "--quiet", "--out="], "--out"),
    (["sweep", "--sweep-tau", "0.01", "--out", "x", "--run="], "--run"),
    (["render", "--run", "somewhere", "--out", ""], "--out"),
    (["eval", "--run", ""], "--run"), (["train", "--out", "  "], "--out"),
])  # fmt: skip
def test_an_empty_path_flag_is_refused_not_taken_as_the_working_directory(
    args, flag, capsys, tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    code, stdout, err = main(args, capsys)
    blank = "empty" if "  " not in args else "blank"
    assert_one_line_error(code, err, f"{flag} is {blank}", "give the path")
    assert stdout == "" and list(tmp_path.iterdir()) == []  # nothing written where it stands


def test_hidden_sizes_help_shows_the_default_a_run_gets(capsys):
    code, out, _ = main(["train", "--help"], capsys)
    assert code == 0
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if "--hidden-sizes" in line)
    end = next(i for i in range(start + 1, len(lines)) if "--" in lines[i])
    entry = " ".join(line.strip("│ ") for line in lines[start:end])
    assert "None" not in entry, entry
    assert "(default: 256 256)" in entry, entry


# --------------------------------------------------------------------------------------------
# config.json
# --------------------------------------------------------------------------------------------


def test_config_json_records_the_values_the_algorithm_chose(tmp_path):
    # TD3Config: actor and critic Adam 1e-3, tau 0.005, 400-300; DDPGConfig: actor 1e-4,
    # critic 1e-3, tau 0.01, 256-256 (each config's own defaults)
    left = dict(actor_lr=None, critic_lr=None, tau=None, hidden_sizes=None)
    for algo, expected in (("td3", [1e-3, 1e-3, 0.005, [400, 300]]),
                           ("ddpg", [1e-4, 1e-3, 0.01, [256, 256]])):  # fmt: skip
        cfg = TrainConfig(algo=algo, **left)
        save_config(cfg, [], tmp_path)
        saved = json.loads((tmp_path / "config.json").read_text())
        assert [saved[k] for k in left] == expected, algo
        assert config_changes(load_config(tmp_path), cfg) == {}  # the same run
    given = TrainConfig(actor_lr=3e-4, tau=0.02, hidden_sizes=(64, 64))
    save_config(given, [], tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    assert [saved[k] for k in left] == [3e-4, 1e-3, 0.02, [64, 64]]


def test_an_old_config_json_with_nulls_still_loads_and_resumes_unchanged(tmp_path):
    cfg = TrainConfig(actor_lr=None, critic_lr=None, tau=None, hidden_sizes=None)
    old = {**dataclasses.asdict(cfg), "preset": "pendulum"}  # as written before
    (tmp_path / "config.json").write_text(json.dumps(old))
    loaded = load_config(tmp_path)
    assert loaded.actor_lr is None and loaded.hidden_sizes is None
    resolved = dataclasses.replace(loaded, actor_lr=1e-3, tau=0.005, hidden_sizes=(400, 300))
    assert config_changes(loaded, resolved) == {}


# --------------------------------------------------------------------------------------------
# where evaluation returns are placed
# --------------------------------------------------------------------------------------------

# A record of an in-chunk evaluation: the returns are of the policy at 3200 env steps.
IN_CHUNK_RECORD = {"env_steps": 6400, "eval_policy_env_steps": 3200, "eval_return_mean": -150.0,
                   "eval_return_std": 12.5, "critic_loss": 0.25, "wall_time_s": 9.0}  # fmt: skip


def test_tensorboard_places_in_chunk_returns_at_the_policys_steps(tmp_path):
    logger = MetricsLogger(tmp_path)
    logger.write(IN_CHUNK_RECORD)
    logger.write({"env_steps": 9600, "eval_return_mean": -90.0, "critic_loss": 0.125})
    logger.close()
    scalars = tensorboard_scalars(tmp_path)
    assert scalars["eval_return_mean"] == {3200: -150.0, 9600: -90.0}
    assert scalars["eval_return_std"] == {3200: 12.5}
    assert scalars["critic_loss"] == {6400: 0.25, 9600: 0.125}
    assert scalars["eval_policy_env_steps"] == {6400: 3200.0}


class _Recorder:
    def __init__(self) -> None:
        self.logged: list[dict] = []

    def log(self, values: dict) -> None:
        self.logged.append(dict(values))


def test_wandb_places_in_chunk_returns_at_the_policys_steps():
    run = _Recorder()
    tracker = Tracker(run, image=lambda path: path)
    member = {"seed": 0, "eval_return_mean": -140.0, "critic_loss": 0.5}
    tracker.log({**IN_CHUNK_RECORD, "per_member": [member]})
    returns, rest = run.logged  # (the earlier env steps first: W&B's env_steps never goes back)
    assert returns == {"eval_return_mean": -150.0, "eval_return_std": 12.5,
                       "per_member/0/eval_return_mean": -140.0, "env_steps": 3200}  # fmt: skip
    assert rest["env_steps"] == 6400 and rest["critic_loss"] == 0.25
    assert rest["per_member/0/critic_loss"] == 0.5 and rest["eval_policy_env_steps"] == 3200
    assert not any("eval_return" in key for key in rest)
    assert tracker.env_steps == 6400
    run.logged.clear()
    tracker.log({"env_steps": 9600, "eval_return_mean": -90.0})  # evaluated after the chunk
    assert run.logged == [{"env_steps": 9600, "eval_return_mean": -90.0}]


# --------------------------------------------------------------------------------------------
# corrupt checkpoints
# --------------------------------------------------------------------------------------------

TENSORSTORE_ERROR = (
    'DATA_LOSS: Error opening "cast" driver: Error opening "zarr" driver: Error reading '
    '"00075/.zarray" in OCDBT database at local file "/r/state/"'
)


def test_a_corrupt_checkpoint_is_said_in_words_with_what_to_do():
    run = Path("/runs/x")
    newest = _unusable(run / "checkpoints" / "2", ValueError(TENSORSTORE_ERROR))
    assert str(newest) == ("checkpoint /runs/x/checkpoints/2 is unreadable or corrupt (its array "
                           "files are damaged)")  # fmt: skip
    older = _unusable(run / "checkpoints" / "1", json.JSONDecodeError("Expecting value", "{", 1))
    assert str(older).endswith("/1 is unreadable or corrupt (its metadata is damaged)")
    said = str(_all_corrupt(run / "checkpoints", [newest, older]))
    assert said.startswith(f"no usable checkpoint in /runs/x/checkpoints: {newest}; {older}; ")
    fix = ("none can be restored: start the run again with another --out (or remove /runs/x), "
           "or put back an intact copy of the checkpoints")  # fmt: skip
    assert said.endswith(fix)
    assert "zarr" not in said and "DATA_LOSS" not in said
    assert str(_all_corrupt(run / "checkpoints", [newest])).startswith(f"{newest}; none can be")


def test_a_checkpoint_cut_short_is_named_from_the_cause_beneath_the_storage_error():
    """Orbax raises a bare ``Exception`` ("Encountered error while reading array ...") from
    TensorStore's OUT_OF_RANGE error of a truncated file: the cause beneath is what is said,
    and the checkpoint counts as damaged (it once read "it cannot be read: ... See f...")."""
    try:
        try:
            raise ValueError('OUT_OF_RANGE: Error reading "00051/0.0.0.0" in OCDBT database: '
                             "Requested byte range [389710, 478562) is not valid for value of "
                             "size 100")  # fmt: skip
        except ValueError as cause:
            raise Exception("Encountered error while reading array index: (slice(0, 1, 1),). "
                            "See full TensorStore details: ...") from cause  # fmt: skip
    except Exception as err:
        cut = _unusable(Path("/runs/x/checkpoints/2"), err)
    assert str(cut).endswith("is unreadable or corrupt (its array files are cut short)")
    said = str(_all_corrupt(Path("/runs/x/checkpoints"), [cut]))
    assert said.endswith("start the run again with another --out (or remove /runs/x), or put "
                         "back an intact copy of the checkpoints")  # fmt: skip


def test_a_checkpoint_unread_for_another_cause_is_not_called_for_removal():
    # Out of memory (or no permission) says nothing of damage: the run is not to be thrown away.
    run = Path("/runs/x")
    damaged = _unusable(run / "checkpoints" / "2", ValueError(TENSORSTORE_ERROR))
    memory = _unusable(run / "checkpoints" / "1", RuntimeError("RESOURCE_EXHAUSTED: Out of memory"))
    assert str(memory).endswith("(it cannot be read: RuntimeError: RESOURCE_EXHAUSTED: Out of "
                                "memory)")  # fmt: skip
    said = str(_all_corrupt(run / "checkpoints", [damaged, memory]))
    assert said.endswith("; fix what keeps them from being read, then try again")
    assert "remove" not in said and "another --out" not in said


@pytest.mark.usefixtures("restored_logging")
def test_errors_a_failed_read_leaves_behind_are_dropped(monkeypatch):
    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)
    runtime.quiet_library_logs()
    namespace: dict = {}  # a coroutine of orbax's, as collected unfinished after a failed read
    exec(compile("async def read(): pass", f"{os.sep}site-packages{os.sep}orbax{os.sep}x.py",
                 "exec"), namespace)  # fmt: skip
    stray = namespace["read"]()
    error = RuntimeError("coroutine ignored GeneratorExit")
    left = types.SimpleNamespace(exc_type=RuntimeError, exc_value=error, exc_traceback=None,
                                 err_msg=None, object=stray)  # fmt: skip
    sys.unraisablehook(left)
    stray.close()
    assert seen == []
    own = types.SimpleNamespace(exc_type=ValueError, exc_value=ValueError("ours"),
                                exc_traceback=None, err_msg=None, object=None)  # fmt: skip
    sys.unraisablehook(own)
    assert seen == [own]  # anything else still reaches the previous hook
    try:  # a closed event loop of someone else's code (not tensorstore's callback) is kept
        raise RuntimeError("Event loop is closed")
    except RuntimeError as err:
        closed = types.SimpleNamespace(exc_type=RuntimeError, exc_value=err, object=None,
                                       exc_traceback=err.__traceback__, err_msg=None)  # fmt: skip
    sys.unraisablehook(closed)
    assert seen == [own, closed]


# --------------------------------------------------------------------------------------------
# the console of a run
# --------------------------------------------------------------------------------------------


def test_sigterm_says_what_it_does_before_and_after_training_starts(capsys):
    stop = runtime.StopToken()
    handler = runtime._signal_handler(stop, [], say=True)
    handler(signal.SIGTERM, None)
    err = capsys.readouterr().err
    assert "nothing trained yet, so nothing to save" in err and "checkpointed" not in err
    stop = runtime.StopToken()
    stop.mark_training()
    runtime._signal_handler(stop, [], say=True)(signal.SIGTERM, None)
    assert "stopping once the chunk in flight is checkpointed" in capsys.readouterr().err


def test_the_progress_bar_fits_80_columns():
    cfg = TrainConfig(env="playground/T1JoystickFlatTerrain", num_envs=4096, eval_every=4_096_000,
                      total_steps=102_400_000, eval_in_chunk=True)  # fmt: skip
    console = Console(width=80, file=io.StringIO(), force_terminal=True, color_system=None)
    progress = _Progress(cfg, 0, enabled=True, console=console)
    progress.update({"env_steps": 8_192_000, "eval_return_mean": -1532.54, "wall_time_s": 300.0,
                     "eval_policy_env_steps": 4_096_000, "env_steps_per_s": 55_123.4})  # fmt: skip
    progress.close()
    shown = Console(width=80, file=io.StringIO(), color_system=None)
    shown.print(progress._progress.make_tasks_table(progress._progress.tasks))
    (line,) = shown.file.getvalue().splitlines()
    assert len(line) <= 80 and "…" not in line, line
    for part in ("8.192M/102.4M steps", "55.12k/s", "eval -1532.5 @4.096M"):
        assert part in line, line


def test_a_terminal_keeps_the_logs_line_for_each_evaluation_above_the_bar(capsys):
    """On a terminal each evaluation leaves the line a log gets (the bar alone kept only the
    last return), whole, however wide."""
    cfg = TrainConfig(env="gymnax/Pendulum-v1", num_envs=16, eval_every=4000, total_steps=12000,
                      warmup_steps=2000)  # fmt: skip
    evaluations = ((4000, -1200.25, 10.0), (8000, -150.5, 14.0))
    records = [{"env_steps": steps, "eval_return_mean": value, "wall_time_s": seconds,
                "env_steps_per_s": 1234.5} for steps, value, seconds in evaluations]  # fmt: skip
    log = _Progress(cfg, 0, enabled=True, console=Console(file=io.StringIO()))
    for record in records:
        log.update(record)
    logged = [line for line in capsys.readouterr().out.splitlines() if line]
    assert len(logged) == 2 and "eval -150.5" in logged[1], logged
    console = Console(width=40, file=io.StringIO(), force_terminal=True, color_system=None)
    terminal = _Progress(cfg, 0, enabled=True, console=console)
    for record in records:
        terminal.update(record)
    terminal.close()
    shown = console.file.getvalue()
    assert all(line in shown for line in logged), (logged, shown)


def test_a_sweeps_line_names_its_best_setting_beside_the_mean_over_all(capsys):
    """A sweep's line keeps the mean over all members and adds the setting with the highest
    mean over its members that did not diverge; a run of seeds alone adds nothing."""
    cfg = TrainConfig(env="gymnax/Pendulum-v1", num_envs=16, eval_every=4000, total_steps=8000)
    members = [({"actor_lr": 0.001}, -1500.0), ({"actor_lr": 0.001}, -1400.0),
               ({"actor_lr": 0.0003}, -1300.0), ({"actor_lr": 0.0003}, None)]  # (diverged)
    record = {"env_steps": 4000, "eval_return_mean": -1400.0, "wall_time_s": 10.0,
              "env_steps_per_s": 1234.5,
              "per_member": [{"settings": s, "eval_return_mean": r} for s, r in members]}
    log = _Progress(cfg, 0, enabled=True, console=Console(file=io.StringIO()))
    log.update(record)
    seeds = {**record, "per_member": [{"eval_return_mean": r} for _, r in members]}
    log.update({**seeds, "env_steps": 8000})
    swept, alone = capsys.readouterr().out.splitlines()
    assert ("eval -1400.0 over the 3 of 4 members that did not diverge; best actor_lr=0.0003 "
            "at -1300.0, 10 s") in swept
    assert "eval -1400.0, 10 s" in alone


def test_a_log_shows_compiling_warm_up_and_a_resumes_own_time(tmp_path, capsys):
    # 64 iterations of 4 envs a chunk: the early evaluation after 8 (32 steps), all warm-up
    flags = ["--env", "gymnax/Pendulum-v1", "--num-envs", "4", "--eval-every", "256",
             "--warmup-steps", "64", "--batch-size", "16", "--updates-per-iter", "1",
             "--hidden-sizes", "16", "16", "--eval-envs", "2", "--episode-length", "16",
             "--buffer-size", "256", "--out", str(tmp_path / "run")]  # fmt: skip
    code, out, err = main(["train", *flags, "--total-steps", "256"], capsys)
    assert code == 0, err
    lines = out.splitlines()
    # (" (or loading it from the cache)" where earlier tests of this run used these settings)
    compiling = next(i for i, x in enumerate(lines) if x.startswith("compiling the training "))
    early, whole = (line for line in lines if line.startswith("td3 gymnax/Pendulum-v1: "))
    assert lines.index(early) > compiling
    assert early.startswith("td3 gymnax/Pendulum-v1: 32/256 env steps, warm-up, eval ")
    assert ": 256/256 env steps, " in whole and "env steps/s (with warm-up), eval" in whole
    assert "done: 256 env steps in " in lines[-1]
    code, out, err = main(["train", "--resume", "--out", str(tmp_path / "run"), "--total-steps",
                           "512"], capsys)  # fmt: skip
    assert code == 0, err
    done = re.fullmatch(r"done: 512 env steps \(256 in this process, in (\d+) s; (\d+) s over the "
                        r"whole run\); eval return .*", out.splitlines()[-1])  # fmt: skip
    assert done and int(done[1]) <= int(done[2]), out
    # a second run of these settings finds its programs stored (traced before): it says that
    # XLA may load them from its cache rather than compile them
    code, out, err = main(["train", *flags[:-1], str(tmp_path / "again"), "--total-steps", "256"],
                          capsys)  # fmt: skip
    assert code == 0, err
    lines = out.splitlines()
    compiling = lines.index("compiling the training program (or loading it from the cache)...")
    assert lines[compiling - 1].startswith("using the traced programs stored in "), out
    assert all(not line.startswith("using the traced") for line in lines[: compiling - 1])
    # a --resume of that finished run says only that it is complete (nothing loaded)
    with warnings.catch_warnings(record=True) as caught:  # (the library's own words for it:
        warnings.simplefilter("always")                    # not shown by the command)
        code, out, err = main(["train", "--resume", "--out", str(tmp_path / "again")], capsys)
    assert code == 0 and out.splitlines()[-1].startswith("nothing to do: the run in "), err
    assert [w.message for w in caught if w.category is RunCompleteWarning] == []
    assert not [line for line in out.splitlines() if line.startswith(("using the", "compiling"))]


def test_a_run_stopped_by_its_time_budget_says_so_and_how_to_go_on(tmp_path, capsys):
    """A budget smaller than one chunk stops the 128-step run after its first chunk of 64: the
    run exits 0, and its last line says why it stopped early and how to continue."""
    out = tmp_path / "run"
    code, stdout, err = main(["train", *TINY_FLAGS, "--time-budget-s", "0.001", "--out", str(out),
                              "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    lines = stdout.strip().splitlines()
    assert lines[-2].startswith("stopped: 64 env steps")  # (not "done": it did not finish)
    assert lines[-1] == (f"stopped by --time-budget-s 0.001 at 64 of 128 env steps; "
                         f"td3-jax train --out {out} --resume continues it")  # fmt: skip


@pytest.mark.parametrize("command", ["eval", "render"])
def test_a_seed_out_of_range_for_eval_and_render_is_one_line(command, tmp_path, capsys):
    code, _, err = main([command, "--run", str(tmp_path), "--seed", str(10**20)], capsys)
    assert_one_line_error(code, err, f"--seed {10**20} must be in [0, 4294967295]")
