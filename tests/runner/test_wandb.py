"""Weights & Biases logging (``--wandb``, :mod:`td3_jax.runner.tracking`).

A fake ``wandb`` module (in ``sys.modules``) records what a run sends, for exact comparisons
with metrics.jsonl and config.json; one real offline run (a subprocess, no network) is read
back from its ``.wandb`` file. The tiny runs share one set of shapes, so they compile once.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import types
from pathlib import Path

import pytest
from support import TINY_FLAGS, assert_one_line_error, main, read_records

from td3_jax.config.schema import ConfigError, TrainConfig, idle_wandb_flags, validate
from td3_jax.runner import run as run_module
from td3_jax.runner import tracking
from td3_jax.runner.rundir import check_fresh, config_changes

# TINY_FLAGS with a ring of 64 rows, which a run of 64 steps and one of 128 both have: one
# compiled program serves the short run, its resume and the full runs.
FLAGS = [*TINY_FLAGS[: TINY_FLAGS.index("--buffer-size")], "--buffer-size", "64"]


class FakeRun:
    """What ``wandb.init`` returns, recording what it is sent."""

    def __init__(self, arguments: dict, fail_on_log: int | None):
        self.arguments, self.fail_on_log = arguments, fail_on_log
        self.history: list[dict] = []
        self.metrics: list[tuple] = []
        self.finished = False
        self.config = types.SimpleNamespace(update=self._update_config, values={})

    def _update_config(self, values: dict, allow_val_change: bool = False) -> None:
        assert allow_val_change  # (a resume sends config.json again, with resume_changes)
        self.config.values.update(values)

    def log(self, data: dict) -> None:
        if self.fail_on_log is not None and len(self.history) + 1 >= self.fail_on_log:
            raise RuntimeError("the W&B service went away")
        self.history.append(dict(data))

    def define_metric(self, name: str, step_metric: str | None = None) -> None:
        self.metrics.append((name, step_metric))

    def finish(self) -> None:
        self.finished = True


def fake_wandb(logged_in: bool = True, fail_on_log: int | None = None) -> types.ModuleType:
    """A ``wandb`` module with what td3-jax calls; ``runs`` lists the runs it started."""
    module = types.ModuleType("wandb")
    module.runs = []
    module.login = lambda prompt=True, verify=True: logged_in
    module.Settings = lambda **settings: settings
    module.Image = lambda path: ("image", path)

    def init(settings=None, **arguments):
        module.runs.append(FakeRun({**arguments, "settings": settings}, fail_on_log))
        return module.runs[-1]

    module.init = init
    return module


@pytest.fixture
def no_wandb_environment(monkeypatch, tmp_path):
    """No W&B credentials or mode from the environment, W&B's files under ``tmp_path``."""
    for name in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_IDENTITY_TOKEN_FILE", "WANDB_BASE_URL"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("NETRC", str(tmp_path / "no-netrc"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "wandb-config"))
    monkeypatch.setenv("WANDB_SILENT", "true")


@pytest.fixture
def wandb_module(monkeypatch, no_wandb_environment):
    module = fake_wandb()
    monkeypatch.setitem(sys.modules, "wandb", module)
    return module


def expected_numbers(record: dict) -> dict:
    """A single run's metrics.jsonl record as W&B should get it: its numbers (it has no nested
    values and, finished, no nulls), nothing else."""
    return {k: v for k, v in record.items() if type(v) in (int, float)}


def stored_id(out: Path) -> str:
    return (out / "wandb" / "td3-jax-run-id").read_text().strip()


# --------------------------------------------------------------------------------------------
# what a run sends (the fake module)
# --------------------------------------------------------------------------------------------


@pytest.mark.runs
def test_a_run_sends_its_records_config_and_curve(wandb_module, tmp_path, capsys):
    out = tmp_path / "pendulum-run"
    args = ["train", *FLAGS, "--out", str(out), "--quiet", "--wandb", "--wandb-entity", "team"]
    code, _, err = main(args, capsys)
    assert code == 0, err
    (run,) = wandb_module.runs
    assert run.arguments == {"project": "td3-jax", "entity": "team", "name": "pendulum-run",
                             "id": stored_id(out), "resume": "allow", "dir": str(out),
                             "settings": {"console": "off", "silent": True,
                                          "init_timeout": 30.0}}  # fmt: skip
    assert run.metrics == [("env_steps", None), ("*", "env_steps")]
    records = read_records(out)
    assert [r["env_steps"] for r in records] == [64, 128]
    assert run.history[:-1] == [expected_numbers(r) for r in records]
    assert run.history[-1] == {"curve": ("image", str(out / "curve.png")), "env_steps": 128}
    assert run.config.values == json.loads((out / "config.json").read_text())
    assert run.config.values["wandb"] is True and run.config.values["wandb_entity"] == "team"
    assert run.finished


def test_a_resumed_run_continues_its_wandb_run(wandb_module, tmp_path, capsys):
    out = tmp_path / "run"
    short = [*FLAGS, "--total-steps", "64", "--out", str(out), "--quiet"]
    code, _, err = main(["train", *short, "--wandb", "--wandb-name", "first"], capsys)
    assert code == 0, err
    code, _, err = main(["train", "--resume", "--out", str(out), "--total-steps", "128",
                         "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    first, second = wandb_module.runs
    assert second.arguments["id"] == first.arguments["id"] == stored_id(out)
    assert second.arguments["resume"] == "allow" and second.arguments["name"] == "first"
    records = read_records(out)
    assert [h["env_steps"] for h in first.history] == [64, 64]  # the record, then the curve
    assert second.history[:-1] == [expected_numbers(records[1])]
    assert second.config.values["resume_changes"] == [
        {"at_env_steps": 64, "total_steps": [64, 128]}
    ]
    # a fresh run elsewhere is a W&B run of its own
    code, _, err = main(["train", *short[:-3], "--out", str(tmp_path / "b"), "--wandb"], capsys)
    assert code == 0, err
    assert wandb_module.runs[-1].arguments["id"] != first.arguments["id"]


def test_a_wandb_failure_mid_run_loses_no_record(monkeypatch, no_wandb_environment, tmp_path,
                                                 capsys):  # fmt: skip
    module = fake_wandb(fail_on_log=2)
    monkeypatch.setitem(sys.modules, "wandb", module)
    out = tmp_path / "run"
    code, _, err = main(["train", *FLAGS, "--out", str(out), "--quiet", "--wandb"], capsys)
    assert code == 0, err
    assert [r["env_steps"] for r in read_records(out)] == [64, 128]
    assert (out / "curve.png").exists()
    (warning,) = [line for line in err.splitlines() if "Weights & Biases" in line]
    assert warning.startswith("td3-jax: warning: Weights & Biases failed (RuntimeError: ")
    assert "metrics.jsonl keeps every record" in warning
    assert len(module.runs[0].history) == 1


# --------------------------------------------------------------------------------------------
# what stops a run before it compiles
# --------------------------------------------------------------------------------------------


def _refuse_tracing(monkeypatch) -> None:
    def traced(*args, **kwargs):
        raise AssertionError("the run was traced before its W&B check")

    monkeypatch.setattr(run_module.programs, "find", traced)


def test_wandb_without_the_package_is_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "wandb", None)  # `import wandb` fails
    _refuse_tracing(monkeypatch)
    out = tmp_path / "run"
    code, _, err = main(["train", *FLAGS, "--out", str(out), "--wandb"], capsys)
    assert_one_line_error(code, err, "--wandb needs the wandb package",
                          "pip install 'td3-jax[wandb]'")  # fmt: skip
    assert not out.exists()


def test_wandb_settings_typed_without_wandb_are_one_line(monkeypatch, tmp_path, capsys):
    _refuse_tracing(monkeypatch)
    out = tmp_path / "run"
    code, _, err = main(["train", *FLAGS, "--out", str(out), "--wandb-entity", "team"], capsys)
    assert_one_line_error(code, err, "--wandb-entity given without --wandb")
    assert not out.exists()


def test_online_wandb_without_a_login_is_one_line(monkeypatch, no_wandb_environment, tmp_path,
                                                  capsys):  # fmt: skip
    pytest.importorskip("wandb")  # W&B's own look for credentials (none here)
    _refuse_tracing(monkeypatch)
    out = tmp_path / "run"
    code, _, err = main(["train", *FLAGS, "--out", str(out), "--wandb"], capsys)
    assert_one_line_error(code, err, "not logged in to Weights & Biases", "run `wandb login`",
                          "--wandb-mode offline")  # fmt: skip
    assert not out.exists()


def test_offline_mode_needs_no_login(monkeypatch, no_wandb_environment):
    monkeypatch.setitem(sys.modules, "wandb", fake_wandb(logged_in=False))
    with pytest.raises(tracking.WandbError, match="wandb login"):
        tracking.check_ready(TrainConfig(wandb=True))
    tracking.check_ready(TrainConfig(wandb=True, wandb_mode="offline"))
    monkeypatch.setenv("WANDB_MODE", "offline")
    tracking.check_ready(TrainConfig(wandb=True))
    tracking.check_ready(TrainConfig())  # no --wandb: nothing to check


def test_a_wandb_run_that_cannot_start_is_one_line(monkeypatch, wandb_module, tmp_path, capsys):
    def unreachable(**arguments):
        raise ConnectionError("\x1b[1;34mapi.wandb.ai\x1b[0m:\n  unreachable")  # (colours)

    def teardown():  # W&B's service says where its logs are as it ends
        torn_down.append(True)
        print("wandb: Find logs at: run/wandb/logs", file=sys.stderr)
        print("wandb: ")

    torn_down = []
    monkeypatch.setattr(wandb_module, "init", unreachable)
    monkeypatch.setattr(wandb_module, "teardown", teardown, raising=False)
    out = tmp_path / "run"
    code, stdout, err = main(["train", *FLAGS, "--out", str(out), "--wandb"], capsys)
    assert_one_line_error(code, err, "could not start the run (api.wandb.ai: unreachable)",
                          "--wandb-mode offline")  # fmt: skip
    assert torn_down == [True] and "wandb" not in stdout  # ended, its lines dropped
    assert not (out / "config.json").exists()
    check_fresh(out)  # the same command can run again there


# --------------------------------------------------------------------------------------------
# settings
# --------------------------------------------------------------------------------------------


def test_mode_is_the_flag_then_wandb_mode_then_online(monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    assert tracking.mode(TrainConfig(wandb=True)) == "online"
    monkeypatch.setenv("WANDB_MODE", "dryrun")
    assert tracking.mode(TrainConfig(wandb=True)) == "offline"
    assert tracking.mode(TrainConfig(wandb=True, wandb_mode="online")) == "online"
    cfg = TrainConfig(wandb=True, wandb_mode="offline")
    assert tracking.init_arguments(cfg, Path("runs/x"), "abc")["mode"] == "offline"
    assert "mode" not in tracking.init_arguments(TrainConfig(wandb=True), Path("r"), "abc")
    monkeypatch.setenv("WANDB_MODE", "bogus")  # one line (exit 2), not W&B's traceback
    with pytest.raises(tracking.WandbError, match="WANDB_MODE is 'bogus'"):
        tracking.check_ready(TrainConfig(wandb=True))
    assert tracking.mode(TrainConfig(wandb=True, wandb_mode="offline")) == "offline"


def test_nested_numbers_are_logged_under_slash_joined_keys():
    record = {"env": "gymnax/Pendulum-v1", "env_steps": 64, "eval_return_mean": -3.5,
              "diverged_members": ["seed=1"], "eval_return_std": None,
              "per_member": [{"seed": 0, "settings": {"actor_lr": 1e-3}, "actor_loss": 0.25,
                              "eval_return_mean": None, "diverged": True}]}  # fmt: skip
    assert tracking.numbers(record) == {
        "env_steps": 64,
        "eval_return_mean": -3.5,
        "per_member/0/seed": 0,
        "per_member/0/settings/actor_lr": 1e-3,
        "per_member/0/actor_loss": 0.25,
    }
    assert tracking.numbers({"x": float("nan"), "y": float("inf"), "z": 1}) == {"z": 1}


def test_wandb_settings_may_change_on_resume_and_are_checked():
    saved = TrainConfig(wandb=True, wandb_mode="offline", wandb_project="p")
    assert config_changes(saved, TrainConfig()) == {
        "wandb": [True, False], "wandb_project": ["p", "td3-jax"], "wandb_mode": ["offline", None]
    }  # fmt: skip
    with pytest.raises(ConfigError, match="--wandb-mode"):
        validate(TrainConfig(wandb=True, wandb_mode="sometimes"))
    with pytest.raises(ConfigError, match="--wandb-project"):
        validate(TrainConfig(wandb=True, wandb_project=""))
    # W&B settings typed without --wandb would do nothing: said, not ignored; carried from
    # config.json (a resume with --no-wandb), they are not refused.
    with pytest.raises(ConfigError, match="--wandb-mode, --wandb-project given without --wandb"):
        idle_wandb_flags(TrainConfig(), {"wandb_mode", "wandb_project", "num_envs"})
    idle_wandb_flags(TrainConfig(wandb=True), {"wandb_mode"})
    idle_wandb_flags(TrainConfig(wandb_mode="offline", wandb_entity="team"), {"wandb"})
    assert validate(TrainConfig(wandb_mode="offline", wandb_entity="team")).wandb_mode


# --------------------------------------------------------------------------------------------
# a real offline run (a subprocess: W&B's service and hooks stay out of the test process)
# --------------------------------------------------------------------------------------------


def wandb_records(path: Path) -> list:
    """The records of a ``.wandb`` file (W&B's LevelDB-style log: a 7-byte header, then 32 KiB
    blocks of chunks, each with a 7-byte header of checksum, length and type)."""
    from wandb.proto import wandb_internal_pb2

    data, pos, parts, records = path.read_bytes(), 7, b"", []
    assert data[:4] == b":W&B"
    while pos + 7 <= len(data):
        if 32768 - pos % 32768 < 7:  # a block's tail too short for a chunk header: padding
            pos += 32768 - pos % 32768
            continue
        _, length, kind = struct.unpack("<IHB", data[pos : pos + 7])
        parts, pos = parts + data[pos + 7 : pos + 7 + length], pos + 7 + length
        if kind in (1, 4):  # a whole record, or the last chunk of one
            records.append(wandb_internal_pb2.Record.FromString(parts))
            parts = b""
    return records


def offline_run(out: Path, part: int) -> tuple[list, list]:
    """``(records, offline run folders)`` of part ``part`` (0: the first) of a run's W&B run."""
    folders = sorted((out / "wandb").glob("offline-run-*"))
    (log,) = folders[part].glob("run-*.wandb")
    return wandb_records(log), folders


def decoded(items) -> dict:
    return {"/".join(item.nested_key) or item.key: json.loads(item.value_json) for item in items}


def run_offline(*args: str, home: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")}
    env.update(WANDB_MODE="offline", WANDB_SILENT="true", WANDB_DIR=str(home / "wandb-dir"),
               WANDB_CONFIG_DIR=str(home / "config"), NETRC=str(home / "no-netrc"))  # fmt: skip
    return subprocess.run([sys.executable, "-m", "td3_jax", "train", *args], env=env,
                          capture_output=True, text=True, timeout=240)  # fmt: skip


@pytest.mark.processes
def test_an_offline_run_holds_the_numbers_config_and_curve_and_resumes_its_id(tmp_path):
    pytest.importorskip("wandb")
    out = tmp_path / "run"
    proc = run_offline(*FLAGS, "--total-steps", "64", "--out", str(out), "--quiet", "--wandb",
                       home=tmp_path)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    records, folders = offline_run(out, 0)
    kinds = [r.WhichOneof("record_type") for r in records]
    (started,) = [r.run for r in records if r.HasField("run")]
    assert started.run_id == stored_id(out) and started.project == "td3-jax"
    assert started.display_name == "run" and folders[0].name.endswith("-" + stored_id(out))
    config = {}
    for record in (r for r in records if r.HasField("config")):
        config.update(decoded(record.config.update))
    saved = json.loads((out / "config.json").read_text())
    assert {k: config[k] for k in saved} == saved
    rows = [decoded(r.history.item) for r in records if r.HasField("history")]
    numbers = [{k: v for k, v in row.items() if not k.startswith("_")} for row in rows]
    assert numbers[0] == expected_numbers(read_records(out)[0])
    assert numbers[1]["curve/format"] == "png" and numbers[1]["env_steps"] == 64
    assert (folders[0] / "files" / numbers[1]["curve/path"]).is_file()
    assert "exit" in kinds  # the W&B run was finished

    proc = run_offline("--resume", "--total-steps", "128", "--out", str(out), "--quiet",
                       home=tmp_path)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    records, folders = offline_run(out, 1)
    assert len(folders) == 2 and folders[1].name.endswith("-" + stored_id(out))
    assert [r.run.run_id for r in records if r.HasField("run")] == [stored_id(out)]
    rows = [decoded(r.history.item) for r in records if r.HasField("history")]
    assert {k: v for k, v in rows[0].items() if not k.startswith("_")} == expected_numbers(
        read_records(out)[1]
    )


@pytest.mark.processes
def test_importing_td3_jax_does_not_import_wandb():
    code = ("import sys, td3_jax.cli.app, td3_jax.cli.train, td3_jax.cli.finished, "
            "td3_jax.runner.run, td3_jax.runner.tracking; "
            "assert 'wandb' not in sys.modules, 'wandb imported'")  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
