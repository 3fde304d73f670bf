"""The run directory (``td3_jax.runner.rundir``): its lock, fresh and resumed starts, config.json.

The lock is checked with real processes (a run that holds it is frozen with SIGSTOP while a
second one tries, so the test does not depend on timing); the resume policy and the directory
checks are checked on files alone, without training; extending a finished run is compared with
the uninterrupted run, bit for bit.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from support import TINY_FLAGS, main, read_records

import td3_jax
from td3_jax.config.build import make_population, members
from td3_jax.config.schema import ConfigError, TrainConfig
from td3_jax.core.population import Member
from td3_jax.runner import finished, rundir
from td3_jax.runner import run as run_module

# tests/cli/test_cli.py's tiny run (its ring holds the extended run too).
TINY_FLAGS = [*TINY_FLAGS, "--quiet"]
VOLATILE = {"wall_time_s", "env_steps_per_s", "chunk_s", "eval_s"}
SMALL = TrainConfig(
    num_envs=4, total_steps=128, eval_every=64, batch_size=16, buffer_size=256, warmup_steps=32
)


def td3_jax_process(*args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "td3_jax", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


def error_line(err: str) -> str:
    """The one ``td3-jax: error:`` line of a refused command (and nothing else on stderr)."""
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("td3-jax: error: "), err
    return lines[0]


def snapshot(folder: Path) -> dict[str, tuple[int, bytes | None]]:
    """Every path under ``folder`` with its mtime and, for files, its bytes."""
    return {
        str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.read_bytes() if p.is_file() else None)
        for p in sorted(folder.rglob("*"))
    }


def lock_is_held(folder: Path) -> bool:
    try:
        rundir.check_not_in_use(folder)
    except ConfigError:
        return True
    return False


# --------------------------------------------------------------------------------------------
# the lock
# --------------------------------------------------------------------------------------------


@pytest.mark.subprocess
def test_a_second_run_on_a_directory_in_use_exits_2_and_writes_nothing(tmp_path):
    out = tmp_path / "run"
    first = td3_jax_process("train", *TINY_FLAGS, "--out", str(out))
    try:
        deadline = time.monotonic() + 240
        while not lock_is_held(out):
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < deadline, "the first run never locked its directory"
            time.sleep(0.05)
        os.kill(first.pid, signal.SIGSTOP)  # it keeps the lock while frozen
        before = snapshot(out)
        for args in (["--seed", "8"], ["--resume"]):
            second = td3_jax_process("train", *TINY_FLAGS, *args, "--out", str(out))
            _, err = second.communicate(timeout=240)
            assert second.returncode == 2, err
            line = error_line(err)
            assert f"{out} is in use by another td3-jax run" in line, line
            assert f"(pid {first.pid} on {socket.gethostname()})" in line, line
            assert snapshot(out) == before, "the refused run wrote into the directory"
    finally:
        os.kill(first.pid, signal.SIGCONT)
    stdout, stderr = first.communicate(timeout=240)
    assert first.returncode == 0, stderr
    assert "done: 128 env steps" in stdout
    assert [(r["env_steps"], r["seed"]) for r in read_records(out)] == [(64, 7), (128, 7)]
    assert not lock_is_held(out)  # unlocked at the end of the run


def lock_holding_process(call: str) -> subprocess.Popen:
    """A Python child that runs ``call`` (a :mod:`td3_jax.runner.rundir` function that takes a run
    directory's lock), says ``locked`` and sleeps, holding it until it is killed."""
    code = f"import time\nfrom td3_jax.runner import rundir\n{call}\nprint('locked', flush=True)\n"
    holder = subprocess.Popen([sys.executable, "-c", code + "time.sleep(600)\n"],
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert holder.stdout.readline().strip() == "locked"
    return holder


def test_the_lock_dies_with_its_process(tmp_path):
    holder = lock_holding_process(f"rundir.acquire_lock({str(tmp_path)!r})")
    try:
        with pytest.raises(ConfigError, match=rf"in use .*\(pid {holder.pid} on "):
            rundir.acquire_lock(tmp_path)
    finally:
        holder.kill()  # SIGKILL: no clean-up code runs
        holder.wait()
    lock = rundir.acquire_lock(tmp_path)  # the kernel dropped the dead process's lock
    assert json.loads((tmp_path / ".lock").read_text())["pid"] == os.getpid()
    lock.unlock()


def test_a_run_killed_while_starting_leaves_a_lock_file_that_stops_nothing(tmp_path):
    """A run SIGKILLed under its lock before it wrote anything (while compiling) leaves .lock
    naming its dead pid: the kernel dropped the lock, so eval says the run stopped before it
    trained (not that it is being started), and a fresh start takes the directory."""
    out = tmp_path / "run"
    holder = lock_holding_process(f"rundir.open_run_dir({str(out)!r}, resume=False)")
    try:
        assert lock_is_held(out)
        with pytest.raises(ConfigError, match="is being started by a td3-jax run"):
            rundir.load_config(out)
    finally:
        holder.kill()  # SIGKILL: no clean-up code runs
        holder.wait()
    assert json.loads((out / ".lock").read_text())["pid"] == holder.pid  # the file stays
    assert not lock_is_held(out)
    with pytest.raises(ConfigError, match="its run stopped before it trained"):
        rundir.load_config(out)
    with pytest.raises(ConfigError, match="run without --resume to start it"):
        rundir.check_resume(out, SMALL)
    rundir.check_fresh(out)
    lock = rundir.open_run_dir(out, resume=False)
    assert json.loads((out / ".lock").read_text())["pid"] == os.getpid()
    lock.unlock()


@pytest.mark.subprocess
def test_a_run_killed_after_a_checkpoint_resumes_despite_its_lock_file(tmp_path, capsys):
    """``td3-jax train`` SIGKILLed (no clean-up) once its first checkpoint is written: its
    .lock stays, naming the dead pid, and ``--resume`` is not refused as busy but finishes."""
    out = tmp_path / "run"
    # 50 chunks: after its first checkpoint it runs on long enough to be killed holding the lock
    first = td3_jax_process("train", *TINY_FLAGS, "--total-steps", "3200", "--out", str(out))
    deadline = time.monotonic() + 240
    try:
        while not rundir.checkpoint_steps(out):
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < deadline, "the run wrote no checkpoint"
            time.sleep(0.05)
        assert lock_is_held(out) and first.poll() is None  # killed while holding the lock
    finally:
        first.kill()
        first.communicate()
    assert json.loads((out / ".lock").read_text())["pid"] == first.pid
    # A write the kill cut short (of a step the resumed run never writes) is removed.
    unfinished = out / "checkpoints" / "999.orbax-checkpoint-tmp" / "state"
    unfinished.mkdir(parents=True)
    (unfinished / "d").write_bytes(b"cut short")
    code, stdout, err = main(["train", "--resume", "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    assert "resuming from checkpoint" in stdout and "done: 3,200 env steps" in stdout
    assert read_records(out)[-1]["env_steps"] == 3200 and not lock_is_held(out)
    assert not list((out / "checkpoints").glob("*orbax-checkpoint-tmp*"))


def test_in_one_process_the_lock_is_exclusive_until_unlocked(tmp_path):
    lock = rundir.acquire_lock(tmp_path)
    with pytest.raises(ConfigError, match="in use"):
        rundir.acquire_lock(tmp_path)
    with pytest.raises(ConfigError, match="in use"):
        rundir.check_fresh(tmp_path)
    lock.unlock()
    lock.unlock()  # (idempotent)
    rundir.check_fresh(tmp_path)  # a left-over .lock file alone is no previous run
    rundir.acquire_lock(tmp_path).unlock()


def test_reading_a_run_that_is_still_starting_says_so(tmp_path):
    with pytest.raises(ConfigError, match=r"holds no config\.json: not a td3-jax run directory"):
        rundir.load_config(tmp_path)
    lock = rundir.acquire_lock(tmp_path)  # a run between its lock and its config.json
    try:
        with pytest.raises(ConfigError, match=r"is being started by a td3-jax run \(pid "):
            rundir.load_config(tmp_path)
    finally:
        lock.unlock()
    with pytest.raises(ConfigError, match=r"holds no config\.json or checkpoint: its run stopped "
                       r"before it trained"):  # fmt: skip
        rundir.load_config(tmp_path)  # (its lock file stays behind, unlocked)
    (tmp_path / "metrics.jsonl").write_text("{}\n")  # a run's output, config.json lost: not that
    with pytest.raises(ConfigError, match=r"holds no config\.json: not a td3-jax run directory"):
        rundir.load_config(tmp_path)


def test_reading_a_run_without_a_checkpoint_says_why(tmp_path):
    """eval, render and export of a run with its config.json but no checkpoint: one that a
    run is training (it writes its first after its first chunk), or one whose run stopped
    before it (it once read "no checkpoint found")."""
    cfg = TrainConfig(env="gymnax/Pendulum-v1")
    (tmp_path / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    program = finished.run_program(tmp_path)[2]
    lock = rundir.acquire_lock(tmp_path)  # a run training, before its first checkpoint
    try:
        written = "is training it and has not written its first"
        with pytest.raises(ConfigError, match=rf"has no checkpoint yet: a td3-jax run \(pid "
                           rf"\d+ on .+\) {written}"):  # fmt: skip
            finished.restore_on_one_device(program, tmp_path)
    finally:
        lock.unlock()
    with pytest.raises(ConfigError, match=r"holds no checkpoint \(its run stopped before its "
                       r"first evaluation\), so there is no policy to read: run its td3-jax "
                       r"train command again to start it over$"):  # fmt: skip
        finished.restore_on_one_device(program, tmp_path)  # (no record: a fresh start there)
    (tmp_path / "metrics.jsonl").write_text('{"env_steps": 64}\n')  # a record, no checkpoint
    with pytest.raises(ConfigError, match=r"holds no checkpoint \(its run stopped before "
                       r"writing one, or they were removed\), so there is no policy to read: "
                       r"train it again with td3-jax train \(move it away or give another "
                       r"--out\)$"):  # fmt: skip
        finished.restore_on_one_device(program, tmp_path)


# --------------------------------------------------------------------------------------------
# what a fresh or resumed run accepts
# --------------------------------------------------------------------------------------------


def test_fresh_run_checks(tmp_path):
    out = tmp_path / "run"
    rundir.check_fresh(out)  # missing: created later, under the lock
    out.mkdir()
    rundir.check_fresh(out)  # an empty directory
    (out / "checkpoints").mkdir()  # an empty checkpoints/ is nothing to keep
    rundir.check_fresh(out)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="is a file, not a directory"):
        rundir.check_fresh(tmp_path / "file")
    (out / "metrics.jsonl").write_text("{}\n")
    with pytest.raises(ConfigError, match=r"previous run's outputs \(metrics.jsonl\)"):
        rundir.check_fresh(out)
    (out / "checkpoints" / "3").mkdir()
    with pytest.raises(ConfigError, match="already holds a run; pass --resume"):
        rundir.check_fresh(out)
    assert rundir.checkpoint_steps(out) == [3]


def test_resume_of_a_missing_directory_creates_nothing(tmp_path):
    for out in (tmp_path / "missing", tmp_path / "missing" / "deeper"):
        with pytest.raises(ConfigError, match="does not exist"):
            rundir.check_resume(out, SMALL)
        with pytest.raises(ConfigError, match="is not a td3-jax run directory"):
            rundir.check_resume(tmp_path, SMALL)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "notes.txt").write_text("a user's file")  # files of its own: not a run either
    with pytest.raises(ConfigError, match=r"is not a td3-jax run directory \(it holds none"):
        rundir.check_resume(tmp_path, SMALL)


def test_a_run_stopped_before_its_first_checkpoint_starts_again_fresh(tmp_path):
    """What such a run leaves (its lock file, no longer held, an empty checkpoints folder;
    config.json and an empty metrics.jsonl where it ended before its first record): --resume
    refuses, saying to start without it, and a fresh start is accepted."""
    rundir.acquire_lock(tmp_path).unlock()
    (tmp_path / "checkpoints").mkdir()
    for name, text in (("", ""), ("config.json", "{}"), ("metrics.jsonl", "")):
        if name:
            (tmp_path / name).write_text(text)
        with pytest.raises(ConfigError, match="run without --resume to start it"):
            rundir.check_resume(tmp_path, SMALL)
        rundir.check_fresh(tmp_path)
    # A run with records but no checkpoint (stopped after its first evaluation, or its
    # checkpoints deleted) is not resumed: the command that started it starts it over
    # (test_a_run_stopped_before_its_first_checkpoint_starts_over_with_the_same_settings).
    (tmp_path / "metrics.jsonl").write_text('{"env_steps": 64}\n')
    with pytest.raises(ConfigError) as refused:
        rundir.check_resume(tmp_path, SMALL)
    assert str(refused.value).endswith(
        "checkpoints has no checkpoint (it holds a run's outputs but no checkpoint: move it "
        "away or choose another --out to train again, unless its run stopped in its first "
        "chunk: then the command that started it, without --resume, starts it over)"
    )
    with pytest.raises(ConfigError, match="previous run's outputs"):
        rundir.check_fresh(tmp_path)
    (tmp_path / "metrics.jsonl").write_text("")  # no record, but a curve (or a file of others)
    for name in ("curve.png", "notes.txt"):
        (tmp_path / name).write_text("x")
        with pytest.raises(ConfigError, match=r"previous run's outputs|directory of other files"):
            rundir.check_fresh(tmp_path)
        (tmp_path / name).unlink()
    rundir.check_fresh(tmp_path)


def test_a_run_killed_before_its_first_record_starts_over_with_the_same_call(tmp_path):
    """A run SIGKILLed (kill -9, the kernel's out-of-memory killer) after it wrote config.json,
    members.json, an empty metrics.jsonl and TensorBoard's file, before its first evaluation:
    once its lock died with it, the same call trains there from the start (it used to be
    refused as "a previous run's outputs ... but no checkpoint to resume"); while a live
    process holds the lock, it is refused as in use."""
    out = tmp_path / "run"
    cfg = dataclasses.replace(SMALL, hidden_sizes=(8,))
    holder = lock_holding_process(
        "import dataclasses\nfrom td3_jax.config.build import members\n"
        "from td3_jax.config.schema import TrainConfig\nfrom td3_jax.runner.logger import "
        f"MetricsLogger\ncfg = TrainConfig(**{dataclasses.asdict(cfg)!r})\n"
        f"lock = rundir.open_run_dir({str(out)!r}, resume=False)\n"
        f"rundir.save_config(cfg, members(cfg), lock.path.parent)\n"
        "MetricsLogger(lock.path.parent, 0)"
    )
    try:
        with pytest.raises(ConfigError, match="in use by another td3-jax run"):
            rundir.check_fresh(out)
    finally:
        holder.kill()  # SIGKILL: no clean-up code runs
        holder.wait()
    left = sorted(p.name for p in out.iterdir())
    assert left == [".lock", "config.json", "members.json", "metrics.jsonl", "tensorboard"]
    assert (out / "metrics.jsonl").stat().st_size == 0 and rundir.checkpoint_steps(out) == []
    rundir.check_fresh(out)
    with pytest.raises(ConfigError, match="run without --resume to start it"):
        rundir.check_resume(out, cfg)
    assert [r["env_steps"] for r in run_module.train(cfg, out, progress=False)] == [64, 128]
    assert [r["env_steps"] for r in read_records(out)] == [64, 128]
    assert rundir.checkpoint_steps(out) == [1, 2]


def test_a_damaged_or_edited_members_json_is_refused_in_one_line(tmp_path):
    """members.json is read back as written (a sweep's overrides included), or refused where
    it is no list of members or names members config.json does not (it once gave tracebacks,
    and a changed seed labelled the member wrongly); deleted, config.json's seeds stand."""
    sweep = {"actor_lr": [1e-3, 3e-4]}
    population = members(dataclasses.replace(SMALL, seeds=2, seed=7), sweep)
    rundir.save_config(dataclasses.replace(SMALL, seeds=2, seed=7), population, tmp_path)
    assert rundir.load_members(tmp_path, SMALL) == population
    assert {m.seed for m in population} == {7, 8} and len(population) == 4
    path = tmp_path / "members.json"
    listing = json.loads(path.read_text())
    bad = ("[]", "{", '[{"seed": "a", "overrides": {}}]', '[{"seed": 7}]',
           '[{"seed": 7, "overrides": {"actor_lr": "fast"}}]')  # fmt: skip
    for text in bad:
        path.write_text(text)
        with pytest.raises(ConfigError, match=r"members.json is not (valid JSON|a list of)"):
            rundir.load_members(tmp_path, SMALL)
    listing[1]["seed"] = 9
    path.write_text(json.dumps(listing))
    with pytest.raises(ConfigError, match=r"seeds 7, 9, 7, 8 but config.json says the run trained "
                       "seeds 7, 8, 7, 8"):  # fmt: skip
        rundir.load_members(tmp_path, SMALL)
    one = tmp_path / "one"
    one.mkdir()
    rundir.save_config(SMALL, [Member(seed=0)], one)
    (one / "members.json").write_text('[{"seed": 3, "overrides": {}}]')
    with pytest.raises(ConfigError, match=r"seeds 3 but config.json says the run trained seeds 0"):
        rundir.load_members(one, SMALL)
    (one / "members.json").unlink()
    assert rundir.load_members(one, SMALL) == [Member(seed=0)]


def test_a_resume_shorter_than_its_run_is_told_so_before_the_warm_up_check(tmp_path, capsys):
    """--resume --total-steps 16 of a run 128 steps in (its warm-up 32 steps): the one line
    says the run has taken 128 steps; the warm-up check's advice (a smaller --warmup-steps)
    is not what a resume can follow. The same from ``td3_jax.train``, in its argument names."""
    cfg = dataclasses.replace(SMALL, env="gymnax/Pendulum-v1")
    rundir.save_config(cfg, [Member(seed=0)], tmp_path)
    (tmp_path / "checkpoints" / "2").mkdir(parents=True)  # 2 chunks of 64 steps done
    code, _, err = main(["train", "--out", str(tmp_path), "--resume", "--total-steps", "16"],
                        capsys)  # fmt: skip
    assert code == 2 and err.strip() == (
        f"td3-jax: error: --total-steps 16 is less than the 128 env steps the run in {tmp_path} "
        "has already taken (give more to extend it)"
    )
    shorter = dataclasses.replace(cfg, total_steps=16)
    with pytest.raises(ConfigError, match=r"^total_steps=16 is less than the 128 env steps"):
        td3_jax.train(shorter, out_dir=tmp_path, resume=True, progress=False)
    # a setting the check cannot count with is left to the config's own line
    with pytest.raises(ConfigError, match=r"^num_envs must be positive, got 0$"):
        td3_jax.train(dataclasses.replace(cfg, num_envs=0), out_dir=tmp_path, resume=True,
                      progress=False)  # fmt: skip


def test_resume_checks_sweep_values_and_the_steps_already_taken(tmp_path):
    sweep = {"actor_lr": [1e-3, 3e-4]}
    population = members(SMALL, sweep)
    rundir.save_config(SMALL, population, tmp_path)
    (tmp_path / "checkpoints" / "2").mkdir(parents=True)  # 2 chunks of 64 steps done
    assert rundir.check_resume(tmp_path, SMALL) == (population, {})
    assert rundir.check_resume(tmp_path, SMALL, sweep) == (population, {})
    with pytest.raises(ConfigError) as refused:  # (both the given and the run's values said)
        rundir.check_resume(tmp_path, SMALL, {"actor_lr": [1e-3, 1e-4], "tau": [0.01]})
    assert str(refused.value).startswith(
        "the --sweep-* values (--sweep-actor-lr 0.001 0.0001 --sweep-tau 0.01) differ from the "
        f"members of the run in {tmp_path} (--sweep-actor-lr 0.001 0.0003, members.json); "
    )
    longer = dataclasses.replace(SMALL, total_steps=512)
    assert rundir.check_resume(tmp_path, longer)[1] == {"total_steps": [128, 512]}
    with pytest.raises(ConfigError, match="--total-steps 64 is less than the 128 env steps"):
        rundir.check_resume(tmp_path, dataclasses.replace(SMALL, total_steps=64))


def test_open_run_dir_reports_a_directory_it_cannot_create(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    for out in (tmp_path / "file" / "run", Path("/proc/td3-jax-run")):
        with pytest.raises(ConfigError, match=r"^--out .*: cannot create it"):
            rundir.open_run_dir(out, resume=False)
    # the check before the environment is made: a read-only file system says so (it read
    # "Permission denied", where mkdir says "Read-only file system")
    monkeypatch.setattr(rundir.os, "statvfs", lambda path: SimpleNamespace(f_flag=os.ST_RDONLY))
    with pytest.raises(ConfigError, match=r"cannot create it \(Read-only file system\)"):
        rundir.check_fresh(tmp_path / "run")


def test_safe_settings_may_change_on_resume():
    changed = dataclasses.replace(SMALL, total_steps=512, keep_checkpoints=5, eval_envs=4,
                                  matmuls="cublas")  # fmt: skip
    assert rundir.config_changes(SMALL, changed) == {
        "total_steps": [128, 512],
        "eval_envs": [16, 4],
        "keep_checkpoints": [3, 5],
        "matmuls": ["auto", "cublas"],
    }
    assert rundir.config_changes(SMALL, SMALL) == {}
    # the value a None stands for is the same value
    td3_default = dataclasses.replace(SMALL, tau=0.005, actor_lr=1e-3, ou_min_sigma=0.3)
    assert rundir.config_changes(SMALL, td3_default) == {}


@pytest.mark.parametrize(
    "changes, needles",
    [
        (dict(eval_every=32), ["--eval-every 32 given", "started with --eval-every 64", "chunk"]),
        (dict(seed=3), ["--seed 3 given", "--seed 0"]),
        (dict(seeds=2), ["--seeds 2 given", "--seeds 1"]),
        (dict(batch_size=8), ["--batch-size 8 given", "--batch-size 16"]),
        (dict(hidden_sizes=(8, 8)), ["--hidden-sizes 8 8 given", "--hidden-sizes 256 256"]),
        (dict(normalize_obs=False), ["--no-normalize-obs given", "with --normalize-obs"]),
        # left to the algorithm (None): the value the run used, TD3's 1e-3
        (
            dict(actor_lr=3e-4),
            ["--actor-lr 0.0003 given", "started with --actor-lr 0.001", "not be reproducible"],
        ),
        (dict(tau=0.01), ["--tau 0.01 given", "started with --tau 0.005"]),
        (
            dict(actor_hidden_sizes=(8,)),
            ["--actor-hidden-sizes 8 given", "started with --actor-hidden-sizes 256 256"],
        ),
        (dict(max_grad_norm=1.0), ["--max-grad-norm 1.0 given", "started with no --max-grad-norm"]),
        (dict(discount=0.9), ["--discount 0.9 given", "--discount 0.99", "reproducible"]),
        (dict(env="brax/ant"), ["--env brax/ant given", "--env gymnax/Pendulum-v1"]),
    ],
)
def test_structural_settings_cannot_change_on_resume(changes, needles):
    with pytest.raises(ConfigError) as err:
        rundir.config_changes(SMALL, dataclasses.replace(SMALL, **changes))
    message = str(err.value)
    assert "\n" not in message and "None" not in message
    for needle in [*needles, "leave it out to resume", "--total-steps"]:
        assert needle in message, (needle, message)


def test_config_json_keeps_its_extra_keys_and_loads(tmp_path):
    population = [Member(seed=0), Member(seed=1)]
    two = dataclasses.replace(SMALL, seeds=2)
    rundir.save_config(two, population, tmp_path, {"preset": "pendulum"})
    # the settings SMALL leaves to TD3 come back as TD3's values (Adam 1e-3, tau 0.005)
    used = dataclasses.replace(two, actor_lr=1e-3, critic_lr=1e-3, tau=0.005)
    assert rundir.load_config(tmp_path) == used
    assert rundir.load_members(tmp_path, SMALL) == population
    assert rundir.load_run_info(tmp_path) == {"preset": "pendulum"}
    info = rundir.run_info(
        tmp_path, resume=True, preset=None, changes={"total_steps": [128, 256]}, at_env_steps=128
    )
    assert info == {
        "preset": "pendulum",
        "resume_changes": [{"at_env_steps": 128, "total_steps": [128, 256]}],
    }
    rundir.save_config(dataclasses.replace(two, total_steps=256), population, tmp_path, info)
    assert rundir.load_config(tmp_path).total_steps == 256
    assert rundir.load_run_info(tmp_path) == info
    assert not list(tmp_path.glob("*.tmp"))
    assert rundir.run_info(tmp_path, resume=False, preset=None, changes={}, at_env_steps=0) == {}


@pytest.mark.parametrize(
    ("name", "value", "expected"),
    [("num_envs", "4", "an integer"), ("seed", True, "an integer"),
     ("algo", None, 'one of "td3", "ddpg"'), ("impl", "cuda", 'one of "warp", "jax" or null'),
     ("hidden_sizes", [1.5], "a list of integers or null"), ("expl_noise", "0.1", "a number"),
     ("total_steps", 1000.5, "an integer")],
)  # fmt: skip
def test_a_hand_edited_setting_of_the_wrong_type_is_one_line_naming_it(
    tmp_path, name, value, expected
):
    """Every setting config.json writes reads back (a whole float for an integer too, as a
    config made in Python with ``total_steps=1e6`` writes); one edited to another JSON type
    is a ConfigError naming the setting, its value and the type, not a traceback later."""
    rundir.save_config(dataclasses.replace(SMALL, total_steps=1e3), [Member(seed=0)], tmp_path, {})
    assert rundir.load_config(tmp_path).total_steps == 1000
    path = tmp_path / "config.json"
    raw = json.loads(path.read_text())
    raw[name] = value
    path.write_text(json.dumps(raw))
    with pytest.raises(ConfigError) as refused:
        rundir.load_config(tmp_path)
    assert str(refused.value) == (f"{path}: {name} is {json.dumps(value)} (expected {expected}); "
                                  "was the file edited? Restore its value")  # fmt: skip


def test_a_checkpoint_folder_given_for_its_run_names_the_run(tmp_path, monkeypatch):
    """``eval --run runs/x/checkpoints/3`` (or ``.../checkpoints``): the error names runs/x,
    as given (relative stays relative); a folder under no run gets no such hint."""
    run = tmp_path / "x"
    (run / "checkpoints" / "3").mkdir(parents=True)
    rundir.save_config(SMALL, [Member(seed=0)], run, {})
    monkeypatch.chdir(tmp_path)
    for given, shown in [(run / "checkpoints" / "3", run), (Path("x/checkpoints"), "x")]:
        with pytest.raises(ConfigError) as refused:
            rundir.load_config(given)
        hint = f"not a td3-jax run directory (its run is {shown}: give that folder)"
        assert str(refused.value) == f"{given} holds no config.json: {hint}"
    (tmp_path / "other").mkdir()
    with pytest.raises(ConfigError, match=r"not a td3-jax run directory$"):
        rundir.load_config(tmp_path / "other")


def test_a_checkpoint_keeps_the_fixed_settings_so_an_edited_config_json_is_noticed(tmp_path):
    """fixed_settings is config.json's record less what a resume may change; check_unedited
    refuses a setting that differs from the recorded one (naming both), lets the settings a
    resume may change and checkpoints from before the record (no dict) through."""
    recorded = rundir.fixed_settings(SMALL)
    assert "total_steps" not in recorded and "keep_checkpoints" not in recorded
    assert recorded["discount"] == SMALL.discount and recorded["actor_lr"] == 1e-3  # (TD3's)
    assert recorded["hidden_sizes"] == list(SMALL.hidden_sizes)  # (as JSON has it)
    path = tmp_path / "config.json"
    rundir.check_unedited(recorded, dataclasses.replace(SMALL, total_steps=10**6), path)
    rundir.check_unedited(None, dataclasses.replace(SMALL, discount=0.5), path)
    rundir.check_unedited(recorded, dataclasses.replace(SMALL, actor_lr=1e-3), path)  # (same)
    with pytest.raises(ConfigError) as refused:
        rundir.check_unedited(recorded, dataclasses.replace(SMALL, discount=0.5), path)
    assert str(refused.value) == (f"{path}: discount is 0.5 but the run's checkpoints were "
                                  f"written with {SMALL.discount}; was the file edited? Restore "
                                  "its value")  # fmt: skip


def test_a_resume_refuses_a_config_json_edited_since_its_checkpoint(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", *TINY_FLAGS, "--out", str(out), "--quiet"], capsys)[0] == 0
    path = out / "config.json"
    saved = path.read_text()
    path.write_text(saved.replace('"discount": 0.99', '"discount": 0.5'))
    code, _, err = main(["train", "--out", str(out), "--resume", "--total-steps", "192",
                         "--quiet"], capsys)  # fmt: skip
    assert code == 2 and "discount is 0.5 but the run's checkpoints were written with 0.99" in err
    assert len(read_records(out)) == 2  # (nothing trained with the edited setting)
    # eval and export read the run the same way: refused too (they used the edited file).
    for command in (["eval", "--run", str(out), "--episodes", "2"],
                    ["export", "--run", str(out), "--format", "npz"]):  # fmt: skip
        code, _, err = main(command, capsys)
        assert code == 2 and "discount is 0.5 but the run's checkpoints were written" in err, err
    # A size or the environment edited: named as the setting, not as the arrays it changes
    # (".env_state...: saved [1, 4] int32, expected [1, 2] int32").
    edits = [('"num_envs": 4', '"num_envs": 2', 'num_envs is 2 but the run\'s checkpoints were '
              'written with 4;'),
             ('"env": "gymnax/Pendulum-v1"', '"env": "gymnax/MountainCarContinuous-v0"',
              'env is "gymnax/MountainCarContinuous-v0" but the run\'s checkpoints were written '
              'with "gymnax/Pendulum-v1";')]  # fmt: skip
    for old, new, said in edits:
        path.write_text(saved.replace(old, new))
        for command in (["train", "--out", str(out), "--resume", "--total-steps", "192"],
                        ["eval", "--run", str(out), "--episodes", "2"],
                        ["export", "--run", str(out), "--format", "npz"]):  # fmt: skip
            code, _, err = main(command, capsys)
            assert code == 2 and err.strip() == f"td3-jax: error: {path}: {said} was the file " \
                "edited? Restore its value", err  # fmt: skip
    path.write_text(saved)
    assert main(["train", "--out", str(out), "--resume", "--total-steps", "192", "--quiet"],
                capsys)[0] == 0  # fmt: skip
    assert [r["env_steps"] for r in read_records(out)] == [64, 128, 192]


def test_a_damaged_newest_record_falls_back_for_resume_eval_and_export(tmp_path, capsys):
    """One byte of the newest checkpoint's record changed ("float32" to "float22", its
    precision setting): eval, export and --resume use the checkpoint before it, with one
    warning naming the damaged one; none says config.json (intact) was edited. The resume
    continues from env step 64 and repeats the first run's record at 128 exactly."""
    out = tmp_path / "run"
    assert main(["train", *TINY_FLAGS, "--out", str(out)], capsys)[0] == 0
    first = read_records(out)
    record = out / "checkpoints" / "2" / "meta" / "metadata"
    text = record.read_text()
    assert text.count('"precision": "float32"') == 1
    record.write_text(text.replace('"precision": "float32"', '"precision": "float22"'))
    newest, before = out / "checkpoints" / "2", out / "checkpoints" / "1"
    warning = (f"td3-jax: warning: checkpoint {newest} is corrupt (its metadata fails its "
               f"checksum); using checkpoint {before}")  # fmt: skip
    for command in (["eval", "--run", str(out), "--episodes", "2"],
                    ["export", "--run", str(out), "--format", "npz"]):  # fmt: skip
        code, _, err = main(command, capsys)
        assert code == 0 and err.strip().splitlines() == [warning], err
    code, stdout, err = main(["train", "--out", str(out), "--resume", "--total-steps", "192"],
                             capsys)  # fmt: skip
    assert code == 0 and err.strip().splitlines() == [warning], err
    assert f"resuming from checkpoint {out / 'checkpoints' / '1'} (env step 64)" in stdout
    records = read_records(out)
    assert [r["env_steps"] for r in records] == [64, 128, 192]
    same = lambda r: {k: v for k, v in r.items() if k not in VOLATILE}
    assert same(records[1]) == same(first[1])  # (the same numbers, trained again from 64)


#: SMALL as config.json records it (the settings it leaves to TD3 as TD3's values).
SMALL_AS_USED = dataclasses.replace(SMALL, actor_lr=1e-3, critic_lr=1e-3, tau=0.005)
#: A sweep of two actor learning rates and one tau, two seeds each.
SWEEP = {"actor_lr": [3e-4, 1e-3], "tau": [0.01]}


def test_a_sweeps_config_json_states_what_each_member_trained_with(tmp_path):
    """config.json used to hold SMALL's actor_lr 0.001 and tau 0.005 for a sweep whose members
    trained with 0.0003/0.001 and 0.01: it now lists the swept values, and a ``sweep`` section
    names each member's; the run's configuration still loads (and resumes) as it was."""
    cfg = dataclasses.replace(SMALL, seeds=2)
    population = members(cfg, SWEEP)
    rundir.save_config(cfg, population, tmp_path, {"preset": "pendulum"})
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["actor_lr"] == [3e-4, 1e-3] and saved["tau"] == [0.01]
    assert saved["critic_lr"] == 1e-3  # not swept: the one value every member trained with
    assert saved["sweep"] == {
        "settings": ["actor_lr", "tau"],
        "base": {"actor_lr": 1e-3, "tau": 0.005},
        "members": [
            {"seed": 0, "actor_lr": 3e-4, "tau": 0.01},
            {"seed": 1, "actor_lr": 3e-4, "tau": 0.01},
            {"seed": 0, "actor_lr": 1e-3, "tau": 0.01},
            {"seed": 1, "actor_lr": 1e-3, "tau": 0.01},
        ],
    }
    assert saved["preset"] == "pendulum"
    used = dataclasses.replace(SMALL_AS_USED, seeds=2)
    assert rundir.load_config(tmp_path) == used
    assert rundir.load_members(tmp_path, used) == population
    (tmp_path / "checkpoints" / "2").mkdir(parents=True)
    assert rundir.check_resume(tmp_path, used, SWEEP) == (population, {})
    longer = dataclasses.replace(used, total_steps=256)
    info = rundir.run_info(tmp_path, resume=True, preset=None, changes={"total_steps": [128, 256]},
                           at_env_steps=128)  # fmt: skip
    rundir.save_config(longer, population, tmp_path, info)  # as a resume writes it again
    resumed = json.loads((tmp_path / "config.json").read_text())
    assert {k: v for k, v in resumed.items() if k not in ("total_steps", "resume_changes")} == {
        k: v for k, v in saved.items() if k != "total_steps"
    }
    assert rundir.load_config(tmp_path) == longer


def test_a_single_or_seeds_only_run_has_no_sweep_section(tmp_path):
    rundir.save_config(SMALL, members(dataclasses.replace(SMALL, seeds=3)), tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    assert "sweep" not in saved and saved["actor_lr"] == 1e-3 and saved["tau"] == 0.005


def test_a_sweep_written_before_the_sweep_section_still_loads_and_resumes(tmp_path):
    """Older sweeps' config.json held the configuration's values of the swept settings."""
    population = members(SMALL, SWEEP)
    rundir.save_config(SMALL, population, tmp_path)
    old = json.loads((tmp_path / "config.json").read_text())
    old.update(old.pop("sweep")["base"])
    (tmp_path / "config.json").write_text(json.dumps(old))
    (tmp_path / "checkpoints" / "2").mkdir(parents=True)
    assert rundir.load_config(tmp_path) == SMALL_AS_USED
    assert rundir.check_resume(tmp_path, SMALL_AS_USED) == (population, {})


def test_a_changed_swept_setting_on_resume_names_the_swept_values(tmp_path):
    """The refusal said 'the run was started with --tau 0.005', a value no member used."""
    rundir.save_config(SMALL, members(SMALL, SWEEP), tmp_path)
    (tmp_path / "checkpoints" / "2").mkdir(parents=True)
    for name, given, used in (("tau", 0.02, "--sweep-tau 0.01"),
                              ("actor_lr", 0.1, "--sweep-actor-lr 0.0003 0.001")):  # fmt: skip
        with pytest.raises(ConfigError) as refused:
            rundir.check_resume(tmp_path, dataclasses.replace(SMALL_AS_USED, **{name: given}))
        assert f"given but the run was started with {used}: " in str(refused.value)
    with pytest.raises(ConfigError, match=r"started with --critic-lr 0\.001: "):  # not swept
        rundir.check_resume(tmp_path, dataclasses.replace(SMALL_AS_USED, critic_lr=0.1))


def test_a_sweep_section_without_its_base_values_is_one_line(tmp_path):
    rundir.save_config(SMALL, members(SMALL, SWEEP), tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    for section in ({"settings": ["tau"]}, [1, 2]):
        (tmp_path / "config.json").write_text(json.dumps({**saved, "sweep": section}))
        with pytest.raises(ConfigError, match=r"config\.json: its 'sweep' section has no 'base'"):
            rundir.load_config(tmp_path)


def test_interrupted_message_says_what_is_kept(tmp_path):
    missing = tmp_path / "not-made"  # (stopped before the run made its directory)
    assert rundir.interrupted_message(missing) == (
        f"interrupted before the run wrote anything to {missing} (run the same command again)"
    )
    message = rundir.interrupted_message(tmp_path)
    assert "before the first checkpoint" in message and "run the same command again" in message
    (tmp_path / "metrics.jsonl").write_text('{"env_steps": 8}\n')  # records, no checkpoint
    message = rundir.interrupted_message(tmp_path)
    assert "holds none to resume (run the same command again to start over)" in message
    (tmp_path / "checkpoints" / "2").mkdir(parents=True)
    message = rundir.interrupted_message(tmp_path)
    assert str(tmp_path / "checkpoints" / "2") in message and "--resume" in message
    # 2 chunks of 8 steps were the whole run: nothing to resume
    cfg = TrainConfig(env="gymnax/Pendulum-v1", num_envs=2, total_steps=16, eval_every=8)
    assert cfg.num_chunks == 2
    rundir.save_config(cfg, [Member(seed=0)], tmp_path)
    message = rundir.interrupted_message(tmp_path, "terminated (SIGTERM)")
    assert message == ("terminated (SIGTERM) after the run's last chunk: the run is complete "
                       f"({tmp_path / 'checkpoints' / '2'})")  # fmt: skip


def test_a_stopped_sweep_is_told_to_resume_as_a_sweep(tmp_path):
    """A sweep's directory (config.json with its 'sweep' section) is continued with `td3-jax
    sweep --resume`, which ends with the sweep's ranking; a run of seeds with `td3-jax train`."""
    cfg = TrainConfig(env="gymnax/Pendulum-v1", num_envs=2, total_steps=32, eval_every=8)
    (tmp_path / "checkpoints" / "2").mkdir(parents=True)
    rundir.save_config(cfg, [Member(seed=0), Member(seed=1)], tmp_path)
    assert rundir.interrupted_message(tmp_path).endswith(
        f"(continue with: td3-jax train --out {tmp_path} --resume)")  # fmt: skip
    swept = [Member(0, (("tau", 0.005),)), Member(0, (("tau", 0.01),))]
    rundir.save_config(cfg, swept, tmp_path)
    assert rundir.SWEEP in json.loads((tmp_path / "config.json").read_text())
    assert rundir.interrupted_message(tmp_path).endswith(
        f"(continue with: td3-jax sweep --out {tmp_path} --resume)")  # fmt: skip


# --------------------------------------------------------------------------------------------
# extending a finished run
# --------------------------------------------------------------------------------------------


@pytest.mark.runs
def test_a_finished_run_extended_equals_the_longer_run(tmp_path, capsys):
    short, long = tmp_path / "short", tmp_path / "long"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(short)], capsys)
    assert code == 0, err
    code, out, err = main(
        ["train", "--resume", "--total-steps", "256", "--out", str(short), "--quiet"], capsys
    )
    assert code == 0, err
    assert f"resuming from checkpoint {short / 'checkpoints' / '2'} (env step 128)\n" in out
    code, _, err = main(["train", *TINY_FLAGS, "--total-steps", "256", "--out", str(long)], capsys)
    assert code == 0, err

    strip = lambda rs: [{k: v for k, v in r.items() if k not in VOLATILE} for r in rs]
    assert [r["env_steps"] for r in read_records(short)] == [64, 128, 192, 256]
    assert strip(read_records(short)) == strip(read_records(long))

    config = json.loads((short / "config.json").read_text())
    assert config["total_steps"] == 256
    assert config["resume_changes"] == [{"at_env_steps": 128, "total_steps": [128, 256]}]
    assert rundir.load_config(short) == rundir.load_config(long)

    cfg = rundir.load_config(long)
    program = make_population(cfg, members(cfg))
    state_short, meta_short, step_short = finished.restore_state(program, short)
    state_long, meta_long, step_long = finished.restore_state(program, long)
    assert step_short == step_long == 4 and meta_short["env_steps"] == meta_long["env_steps"]
    leaves = jax.tree_util.tree_leaves_with_path(state_long)
    for (path, a), b in zip(leaves, jax.tree.leaves(state_short), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), jax.tree_util.keystr(path)


@pytest.mark.runs
def test_an_interrupted_run_shortened_on_resume_equals_the_shorter_run(tmp_path, capsys):
    """The replay ring is sized to the run, so a run shortened by ``--resume --total-steps``
    restores a larger ring than its own: it is cut to the new run's rows (every step taken so
    far fits), and the run then equals one started that short."""
    cut, short = tmp_path / "cut", tmp_path / "short"
    code, _, err = main(["train", *TINY_FLAGS, "--total-steps", "256", "--out", str(cut)], capsys)
    assert code == 0, err
    for chunk in (3, 4):  # as if stopped after the second chunk's checkpoint
        shutil.rmtree(cut / "checkpoints" / str(chunk))
    kept = [line for line in (cut / "metrics.jsonl").read_text().splitlines()
            if json.loads(line)["env_steps"] <= 128]  # fmt: skip
    (cut / "metrics.jsonl").write_text("\n".join(kept) + "\n")
    code, out, err = main(["train", "--resume", "--total-steps", "192", "--out", str(cut),
                           "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert f"resuming from checkpoint {cut / 'checkpoints' / '2'} (env step 128)" in out
    code, _, err = main(["train", *TINY_FLAGS, "--total-steps", "192", "--out", str(short)], capsys)
    assert code == 0, err
    strip = lambda rs: [{k: v for k, v in r.items() if k not in VOLATILE} for r in rs]
    assert [r["env_steps"] for r in read_records(cut)] == [64, 128, 192]
    assert strip(read_records(cut)) == strip(read_records(short))


def test_a_directory_of_other_files_is_refused(tmp_path, capsys):
    """``--out ~`` or ``--out /`` used to train into the directory, among the user's files."""
    (tmp_path / "thesis.tex").write_text("mine\n")
    (tmp_path / "data").mkdir()
    code, _, err = main(["train", "--out", str(tmp_path), "--quiet"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "a directory of other files (data, thesis.tex)" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "thesis.tex"]


# --------------------------------------------------------------------------------------------
# checkpoints written in the background, and the disk they need
# --------------------------------------------------------------------------------------------


def test_a_background_checkpoint_that_fails_stops_the_run_with_its_records_kept(
    tmp_path, capsys, monkeypatch
):
    """Checkpoint 2 is written while chunk 3 runs; its failure (a full disk) stops the run at
    the next save with one error line naming the last good checkpoint and how to go on, and
    every chunk's record stays in metrics.jsonl."""
    import builtins
    import errno

    out = tmp_path / "run"
    failing = str(out / "checkpoints" / "2")
    real_open = builtins.open

    def open_(file, mode="r", *args, **kwargs):
        if str(file).startswith(failing) and any(flag in mode for flag in "wax+"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", open_)
    code, _, err = main(["train", *TINY_FLAGS, "--total-steps", "192", "--out", str(out)],
                           capsys)  # fmt: skip
    monkeypatch.undo()
    assert code == 2
    assert error_line(err) == (
        f"td3-jax: error: could not write checkpoint {out / 'checkpoints' / '2'}: no space left "
        f"on the disk holding {out / 'checkpoints'}; the last good checkpoint is "
        f"{out / 'checkpoints' / '1'} (env step 64); free space on the disk holding {out}, then "
        f"continue with: td3-jax train --out {out} --resume"
    )
    assert [r["env_steps"] for r in read_records(out)][-1] == 192
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["1"]


def test_a_run_whose_checkpoints_cannot_fit_is_refused_before_training(
    tmp_path, capsys, monkeypatch
):
    import shutil

    from td3_jax.runner import checkpoint

    usage = shutil.disk_usage(tmp_path)._replace(free=1000)
    monkeypatch.setattr(checkpoint.shutil, "disk_usage", lambda path: usage)
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    assert code == 2
    line = error_line(err)
    assert f"the disk holding {out / 'checkpoints'} has 0.0 MB free" in line
    assert "(3 kept and one being written" in line
    # (TINY_FLAGS' 16-wide networks with Adam's moments outweigh its 256 ring rows)
    assert "use smaller --critic-hidden-sizes" in line and "--buffer-size" not in line
    assert "--keep-checkpoints 1" not in line  # (1000 bytes hold no checkpoint of this run)
    assert not (out / "metrics.jsonl").exists()


def test_a_last_metrics_line_cut_short_is_left_out_and_the_run_resumes(tmp_path, capsys):
    """A run killed (or a disk filled) while appending to metrics.jsonl leaves half a line:
    reading it warns and leaves it out; the resume rewrites the file without it."""
    from td3_jax.runner.logger import read_metrics

    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    assert code == 0, err
    metrics = out / "metrics.jsonl"
    whole = read_records(out)
    metrics.write_text(metrics.read_text() + '{"env_steps": 192, "eval_ret')
    assert read_metrics(metrics) == whole
    assert "the last line of" in capsys.readouterr().err
    code, _, err = main(
        ["train", "--resume", "--total-steps", "256", "--out", str(out), "--quiet"], capsys
    )
    assert code == 0, err
    assert err.count("warning") == 1 and f"the last line of {metrics} is incomplete" in err
    assert [r["env_steps"] for r in read_records(out)] == [64, 128, 192, 256]
    # A broken line before the last is not guessed at: one line, exit 2.
    lines = metrics.read_text().splitlines()
    metrics.write_text("\n".join([lines[0], "{oops", *lines[1:]]) + "\n")
    code, _, err = main(["plot", "--run", str(out)], capsys)
    assert code == 2 and "line 2 of" in error_line(err)


def _fill_the_disk_at(monkeypatch, env_steps: int) -> None:
    """The disk fills while metrics.jsonl gets the record of ``env_steps``: half of its line
    is written, then the write stops short (as os.write does on a full disk)."""
    from td3_jax.runner import logger

    real_write = os.write

    def write(fd, data):
        if data.startswith(b'{"env": ') and f'"env_steps": {env_steps},'.encode() in data:
            return real_write(fd, data[: len(data) // 2])
        return real_write(fd, data)

    monkeypatch.setattr(logger.os, "write", write)


def test_a_full_disk_while_logging_ends_on_one_line_that_says_how_to_go_on(
    tmp_path, capsys, monkeypatch
):
    """The last line names the file, the last good checkpoint (one written in the background
    while the failing chunk ran is finished first) and the resume command; metrics.jsonl keeps
    whole records only; nothing suggests td3-jax plot; the resume, with room again, completes."""
    out = tmp_path / "run"
    _fill_the_disk_at(monkeypatch, 128)
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    monkeypatch.undo()
    assert code == 2 and "Traceback" not in err and "td3-jax plot" not in err, err
    assert err.strip().splitlines()[-1] == (
        f"td3-jax: error: could not write {out / 'metrics.jsonl'}: {os.strerror(errno.ENOSPC)}; "
        f"the last good checkpoint is {out / 'checkpoints' / '1'} (env step 64); free space on "
        f"the disk holding {out}, then continue with: td3-jax train --out {out} --resume"
    )
    assert (out / "metrics.jsonl").read_text().endswith("}\n")  # no part of the failed record
    assert [r["env_steps"] for r in read_records(out)] == [64]
    code, stdout, err = main(["train", "--resume", "--out", str(out)], capsys)
    assert code == 0, err
    assert f"resuming from checkpoint {out / 'checkpoints' / '1'} (env step 64)" in stdout
    assert [r["env_steps"] for r in read_records(out)] == [64, 128]


def test_a_full_disk_before_the_first_checkpoint_says_to_remove_the_directory(
    tmp_path, capsys, monkeypatch
):
    out = tmp_path / "run"
    _fill_the_disk_at(monkeypatch, 64)
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    monkeypatch.undo()
    assert code == 2 and "td3-jax plot" not in err, err
    assert err.strip().splitlines()[-1] == (
        f"td3-jax: error: could not write {out / 'metrics.jsonl'}: {os.strerror(errno.ENOSPC)}; "
        f"no checkpoint was written, so there is nothing to resume: free space on the disk "
        f"holding {out}, then remove {out} (or choose another --out) and start the run again"
    )
    assert (out / "metrics.jsonl").read_text() == ""


def test_a_full_disk_when_writing_config_json_is_one_line_and_leaves_no_temporary_file(
    tmp_path, capsys, monkeypatch
):
    import errno
    from pathlib import Path as _Path

    real_write_text = _Path.write_text

    def write_text(self, *args, **kwargs):
        if self.name == "config.json.tmp":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return real_write_text(self, *args, **kwargs)

    monkeypatch.setattr(_Path, "write_text", write_text)
    out = tmp_path / "run"
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    monkeypatch.undo()
    assert code == 2
    assert error_line(err) == (
        f"td3-jax: error: could not write {out / 'config.json'}: {os.strerror(errno.ENOSPC)}; "
        f"no checkpoint was written (nor anything else to keep): free space on the disk "
        f"holding {out}, then start the run again"
    )
    assert not (out / "config.json.tmp").exists()
    # Once there is room, the same --out starts (nothing half-written blocks it).
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(out)], capsys)
    assert code == 0, err


@pytest.mark.runs
def _stop_after(monkeypatch, step: str, stop, when=lambda out: True) -> None:
    """``run_module.<step>`` patched to set ``stop`` once it returns (where ``when(out)``)."""
    real = getattr(run_module, step)

    def step_then_stop(*args, **kwargs):
        out = real(*args, **kwargs)
        if when(out):
            stop.set()
        return out

    monkeypatch.setattr(run_module, step, step_then_stop)


def test_stop_ends_the_run_after_checkpointing_the_chunk_it_interrupts(tmp_path, monkeypatch):
    """The stop token given to train (set by the CLI's Ctrl-C handler, also when Python
    discards the interrupt) stops a run at the next chunk boundary: that chunk is logged and
    checkpointed, then the run raises KeyboardInterrupt."""
    from td3_jax.common.runtime import StopToken
    from td3_jax.runner.checkpoint import Checkpointer

    stop = StopToken()
    _stop_after(monkeypatch, "_chunk_and_record", stop)
    cfg = dataclasses.replace(SMALL, total_steps=192, warmup_steps=16, hidden_sizes=(8,))
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_module.train(cfg, out, progress=False, stop=stop)
    assert [r["env_steps"] for r in read_records(out)] == [64]
    checkpointer = Checkpointer(out / "checkpoints", create=False)
    assert checkpointer.steps() == [1]
    checkpointer.close()
    monkeypatch.undo()
    assert len(run_module.train(cfg, out, resume=True, progress=False)) == 2  # 128, 192


def test_a_stop_as_the_programs_load_leaves_a_startable_directory(tmp_path, monkeypatch):
    """A stop that comes while the programs load (from the cache, so no compile wait sees
    it) ends the run before it writes config.json or records: the same call then starts it
    (it used to find "a previous run's outputs" and no checkpoint to resume)."""
    from td3_jax.common.runtime import StopToken

    stop = StopToken()
    _stop_after(monkeypatch, "_compiled_and_state", stop)
    cfg = dataclasses.replace(SMALL, total_steps=128, warmup_steps=16, hidden_sizes=(8,))
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_module.train(cfg, out, progress=False, stop=stop)
    assert not (out / "config.json").exists() and not (out / "metrics.jsonl").exists()
    monkeypatch.undo()
    assert [r["env_steps"] for r in run_module.train(cfg, out, progress=False)] == [64, 128]


@pytest.mark.parametrize("limits", [{"time_budget_s": -1.0}, {"time_budget_s": float("inf")},
                                    {"devices": 0}, {"devices": -2}])  # fmt: skip
def test_the_library_refuses_a_bad_budget_or_device_count_before_the_run_starts(tmp_path,
                                                                               limits):  # fmt: skip
    """run.train (not only the CLI) refuses a time budget or a device count that is not
    positive: a budget of -1 trained one chunk and stopped; nothing is created."""
    flag = "--time-budget-s" if "time_budget_s" in limits else "--devices"
    with pytest.raises(ConfigError, match=f"^{flag} must be positive|^{flag} must be a positive"):
        run_module.train(SMALL, tmp_path / "run", progress=False, **limits)
    assert not (tmp_path / "run").exists()


def test_a_stop_that_comes_with_the_last_chunk_lets_the_run_finish(tmp_path, monkeypatch):
    """Set during the run's last chunk (a SIGTERM as the job ends), the token changes nothing:
    the run is complete, so train returns its records instead of raising."""
    from td3_jax.common.runtime import StopToken

    stop = StopToken()
    _stop_after(monkeypatch, "_chunk_and_record", stop, when=lambda out: out[1]["env_steps"] == 128)
    cfg = dataclasses.replace(SMALL, total_steps=128, warmup_steps=16, hidden_sizes=(8,))
    done = run_module.train(cfg, tmp_path / "run", progress=False, stop=stop)
    assert [r["env_steps"] for r in done] == [64, 128] and stop.is_set()


def test_a_state_larger_than_memory_is_refused_before_it_is_allocated(tmp_path, monkeypatch,
                                                                       capsys):  # fmt: skip
    """One line with both sizes and the flag to change, exit 2, and nothing allocated or
    compiled: the run directory holds no checkpoint."""
    from td3_jax.runner import sharding
    from td3_jax.runner.checkpoint import size_text, state_bytes

    host = sharding.memory_of(jax.devices()[0])
    assert host is not None and host[0] > 1e9 and "memory" in host[1]  # the host's, on a CPU
    cfg = TrainConfig(num_envs=4, total_steps=128, eval_every=64, warmup_steps=32, batch_size=16,
                      updates_per_iter=1, hidden_sizes=(16, 16), eval_envs=2, episode_length=16,
                      seed=7, buffer_size=256)  # TINY_FLAGS'  # fmt: skip
    state = make_population(cfg, members(cfg)).abstract_state
    need, ring = state_bytes(state), state_bytes(state.buffer)
    monkeypatch.setattr(sharding, "memory_of", lambda device: (need - 1, "the test's memory is"))
    code, _, err = main(["train", *TINY_FLAGS, "--out", str(tmp_path / "run")], capsys)
    line = err.strip().splitlines()[-1]
    networks = state_bytes(state.agent)
    assert networks > ring  # 16-wide networks with Adam's moments outweigh 256 ring rows
    assert code == 2 and "use smaller --critic-hidden-sizes (or --hidden-sizes, which " in line, err
    assert "--num-envs" not in line  # (it sizes the ring, not the networks)
    assert f"{size_text(need)} per device" in line and f"ring {size_text(ring)}, " in line
    assert f"optimiser states {size_text(networks)})" in line
    assert not list((tmp_path / "run").glob("checkpoints/*"))
    monkeypatch.setattr(sharding, "memory_of", lambda device: (need, "the test's memory is"))
    sharding.check_memory(state, sharding.make_mesh(1))  # exactly enough: accepted
    # A ring that outweighs the networks is what to shrink.
    big = dataclasses.replace(cfg, buffer_size=100_000, total_steps=100_000, eval_every=100_000)
    state = make_population(big, members(big)).abstract_state
    assert state_bytes(state.buffer) > state_bytes(state.agent)
    monkeypatch.setattr(sharding, "memory_of", lambda device: (1, "the test's memory is"))
    with pytest.raises(ConfigError, match=r"; use a smaller --buffer-size$"):  # (not --num-envs)
        sharding.check_memory(state, sharding.make_mesh(1))
    # The actor's layers outweigh the critics': its own flag is named.
    wide = dataclasses.replace(cfg, actor_hidden_sizes=(256, 256))
    state = make_population(wide, members(wide)).abstract_state
    with pytest.raises(ConfigError, match=r"; use smaller --actor-hidden-sizes \(or "):
        sharding.check_memory(state, sharding.make_mesh(1))
    # Several members: fewer of them first (each has its own networks and ring).
    seeds = dataclasses.replace(cfg, seeds=3)
    state = make_population(seeds, members(seeds)).abstract_state
    with pytest.raises(
        ConfigError,
        match=r"; use fewer --seeds or sweep values \(the run has 3 "
        r"members, each .*\), or smaller --critic-hidden-sizes \(or --hidden-sizes, which "
        r"sets both\)$",
    ):
        sharding.check_memory(state, sharding.make_mesh(1))


def test_a_file_system_that_refuses_locks_is_one_line_for_starting_and_probing(
    tmp_path, monkeypatch
):
    """ENOLCK (an NFS mount without its lock service) was a traceback: taking the lock and the
    busy probe both say, in one line, that the directory cannot be locked and what to do."""
    (tmp_path / rundir.LOCK_FILE).write_text("")

    def refuse(fd, operation):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(rundir.fcntl, "flock", refuse)
    expected = f"cannot lock {tmp_path / rundir.LOCK_FILE} (No locks available); "
    # the lock taken, the busy probe, and eval's reading of a directory without config.json
    # (which said the directory 'is being started by a td3-jax run')
    for take in (rundir.acquire_lock, rundir.check_not_in_use, rundir.load_config):
        with pytest.raises(ConfigError) as caught:
            take(tmp_path)
        assert str(caught.value).startswith(expected)
        assert str(caught.value).endswith("use a run directory on a local disk")
    # eval, render and export of a run without a checkpoint only read it: no lock needed
    assert "holds no checkpoint (its run stopped" in str(rundir.no_checkpoint_error(tmp_path))


def test_a_sweep_directory_is_told_by_its_sweep_section_or_its_swept_members(tmp_path):
    """config.json's sweep section, or (older sweeps) a members.json with swept values, makes a
    sweep; seeds alone, or no readable config.json, do not."""
    cases = {
        "section": ({"env": "e", "sweep": {"settings": ["tau"]}}, None, True),
        "old-sweep": ({"env": "e"}, [{"seed": 0, "overrides": {"tau": 0.1}}], True),
        "seeds": (
            {"env": "e"},
            [{"seed": 0, "overrides": {}}, {"seed": 1, "overrides": {}}],
            False,
        ),
        "one-run": ({"env": "e"}, None, False),
        "bad-members": ({"env": "e"}, "{oops", False),
        "no-config": (None, [{"seed": 0, "overrides": {"tau": 0.1}}], False),
    }
    for name, (config, listing, sweep) in cases.items():
        run = tmp_path / name
        run.mkdir()
        if config is not None:
            (run / rundir.CONFIG_FILE).write_text(json.dumps(config))
        if listing is not None:
            text = listing if isinstance(listing, str) else json.dumps(listing)
            (run / rundir.MEMBERS_FILE).write_text(text)
        assert rundir.is_sweep_dir(run) == sweep, name


def _stopped_in_first_chunk(out: Path, cfg: TrainConfig, record_steps: int = 8) -> None:
    """What a run of ``cfg`` stopped in its first chunk leaves in ``out``: config.json,
    members.json, a record, TensorBoard's event file, curve.png and an empty checkpoints
    folder (its lock released)."""
    lock = rundir.open_run_dir(out, resume=False)
    rundir.save_config(cfg, members(cfg), out, {"preset": None})
    (out / "metrics.jsonl").write_text(f'{{"env_steps": {record_steps}}}\n')
    (out / "curve.png").write_bytes(b"png")
    (out / "tensorboard").mkdir()
    (out / "tensorboard" / "events.out.tfevents.1.host").write_bytes(b"")
    (out / "checkpoints").mkdir()
    lock.unlock()


def test_a_run_stopped_before_its_first_checkpoint_starts_over_with_the_same_settings(
    tmp_path, capsys
):
    """The same settings start over there (the outputs removed under the lock, then written
    anew: one run's records, not two); other settings or members are refused as before, also
    when they are found only under the lock, and nothing is removed then."""
    out = tmp_path / "run"
    cfg = dataclasses.replace(SMALL, hidden_sizes=(8,))
    _stopped_in_first_chunk(out, cfg)
    assert rundir.stopped_before_checkpoint(out, cfg, members(cfg))
    other = dataclasses.replace(cfg, seed=cfg.seed + 1)
    for settings in (other, dataclasses.replace(cfg, actor_lr=1e-4)):
        assert not rundir.stopped_before_checkpoint(out, settings, members(settings))
        with pytest.raises(ConfigError, match="previous run's outputs"):
            rundir.check_fresh(out, run=(settings, members(settings)))
    assert not rundir.stopped_before_checkpoint(out, cfg, members(other))
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(ConfigError, match="previous run's outputs"):  # (checked under the lock)
        rundir.open_run_dir(out, resume=False, run=(other, members(other)))
    assert sorted(p.name for p in out.iterdir()) == before
    assert rundir.check_fresh(out, run=(cfg, members(cfg)))  # (it starts over there)
    assert not rundir.check_fresh(tmp_path / "new", run=(cfg, members(cfg)))
    lock = rundir.open_run_dir(out, resume=False, run=(cfg, members(cfg)))
    try:
        assert sorted(p.name for p in out.iterdir()) == [".lock"]
        assert "starting over in" in capsys.readouterr().out
    finally:
        lock.unlock()


@pytest.mark.parametrize("left", ["record past the first checkpoint", "no record", "resumed",
                                  "a file in checkpoints", "a folder in tensorboard",
                                  "a file of others", "an environment of one's own"])  # fmt: skip
def test_what_could_not_be_written_again_is_never_started_over(tmp_path, left):
    """A finished run whose checkpoints were deleted, one that recorded nothing (a fresh start
    is accepted there without removing anything), a resumed run (its config.json holds what
    this run would not write), anything of others in its folders, and an environment of the
    user's own (its code may have changed): no start-over."""
    out = tmp_path / "run"
    cfg = dataclasses.replace(SMALL, hidden_sizes=(8,))
    first = cfg.checkpoint_every * cfg.steps_per_chunk
    _stopped_in_first_chunk(out, cfg, record_steps=first)  # (a record at the first: still one)
    assert rundir.stopped_before_checkpoint(out, cfg, members(cfg))
    if left == "record past the first checkpoint":
        (out / "metrics.jsonl").write_text(f'{{"env_steps": {first}}}\n{{"env_steps": '
                                           f'{first + cfg.steps_per_chunk}}}\n')  # fmt: skip
    elif left == "no record":
        (out / "metrics.jsonl").write_text("")
    elif left == "resumed":
        saved = json.loads((out / "config.json").read_text())
        saved["resume_changes"] = [{"at_env_steps": first, "total_steps": [first, 2 * first]}]
        (out / "config.json").write_text(json.dumps(saved))
    elif left == "a file in checkpoints":
        (out / "checkpoints" / "my_best_policy").mkdir()
    elif left == "a folder in tensorboard":
        (out / "tensorboard" / "other_run").mkdir()
    elif left == "a file of others":
        (out / "notes.txt").write_text("mine")
    else:
        cfg = dataclasses.replace(cfg, env="mypackage.envs:make_env")
        rundir.save_config(cfg, members(cfg), out, {"preset": None})
    assert not rundir.stopped_before_checkpoint(out, cfg, members(cfg))
