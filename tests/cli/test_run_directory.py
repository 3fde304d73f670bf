"""Where a train or sweep command without --out writes its run (argv.with_run_directory):
a new folder named for its preset or environment and its start, never one already used."""

from __future__ import annotations

import time

import pytest
from support import TINY_FLAGS, assert_one_line_error, main

from td3_jax.cli import argv
from td3_jax.config.schema import ConfigError, TrainConfig

#: 2026-11-30 21:15:00 in this process's local time.
NOON = time.mktime((2026, 11, 30, 21, 15, 0, 0, 0, -1))


@pytest.mark.parametrize("given", [["--out", "runs/mine"], ["--out=runs/mine"], ["--help"],
                                   ["-h"], ["--out"]])
def test_a_given_out_or_help_leaves_the_flags_as_they_are(given):
    args = ["--total-steps", "100", *given]
    assert argv.with_run_directory(args, NOON) == (args, None)


@pytest.mark.parametrize(
    ("flags", "name"),
    [([], TrainConfig.env.replace("/", "-")), (["--preset", "t1"], "t1"),
     (["--env", "brax/ant"], "brax-ant"), (["--env=my.module:make env"], "my.module-make-env"),
     (["--preset", "ant", "--env", "brax/ant"], "ant")],
)
def test_without_out_the_run_goes_to_a_new_folder_named_for_its_preset_or_env(
    flags, name, monkeypatch, tmp_path
):
    monkeypatch.chdir(tmp_path)
    args, out = argv.with_run_directory(flags, NOON)
    assert str(out) == f"runs/{name}-20261130-211500"
    assert args == [*flags, "--out", str(out)]


def test_a_used_name_gets_the_next_number(tmp_path):
    (tmp_path / "t1-20261130-211500").mkdir()
    (tmp_path / "t1-20261130-211500-2").mkdir()
    assert argv.new_run_directory("t1", tmp_path, NOON) == tmp_path / "t1-20261130-211500-3"


def test_a_name_without_letters_or_digits_is_run(tmp_path):
    assert argv.new_run_directory("//", tmp_path, NOON).name == "run-20261130-211500"


def test_a_resume_without_out_is_refused():
    with pytest.raises(ConfigError, match="--resume continues the run in --out DIR"):
        argv.with_run_directory(["--resume"], NOON)


@pytest.mark.parametrize(("flags", "variable", "named"), [
    (["--num-processes", "2"], None, "--num-processes"),
    (["--process-id=1"], None, "--process-id"),
    ([], "JAX_COORDINATOR_ADDRESS", "JAX_COORDINATOR_ADDRESS"),
])
def test_a_process_of_several_without_out_is_refused(flags, variable, named, monkeypatch):
    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(name, raising=False)
    if variable:
        monkeypatch.setenv(variable, "localhost:1234")
    with pytest.raises(ConfigError, match=f"^{named} makes this one process of several"):
        argv.with_run_directory(flags, NOON)


def test_two_runs_without_out_write_two_folders_and_say_where(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    outs = []
    for _ in range(2):
        code, stdout, stderr = main(["train", *TINY_FLAGS, "--quiet"])
        assert code == 0, stderr
        first = stdout.splitlines()[0]
        assert first.startswith("no --out given: the run goes to runs/")
        outs.append(tmp_path / first.rsplit(" ", 1)[1])
    assert outs[0] != outs[1]
    assert all((out / "metrics.jsonl").is_file() for out in outs)


def test_the_command_refuses_a_resume_without_out_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, _, err = main(["train", "--resume"], capsys)
    assert_one_line_error(code, err, "--resume continues the run in --out DIR")
    assert not (tmp_path / "runs").exists()
