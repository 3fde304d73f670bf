"""Where a train or sweep command without --out writes its run (cli.run_folder): a new folder
named for its preset or environment and its start, made at once so no two runs share it,
and removed again where the run was refused before writing anything."""

from __future__ import annotations

import time

import pytest
from support import TINY_FLAGS, assert_one_line_error, main

from td3_jax.cli import run_folder
from td3_jax.config.schema import ConfigError, TrainConfig

#: 2026-11-30 21:15:00 in this process's local time.
MOMENT = time.mktime((2026, 11, 30, 21, 15, 0, 0, 0, -1))
STAMP = "20261130-211500"


@pytest.fixture(autouse=True)
def _one_process(monkeypatch, tmp_path):
    """A process that joins no others, in a folder of its own."""
    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.chdir(tmp_path)


@pytest.mark.parametrize("given", [["--out", "runs/mine"], ["--out=runs/mine"], ["--help"],
                                   ["-h"], ["--out"]])
def test_a_given_out_or_help_leaves_the_flags_as_they_are(given, tmp_path):
    args = ["--total-steps", "100", *given]
    assert run_folder.with_run_directory(args, MOMENT) == (args, None)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    ("flags", "name"),
    [([], TrainConfig.env.replace("/", "-")), (["--preset", "t1"], "t1"),
     (["--env", "brax/ant"], "brax-ant"), (["--env=my.module:make env"], "my.module-make-env"),
     (["--preset", "ant", "--env", "brax/ant"], "ant"),
     (["--preset", "ant", "--preset=t1"], "t1")],  # (the last, as the parser takes it)
)  # fmt: skip
def test_without_out_the_run_goes_to_a_new_folder_named_for_its_preset_or_env(
    flags, name, tmp_path
):
    args, out = run_folder.with_run_directory(flags, MOMENT)
    assert str(out) == f"runs/{name}-{STAMP}"
    assert args == [*flags, "--out", str(out)]
    assert (tmp_path / out).is_dir()  # (made now: another run cannot take it)


def test_a_used_name_gets_the_next_number(tmp_path):
    (tmp_path / f"t1-{STAMP}").mkdir()
    (tmp_path / f"t1-{STAMP}-2").mkdir()
    assert run_folder.new_run_directory("t1", tmp_path, MOMENT) == tmp_path / f"t1-{STAMP}-3"


@pytest.mark.parametrize(("name", "label"), [("//", "run"), ("a" * 59 + "/b", "a" * 59)])
def test_a_name_is_letters_digits_dots_and_dashes_at_most_60(name, label, tmp_path):
    assert run_folder.new_run_directory(name, tmp_path, MOMENT).name == f"{label}-{STAMP}"


def test_a_resume_without_out_is_refused_and_the_former_default_named(tmp_path):
    with pytest.raises(ConfigError, match=r"^--resume continues the run in --out DIR: name it "
                                          r"with --out$"):  # fmt: skip
        run_folder.with_run_directory(["--resume"], MOMENT)
    (tmp_path / "runs" / "latest").mkdir(parents=True)
    (tmp_path / "runs" / "latest" / "config.json").write_text("{}")
    with pytest.raises(ConfigError, match=r"; --out runs/latest for the run an earlier td3-jax"):
        run_folder.with_run_directory(["--resume"], MOMENT)


@pytest.mark.parametrize(("flags", "variable"), [
    (["--num-processes", "2"], None), (["--num_processes=2"], None),
    (["--process-id=1"], None), (["--coordinator_address", "h:1"], None),
    ([], ("JAX_COORDINATOR_ADDRESS", "localhost:1234")), ([], ("JAX_NUM_PROCESSES", "2")),
])  # fmt: skip
def test_a_process_that_joins_others_without_out_is_refused(flags, variable, monkeypatch):
    if variable:
        monkeypatch.setenv(*variable)
    with pytest.raises(ConfigError, match="joins others of one run, which write one folder"):
        run_folder.with_run_directory(flags, MOMENT)


def test_one_process_by_jaxs_variables_gets_a_folder(monkeypatch):
    monkeypatch.setenv("JAX_NUM_PROCESSES", "1")
    assert run_folder.with_run_directory([], MOMENT)[1] is not None


def test_two_runs_in_one_second_write_two_folders_and_say_where(tmp_path, monkeypatch):
    frozen = time.localtime(MOMENT)
    monkeypatch.setattr(run_folder.time, "localtime", lambda now=None: frozen)
    outs = []
    for _ in range(2):
        code, stdout, stderr = main(["train", *TINY_FLAGS, "--quiet"])
        assert code == 0, stderr
        first = stdout.splitlines()[0]
        assert first.startswith("no --out given: the run goes to runs/")
        outs.append(first.rsplit(" ", 1)[1])
    name = TrainConfig.env.replace("/", "-")
    assert outs == [f"runs/{name}-{STAMP}", f"runs/{name}-{STAMP}-2"]
    assert all((tmp_path / out / "metrics.jsonl").is_file() for out in outs)


def test_a_refused_run_leaves_no_folder(tmp_path, capsys):
    code, _, err = main(["train", *TINY_FLAGS, "--batch-size", "0"], capsys)
    assert code == 2, err
    assert not (tmp_path / "runs").exists()  # (made for the run, so removed with it)


def test_an_earlier_runs_made_folder_is_not_removed_by_a_later_refused_run(tmp_path, capsys):
    """A runs/ made for an earlier run of this process is there before the next one."""
    _, out = run_folder.with_run_directory([], MOMENT)
    out.rmdir()  # (that run's folder gone, runs/ left empty)
    code, _, err = main(["train", *TINY_FLAGS, "--batch-size", "0"], capsys)
    assert code == 2, err
    assert (tmp_path / "runs").is_dir()


def test_a_runs_folder_removed_meanwhile_is_made_again(tmp_path, monkeypatch):
    """Another run's removal of runs/ between this one's look and its mkdir."""
    real, calls = run_folder._make_folder, []

    def already_there_then_real(folder):
        calls.append(folder)
        return False if len(calls) == 1 else real(folder)  # (first: "there", made by no one)

    monkeypatch.setattr(run_folder, "_make_folder", already_there_then_real)
    out = run_folder.new_run_directory("t1", tmp_path / "runs", MOMENT)
    assert out == tmp_path / "runs" / f"t1-{STAMP}" and out.is_dir() and len(calls) == 2
    run_folder.remove_if_empty(out)
    assert not (tmp_path / "runs").exists()  # (made by this run the second time)


def test_a_runs_link_to_a_folder_that_is_gone_is_one_line(tmp_path, capsys):
    (tmp_path / "runs").symlink_to(tmp_path / "purged scratch")
    code, _, err = main(["train", *TINY_FLAGS], capsys)
    assert_one_line_error(code, err, "cannot make a folder for the run in runs/",
                          "give one with --out DIR")  # fmt: skip


def test_a_refused_run_keeps_a_runs_folder_that_was_there(tmp_path, capsys):
    (tmp_path / "runs").mkdir()
    code, _, err = main(["train", *TINY_FLAGS, "--batch-size", "0"], capsys)
    assert code == 2, err
    assert list((tmp_path / "runs").iterdir()) == []


@pytest.mark.parametrize(("args", "message"), [
    (["--resume"], "--resume continues the run in --out DIR"),
    (["--out", "None"], "--out None names no folder"),
])  # fmt: skip
def test_the_command_refuses_in_one_line(args, message, tmp_path, capsys):
    code, _, err = main(["train", *args], capsys)
    assert_one_line_error(code, err, message)
    assert not (tmp_path / "runs").exists()


def test_a_file_named_runs_is_one_line_naming_out(tmp_path, capsys):
    (tmp_path / "runs").write_text("not a folder")
    code, _, err = main(["train", *TINY_FLAGS], capsys)
    assert_one_line_error(code, err, "cannot make a folder for the run in runs/",
                          "give one with --out DIR")  # fmt: skip


@pytest.mark.parametrize("command", ["train", "sweep"])
def test_a_resumes_help_is_the_help(command, capsys):
    code, out, err = main([command, "--resume", "--help"], capsys)
    assert code == 0, err
    assert out.startswith(f"usage: td3-jax {command}") and "--out" in out
