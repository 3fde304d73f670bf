"""What W&B (``td3_jax.runner.tracking``) is sent across a run's resumes (each record once), and
what it prints (its banners left out).

A small fake ``wandb`` module records what each W&B run is sent; no training runs. One real
offline W&B run, in a child process (W&B's service and hooks stay out of the test process).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import types

import pytest

from td3_jax.config.schema import TrainConfig
from td3_jax.runner import tracking


class _Run:
    """What ``wandb.init`` returns: the history it is sent."""

    def __init__(self, arguments: dict):
        self.arguments, self.history = arguments, []
        self.config = types.SimpleNamespace(update=lambda values, allow_val_change=False: None)

    def log(self, data: dict) -> None:
        self.history.append(dict(data))

    def define_metric(self, name: str, step_metric: str | None = None) -> None:
        pass

    def finish(self) -> None:
        pass


@pytest.fixture
def runs(monkeypatch) -> list[_Run]:
    """The W&B runs started, in order (a fake ``wandb`` in ``sys.modules``)."""
    module, started = types.ModuleType("wandb"), []
    module.Settings = lambda **settings: settings
    module.Image = lambda path: ("image", path)
    module.init = lambda settings=None, **arguments: started.append(_Run(arguments)) or started[-1]
    monkeypatch.setitem(sys.modules, "wandb", module)
    return started


def _record(steps: int) -> dict:
    """A record with its evaluation inside the chunk: returns of the policy of 32 steps before."""
    return {"env_steps": steps, "eval_policy_env_steps": steps - 32,
            "eval_return_mean": steps / 10, "critic_loss": steps / 100}  # fmt: skip


def _points(history: list[dict], key: str) -> list[tuple[int, float]]:
    """``(env_steps, value)`` of each point of ``key`` that a W&B run was sent."""
    return [(row["env_steps"], row[key]) for row in history if key in row]


def _part(out, steps: list[int], *, resume: bool) -> None:
    """One process's part of a run: its W&B run started, these records logged, nothing ended
    (a stop)."""
    tracker = tracking.start(TrainConfig(wandb=True), out, resume=resume)
    for step in steps:
        tracker.log(_record(step))


def test_a_resume_sends_wandb_each_record_once(runs, tmp_path):
    """A run checkpointed at 64 sent the record of 96 before it stopped; resumed from 64, it
    writes that record again (the same numbers) and goes on to 128. W&B gets each record, and
    each evaluation's returns, once: no second point at 96 (nor at 64, the returns' steps)."""
    _part(tmp_path, [32, 64, 96], resume=False)
    _part(tmp_path, [96, 128], resume=True)
    first, second = runs
    assert second.arguments["id"] == first.arguments["id"]
    history = first.history + second.history
    assert _points(history, "critic_loss") == [(32, 0.32), (64, 0.64), (96, 0.96), (128, 1.28)]
    assert _points(history, "eval_return_mean") == [(0, 3.2), (32, 6.4), (64, 9.6), (96, 12.8)]
    # resumed again from 96, it sends what the second part did not
    _part(tmp_path, [128, 160], resume=True)
    assert _points(runs[2].history, "critic_loss") == [(160, 1.6)]


def test_records_no_wandb_run_was_sent_are_sent(runs, tmp_path):
    """A fresh run in a directory that held another W&B run, and a resume whose W&B run's id
    file was replaced (another W&B run), send every record: what the old run had is not the
    new one's."""
    _part(tmp_path, [32, 64], resume=False)
    _part(tmp_path, [32, 64], resume=False)
    assert runs[1].arguments["id"] != runs[0].arguments["id"]
    assert _points(runs[1].history, "critic_loss") == [(32, 0.32), (64, 0.64)]
    (tmp_path / tracking.WANDB_DIR / tracking.ID_FILE).write_text("another\n")
    _part(tmp_path, [64, 96], resume=True)
    assert runs[2].arguments["id"] == "another"
    assert _points(runs[2].history, "critic_loss") == [(64, 0.64), (96, 0.96)]


@pytest.mark.parametrize(
    "change",
    [
        {"wandb_project": "another-project"},
        {"wandb_entity": "another-team"},
        {"WANDB_ENTITY": "team-of-the-environment"},
    ],
)
def test_a_resume_sending_elsewhere_sends_every_record(runs, tmp_path, monkeypatch, change):
    """The same W&B run id under another project or entity (``--resume`` may change them;
    ``$WANDB_ENTITY`` too) is a W&B run that has none of the records: each one the resume
    writes is sent there, those it redoes included. Back at the first place, only the new."""
    monkeypatch.delenv("WANDB_ENTITY", raising=False)
    _part(tmp_path, [32, 64, 96], resume=False)
    settings = {k: v for k, v in change.items() if k.startswith("wandb_")}
    with monkeypatch.context() as environment:
        for name in set(change) - set(settings):
            environment.setenv(name, change[name])
        tracker = tracking.start(TrainConfig(wandb=True, **settings), tmp_path, resume=True)
        for step in (96, 128):
            tracker.log(_record(step))
    assert runs[1].arguments["id"] == runs[0].arguments["id"]
    assert _points(runs[1].history, "critic_loss") == [(96, 0.96), (128, 1.28)]
    _part(tmp_path, [96, 128, 160], resume=True)  # the first place again: it has up to 96
    assert _points(runs[2].history, "critic_loss") == [(128, 1.28), (160, 1.6)]


def test_an_offline_resume_of_an_online_run_holds_only_what_it_lacks(runs, tmp_path):
    """Offline parts are synced into the same W&B run (``wandb sync``): one must not hold the
    records the W&B run has already, or they would show twice there."""
    _part(tmp_path, [32, 64, 96], resume=False)
    tracker = tracking.start(TrainConfig(wandb=True, wandb_mode="offline"), tmp_path, resume=True)
    for step in (96, 128):
        tracker.log(_record(step))
    assert runs[1].arguments["mode"] == "offline"
    assert _points(runs[1].history, "critic_loss") == [(128, 1.28)]


def test_wandb_waits_30_s_to_start_unless_wandb_init_timeout_says(monkeypatch):
    """W&B's own 90 s (a machine without network waited two minutes for the one-line error)
    become 30; ``$WANDB_INIT_TIMEOUT`` is W&B's to read and wins."""
    monkeypatch.delenv("WANDB_INIT_TIMEOUT", raising=False)
    assert tracking.init_settings() == {"console": "off", "silent": True, "init_timeout": 30.0}
    monkeypatch.setenv("WANDB_INIT_TIMEOUT", "120")
    assert tracking.init_settings() == {"console": "off", "silent": True}


# A process that starts an offline W&B run as a training run does, logs a record and ends it;
# then a warning of W&B's own, which must still show.
_OFFLINE = textwrap.dedent(
    """
    import sys, wandb
    from td3_jax.runner import tracking
    from td3_jax.config.schema import TrainConfig

    tracker = tracking.start(TrainConfig(wandb=True), sys.argv[1], resume=False)
    tracker.log({"env_steps": 64, "eval_return_mean": -3.5})
    tracker.finish()
    wandb.termwarn("a warning of W&B's own")
    """
)


@pytest.mark.processes
def test_an_offline_wandb_run_prints_one_line_of_td3_jax_and_keeps_its_data(tmp_path):
    """With W&B offline (``$WANDB_MODE``), starting, logging and ending a W&B run prints one
    line, td3-jax's, saying where the run is and how to upload it, and none of W&B's banners
    (version, offline notice, history, summary, logs); W&B's warnings still show, and the
    offline run holds the record."""
    pytest.importorskip("wandb")
    from test_wandb import decoded, wandb_records

    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")}
    home = {"WANDB_DIR": "wandb-dir", "WANDB_CONFIG_DIR": "config", "NETRC": "no-netrc"}
    env.update(WANDB_MODE="offline", **{name: str(tmp_path / path) for name, path in home.items()})
    out = tmp_path / "run"
    out.mkdir()
    done = subprocess.run([sys.executable, "-c", _OFFLINE, str(out)], env=env,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    (folder,) = (out / "wandb").glob("offline-run-*")
    assert done.stderr.splitlines() == ["wandb: WARNING a warning of W&B's own"]
    assert done.stdout.splitlines() == [
        f"W&B run: {folder} (offline; upload it with: wandb sync {folder})"
    ]
    (log,) = folder.glob("run-*.wandb")
    rows = [decoded(r.history.item) for r in wandb_records(log) if r.HasField("history")]
    assert [{k: v for k, v in row.items() if not k.startswith("_")} for row in rows] == [
        {"env_steps": 64, "eval_return_mean": -3.5}
    ]
