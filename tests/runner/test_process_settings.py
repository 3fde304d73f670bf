"""The several-process settings (``--coordinator-address``, ``--num-processes``,
``--process-id`` and their environment variables) are checked before JAX's runtime starts
(:func:`td3_jax.runner.sharding.check_processes`): one line each, never a traceback."""

from __future__ import annotations

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
