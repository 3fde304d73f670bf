"""The several-process settings (``--coordinator-address``, ``--num-processes``,
``--process-id`` and their environment variables) are checked before JAX's runtime starts
(:func:`td3_jax.runner.sharding.check_processes`): one line each, never a traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from td3_jax.common.errors import ConfigError
from td3_jax.runner.sharding import check_processes, initialize_distributed


@pytest.mark.parametrize(
    ("address", "processes", "process", "message"),
    [
        ("localhost", 2, 0, "--coordinator-address 'localhost' must be HOST:PORT (e.g. "
         "10.0.0.1:12345): the first process's host and a free port"),
        (":1234", 2, 0, "--coordinator-address ':1234' must be HOST:PORT (e.g. 10.0.0.1:12345): "
         "the first process's host and a free port"),
        ("host:99999", 2, 0, "--coordinator-address 'host:99999' must be HOST:PORT (e.g. "
         "10.0.0.1:12345): the first process's host and a free port"),
        ("host:1234", 0, 0, "--num-processes must be at least 1, got 0"),
        ("host:1234", 2, 2, "--process-id must be from 0 to 1 (one per process), got 2"),
        ("host:1234", 2, -1, "--process-id must be from 0 to 1 (one per process), got -1"),
    ],
)  # fmt: skip
def test_bad_several_process_settings_are_refused_in_one_line(address, processes, process,
                                                              message):  # fmt: skip
    with pytest.raises(ConfigError) as err:
        check_processes(address, processes, process)
    assert str(err.value) == message


def test_good_several_process_settings_pass():
    check_processes("10.0.0.1:12345", 4, 3)
    check_processes("host:1", None, None)  # (JAX finds the counts itself, e.g. under SLURM)


def test_a_process_count_in_the_environment_must_be_a_whole_number(monkeypatch):
    monkeypatch.setenv("JAX_NUM_PROCESSES", "two")
    with pytest.raises(ConfigError, match=r"^JAX_NUM_PROCESSES='two' is not a whole number$"):
        initialize_distributed("host:1234", None, 0)


_COORDINATOR_ALONE = """
import sys
from td3_jax.common.errors import ConfigError
from td3_jax.runner.sharding import initialize_distributed
processes = None if sys.argv[1] == "-" else int(sys.argv[1])
try:
    initialize_distributed("127.0.0.1:1", processes, None)
except ConfigError as err:
    print(err)
"""


@pytest.mark.parametrize("processes", ["-", "2"])
def test_a_coordinator_without_the_counts_jax_needs_is_refused_in_one_line(processes):
    """--coordinator-address alone (or without --process-id), with no cluster manager to read
    the counts from: JAX's ValueError becomes one line naming the flags (it was a traceback).
    In a fresh process (JAX refuses to start its runtime once a backend exists) whose
    environment names no process count, id or cluster."""
    cluster = ("JAX_", "SLURM_", "OMPI_", "PMI_", "KUBERNETES_", "MPI_", "TPU_")
    env = {k: v for k, v in os.environ.items() if not k.startswith(cluster)}
    proc = subprocess.run([sys.executable, "-c", _COORDINATOR_ALONE, processes],
                          env={**env, "JAX_PLATFORMS": "cpu"}, capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    said = proc.stdout.strip()
    assert said.startswith(
        "--coordinator-address needs --num-processes and --process-id (or JAX_NUM_PROCESSES and "
        "JAX_PROCESS_ID) where no cluster manager (SLURM, Open MPI, ...) sets them; JAX: "
    ), said
    assert said.endswith("must be defined."), said
    assert "waiting for" not in said  # (no process id: nothing said of waiting)


def test_a_waiting_process_says_which_ids_to_start_and_how_long_jax_waits(monkeypatch, capsys):
    """The waiting line names the ids the other processes need and the join timeout, which is
    the one given to JAX (past it JAX aborts the process with a C++ check failure)."""
    import jax

    from td3_jax.envs import mjx_devices
    from td3_jax.runner import sharding

    given = {}
    monkeypatch.setattr(jax.distributed, "initialize", lambda **kw: given.update(kw))
    monkeypatch.setattr(jax.config, "update", lambda *args: None)
    monkeypatch.setattr(mjx_devices, "place_on_local_devices", lambda: None)
    assert initialize_distributed("127.0.0.1:5", 3, 1)
    said = capsys.readouterr().out
    assert said.startswith("td3-jax: waiting for 3 processes at 127.0.0.1:5 (this is process 1;")
    assert "its own --process-id, 0 to 2" in said
    assert f"gives up after {sharding.JOIN_TIMEOUT_S} s" in said
    assert given == {"coordinator_address": "127.0.0.1:5", "num_processes": 3, "process_id": 1,
                     "initialization_timeout": sharding.JOIN_TIMEOUT_S}  # fmt: skip


class _Store:
    """A stand-in for the runtime's key-value store: what each process published."""

    def __init__(self, published: dict[str, str]):
        self.published = published

    def key_value_set(self, key: str, value: str) -> None:
        self.published[key] = value

    def blocking_key_value_get(self, key: str, timeout_ms: int) -> str:
        return self.published[key]


def _as_process(monkeypatch, index: int, count: int, store: _Store) -> None:
    import jax

    from td3_jax.common import upstream

    monkeypatch.setattr(jax, "process_count", lambda: count)
    monkeypatch.setattr(jax, "process_index", lambda: index)
    monkeypatch.setattr(upstream, "distributed_store", lambda: store)


def test_processes_given_other_settings_are_told_which_one_differs(monkeypatch):
    """Process 0 of 2 finds process 1's --total-steps different and says so in one line (the
    first setting that differs, and how many more); its own settings are published for the
    others to check."""
    from td3_jax.runner.sharding import SETTINGS_KEY, check_same_settings

    theirs = {"total_steps": 1024, "num_envs": 16, "seed": 0}
    store = _Store({f"{SETTINGS_KEY}/1": json.dumps(theirs)})
    _as_process(monkeypatch, 0, 2, store)
    with pytest.raises(ConfigError) as err:
        check_same_settings({"total_steps": 512, "num_envs": 8, "seed": 0})
    assert str(err.value) == (
        "process 1 was given other settings than this process (0): --num-envs 16 there, 8 "
        "here (and 1 more); start every process with the same flags, only --process-id "
        "differing")  # fmt: skip
    assert json.loads(store.published[f"{SETTINGS_KEY}/0"])["total_steps"] == 512


def test_processes_given_the_same_settings_go_on(monkeypatch):
    """Equal settings pass (tuples and paths compare as the JSON the others published); one
    process checks nothing."""
    from pathlib import Path

    from td3_jax.runner.sharding import SETTINGS_KEY, check_same_settings

    settings = {"hidden_sizes": (32, 32), "menagerie": Path("/m"), "resume": False}
    published = json.dumps(settings, sort_keys=True, default=str)
    _as_process(monkeypatch, 1, 3, _Store({f"{SETTINGS_KEY}/0": published,
                                           f"{SETTINGS_KEY}/2": published}))  # fmt: skip
    check_same_settings(settings)
    _as_process(monkeypatch, 0, 1, None)  # (a store would be asked for: None has no methods)
    check_same_settings(settings)


@pytest.mark.timeout(300)
@pytest.mark.processes
def test_two_processes_given_different_flags_both_stop_in_one_line(tmp_path):
    """Two CPU processes of one run, the second given another --total-steps: each says which
    setting differs and exits 2 before anything is written (they waited for each other at
    the end until JAX aborted both, exit status 134)."""
    from benchmarks.multiprocess import free_port

    flags = ["--env", "gymnax/Pendulum-v1", "--num-envs", "8", "--eval-every", "256",
             "--batch-size", "64", "--hidden-sizes", "8", "--eval-envs", "4", "--buffer-size",
             "512", "--replay-shards", "2", "--compile-cache", "off", "--out",
             str(tmp_path / "run"), "--coordinator-address", f"localhost:{free_port()}",
             "--num-processes", "2"]  # fmt: skip
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    procs = [subprocess.Popen([sys.executable, "-m", "td3_jax", "train", *flags, "--total-steps",
                               steps, "--process-id", str(i)], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for i, steps in enumerate(("512", "1024"))]  # fmt: skip
    outs = [p.communicate(timeout=240) for p in procs]
    for i, (p, (_, err)) in enumerate(zip(procs, outs, strict=True)):
        assert p.returncode == 2, err[-2000:]
        there, here = ("1024", "512") if i == 0 else ("512", "1024")
        assert (f"td3-jax: error: process {1 - i} was given other settings than this process "
                f"({i}): --total-steps {there} there, {here} here;") in err  # fmt: skip
    assert not (tmp_path / "run").exists()
