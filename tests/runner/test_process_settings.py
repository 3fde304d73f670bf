"""The several-process settings (``--coordinator-address``, ``--num-processes``,
``--process-id`` and their environment variables) are checked before JAX's runtime starts
(:func:`td3_jax.runner.sharding.check_processes`), and the processes' flags against each other
once it has (:func:`td3_jax.runner.sharding.check_same_settings`): one line each, never a
traceback or a process left waiting."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from td3_jax.common.errors import ConfigError
from td3_jax.config.schema import TrainConfig
from td3_jax.runner.sharding import (
    JOIN_TIMEOUT_S,
    SETTINGS_KEY,
    STOP_KEY,
    check_processes,
    check_same_settings,
    initialize_distributed,
)


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


_SIGTERM_AFTER_JOINING = """
import os, signal, sys, time
got = []
signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
from td3_jax.cli.local_processes import free_port
from td3_jax.runner.sharding import initialize_distributed
initialize_distributed(f"127.0.0.1:{free_port()}", 1, 0)
os.kill(os.getpid(), signal.SIGTERM)
deadline = time.monotonic() + 10
while not got and time.monotonic() < deadline:
    time.sleep(0.05)
print("handled" if got else "lost", flush=True)
os._exit(0)
"""


def test_a_sigterm_after_the_processes_join_reaches_the_handlers_of_td3_jax():
    """JAX's preemption service, which its runtime starts on joining, took SIGTERM for itself:
    a SIGTERM between the join and training was lost and the run trained on. A handler
    installed before the join still gets it (a fresh process: one joins once)."""
    proc = subprocess.run([sys.executable, "-c", _SIGTERM_AFTER_JOINING],
                          env={**os.environ, "JAX_PLATFORMS": "cpu"}, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "handled", proc.stderr[-2000:]
    assert "SIGTERM caught" not in proc.stderr


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
    monkeypatch.delenv("TD3_JAX_LOCAL_PROCESSES", raising=False)
    assert initialize_distributed("127.0.0.1:5", 3, 1)
    said = capsys.readouterr().out
    assert said.startswith("td3-jax: waiting for 3 processes at 127.0.0.1:5 (this is process 1;")
    assert "its own --process-id, 0 to 2" in said
    assert f"gives up after {sharding.JOIN_TIMEOUT_S} s" in said
    assert given == {"coordinator_address": "127.0.0.1:5", "num_processes": 3, "process_id": 1,
                     "initialization_timeout": sharding.JOIN_TIMEOUT_S,
                     "coordinator_bind_address": "127.0.0.1:5"}  # fmt: skip
    monkeypatch.setenv("TD3_JAX_LOCAL_PROCESSES", "3")  # (--local-processes said where they join)
    assert initialize_distributed("127.0.0.1:5", 3, 1)
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize(("address", "bound"), [("127.0.0.1:5", "127.0.0.1:5"),
                                                ("10.0.0.1:5", None), ("localhost:5", None),
                                                ("127.0.0.10:5", None)])  # fmt: skip
def test_a_loopback_coordinator_listens_on_loopback_alone(address, bound):
    """--local-processes joins at 127.0.0.1: the service then listens there, not on every
    interface (JAX's default, kept for other addresses: "localhost" may resolve to ::1)."""
    from td3_jax.runner import sharding

    assert sharding._bind_address(address) == bound


#: A small run's settings (nothing of it runs in these tests).
SMALL_CFG = TrainConfig(env="gymnax/Pendulum-v1", num_envs=2, total_steps=64, eval_every=32)


class _Store:
    """A stand-in for the runtime's key-value store (its two calls, arguments as JAX's): what
    each process published; a key never published times out as JAX's does."""

    def __init__(self, published: dict[str, str]):
        self.published = published

    def key_value_set(self, key: str, value: str) -> None:
        if key in self.published:  # (as JAX refuses to set a key twice)
            raise jax.errors.JaxRuntimeError(f"ALREADY_EXISTS: Config key {key} already exists.")
        self.published[key] = value

    def blocking_key_value_get(self, key: str, timeout_in_ms: int) -> str:
        if key not in self.published:
            raise jax.errors.JaxRuntimeError(f"DEADLINE_EXCEEDED: GetKeyValue() timed out: {key}")
        return self.published[key]


def _as_process(monkeypatch, index: int, count: int, store: _Store | None) -> None:
    from td3_jax.common import upstream

    monkeypatch.setattr(jax, "process_count", lambda: count)
    monkeypatch.setattr(jax, "process_index", lambda: index)
    monkeypatch.setattr(upstream, "distributed_store", lambda: store)


def _publication(settings: dict) -> str:
    """What a process publishes: each setting's JSON text, as one JSON object."""
    return json.dumps({k: json.dumps(v, sort_keys=True, default=str) for k, v in settings.items()})


def test_processes_given_other_settings_are_told_which_one_differs(monkeypatch):
    """Process 0 of 2 finds process 1's settings different and says so in one line (the first
    setting that differs by name, and how many more); its own are published for the others."""
    store = _Store({f"{SETTINGS_KEY}/1": _publication({"total_steps": 1024, "num_envs": 16,
                                                        "seed": 0})})  # fmt: skip
    _as_process(monkeypatch, 0, 2, store)
    with pytest.raises(ConfigError) as err:
        check_same_settings({"total_steps": 512, "num_envs": 8, "seed": 0})
    assert str(err.value) == (
        "process 1 was given other settings than this process (0): --num-envs 16 there, "
        "--num-envs 8 here (and 1 more); start every process with the same flags (only "
        "--process-id, --menagerie, --quiet and --compile-cache may differ)")  # fmt: skip
    assert json.loads(json.loads(store.published[f"{SETTINGS_KEY}/0"])["total_steps"]) == 512


def test_a_setting_only_one_process_has_is_named_as_not_given(monkeypatch):
    _as_process(monkeypatch, 1, 2, _Store({f"{SETTINGS_KEY}/0": _publication({"seed": 0})}))
    with pytest.raises(ConfigError, match=r": no --resume there, --resume here;"):
        check_same_settings({"seed": 0, "resume": True})


@pytest.mark.parametrize(("theirs", "mine", "said"), [
    ((256, 256), (32, 32), "--hidden-sizes 256 256 there, --hidden-sizes 32 32 here;"),
    (True, False, "--layer-norm there, --no-layer-norm here;"),
    ("playground/T1JoystickFlatTerrain", "brax/ant",
     "--env playground/T1JoystickFlatTerrain there, --env brax/ant here;"),
])
def test_a_setting_that_differs_is_said_as_it_is_typed(monkeypatch, theirs, mine, said):
    """Each side as its flag on the command line (it was the published JSON: [256, 256],
    true, quoted names)."""
    name = {tuple: "hidden_sizes", bool: "layer_norm", str: "env"}[type(theirs)]
    _as_process(monkeypatch, 1, 2, _Store({f"{SETTINGS_KEY}/0": _publication({name: theirs})}))
    with pytest.raises(ConfigError) as err:
        check_same_settings({name: mine})
    assert said in str(err.value)


@pytest.mark.parametrize(("name", "theirs", "mine", "said"), [
    ("command", "sweep", "train", "td3-jax sweep there, td3-jax train here;"),
    ("time_budget_s", None, 60.0, "no --time-budget-s there, --time-budget-s 60.0 here;"),
])
def test_the_subcommand_and_an_unset_flag_are_said_as_typed(monkeypatch, name, theirs, mine,
                                                            said):  # fmt: skip
    _as_process(monkeypatch, 1, 2, _Store({f"{SETTINGS_KEY}/0": _publication({name: theirs})}))
    with pytest.raises(ConfigError) as err:
        check_same_settings({name: mine})
    assert said in str(err.value)


def test_processes_given_the_same_settings_go_on(monkeypatch):
    """Equal settings pass (tuples, paths and NaN compare as the JSON the others published);
    without jax.distributed nothing is checked (no store asked for, no backend started)."""
    settings = {"hidden_sizes": (32, 32), "out": Path("/m"), "v_min": float("nan")}
    published = {f"{SETTINGS_KEY}/{i}": _publication(settings) for i in (0, 2)}
    _as_process(monkeypatch, 1, 3, _Store(published))
    check_same_settings(settings)
    _as_process(monkeypatch, 0, 1, None)
    check_same_settings({"seed": 1})


def test_a_process_that_gives_no_settings_is_named_not_waited_for_forever(monkeypatch):
    """A process that stopped before publishing (its own output says why): the others stop
    with one line once JAX's wait times out, not with JAX's traceback."""
    _as_process(monkeypatch, 0, 2, _Store({}))
    with pytest.raises(ConfigError) as err:
        check_same_settings({"seed": 0})
    assert str(err.value) == (
        f"process 1 did not give its settings within {JOIN_TIMEOUT_S} s: it stopped before "
        "(its own output says why) or is stuck")  # fmt: skip


def test_train_compares_the_flags_as_parsed_with_the_process_flags_that_must_agree(monkeypatch):
    """What td3-jax train hands the check: every training setting but --menagerie (each host's
    own robots folder), the subcommand, --resume, --devices, --out, --time-budget-s and the
    swept values."""
    from td3_jax.cli import train
    from td3_jax.runner import sharding

    handed = {}
    monkeypatch.setattr(sharding, "check_same_settings", handed.update)
    args = ["--env", "gymnax/Pendulum-v1", "--menagerie", "/r", "--out", "runs/x",
            "--time-budget-s", "60"]  # fmt: skip
    command, cfg, _, _ = train.parse_train(args, False)
    train._check_processes_agree(cfg, command, {"tau": [0.1, 0.2]}, sweeping=True)
    assert "menagerie" not in handed
    assert handed["env"] == "gymnax/Pendulum-v1" and handed["total_steps"] == cfg.total_steps
    assert {k: handed[k] for k in ("command", "resume", "devices", "out", "time_budget_s",
                                   "sweep_tau")} == {
        "command": "sweep", "resume": False, "devices": None, "out": "runs/x",
        "time_budget_s": 60.0, "sweep_tau": [0.1, 0.2]}  # fmt: skip


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
    try:
        outs = [p.communicate(timeout=240) for p in procs]
    finally:
        for p in procs:
            p.kill()
    for i, (p, (_, err)) in enumerate(zip(procs, outs, strict=True)):
        assert p.returncode == 2, err[-2000:]
        there, here = ("1024", "512") if i == 0 else ("512", "1024")
        assert (f"td3-jax: error: process {1 - i} was given other settings than this process "
                f"({i}): --total-steps {there} there, --total-steps {here} here;"
                ) in err  # fmt: skip
    assert not (tmp_path / "run").exists()


# --- stopping together ----------------------------------------------------------------------


def _stop_run(stop_set: bool = False, budget: float | None = None, wall: float = 0.0,
              after_chunks: int | None = None):  # fmt: skip
    """The fields of a run that its stop decision reads."""
    from types import SimpleNamespace

    from td3_jax.common.runtime import StopToken

    stop = StopToken()
    if stop_set:
        stop.set()
    checkpointer = SimpleNamespace(latest_step=lambda: 3)
    return SimpleNamespace(stop=stop, stop_after_chunks=after_chunks, time_budget_s=budget,
                           records=[{"wall_time_s": wall}], checkpointer=checkpointer,
                           start_chunk=0, start_steps=0, call=0, started_together=False,
                           last_chunk=None, writer=False, out_dir=None,
                           cfg=SimpleNamespace(steps_per_chunk=32, run_steps=1000))  # fmt: skip


@pytest.mark.parametrize(
    ("mine", "theirs", "agreed"),
    [("", ["", ""], ""), ("", ["limit", ""], "limit"), ("limit", ["", ""], "limit"),
     ("", ["", "token"], "token"), ("limit", ["token", ""], "token"),
     ("token", ["", ""], "token")],
)  # fmt: skip
def test_the_processes_stop_together_for_the_strongest_reason_any_has(monkeypatch, mine, theirs,
                                                                      agreed):  # fmt: skip
    """Process 1 of 3: its own reason published under the boundary's key, the others' read;
    any process's stop token wins over any limit, which wins over going on."""
    from td3_jax.runner.sharding import STOP_KEY, stop_agreed

    published = {f"{STOP_KEY}/0/4/end/{i}": r for i, r in zip((0, 2), theirs, strict=True)}
    store = _Store(published)
    _as_process(monkeypatch, 1, 3, store)
    assert stop_agreed(mine, 4, end=True) == agreed
    assert store.published[f"{STOP_KEY}/0/4/end/1"] == mine


def test_one_process_decides_alone(monkeypatch):
    from td3_jax.runner.sharding import stop_agreed

    _as_process(monkeypatch, 0, 1, None)
    assert [stop_agreed(r, 0, end=False) for r in ("", "limit", "token")] == ["", "limit", "token"]


def test_a_budget_one_process_reached_first_stops_the_other_at_the_same_boundary(monkeypatch):
    """--time-budget-s is read from each process's own clock: process 0 is past it, process 1
    (its clock a little behind) not yet; both stop at the end of chunk 2, process 1 without a
    stop token of its own (a budget stop ends as done, not interrupted)."""
    from td3_jax.runner import run as run_module
    from td3_jax.runner.sharding import STOP_KEY

    run = _stop_run(budget=60.0, wall=59.5)
    assert run_module._own_stop_reason(run, 3) == ""
    _as_process(monkeypatch, 1, 2, _Store({f"{STOP_KEY}/0/2/end/0": "limit"}))
    assert run_module._stopping(run, 3, 2, end=True)
    assert not run.stop.is_set()


def test_another_process_stopped_by_a_signal_stops_this_one_as_interrupted(monkeypatch):
    """A Ctrl-C or SIGTERM that reached process 0 alone: process 1 stops at the same boundary
    with its own stop token set, so it ends as interrupted too (after the chunk's
    checkpoint)."""
    from td3_jax.runner import run as run_module
    from td3_jax.runner.sharding import STOP_KEY

    run = _stop_run()
    _as_process(monkeypatch, 1, 2, _Store({f"{STOP_KEY}/0/5/start/0": "token"}))
    assert run_module._stopping(run, 0, 5, end=False)
    assert run.stop.is_set()


def test_a_process_that_never_reaches_the_boundary_stops_this_one_keeping_its_checkpoint(
    monkeypatch,
):
    """Process 0 stopped (or hangs) before the end of chunk 3: once JAX's wait times out,
    process 1 stops with one line naming it and the checkpoint it keeps (exit status 3),
    rather than going on into a chunk whose collectives would never complete."""
    from td3_jax.common.errors import ProcessLostError
    from td3_jax.runner import run as run_module
    from td3_jax.runner.sharding import STOP_WAIT_S

    run = _stop_run()
    _as_process(monkeypatch, 1, 2, _Store({}))
    with pytest.raises(ProcessLostError) as err:
        run_module._stopping(run, 3, 2, end=True)
    assert str(err.value).startswith(
        f"process 0 did not reach the end of chunk 3 within {STOP_WAIT_S} s of this process")
    assert "the last good checkpoint (after 96 env steps) is kept" in str(err.value)
    assert ProcessLostError.exit_code == 3


def test_a_process_that_stops_with_an_error_stops_the_others_at_once(monkeypatch):
    """Process 0 failed in chunk 4 (its disk full, say) and said so at that chunk's boundaries
    (keeping the reason it gave at the chunk's start); process 1, at the chunk's end, stops
    with one line naming it instead of waiting for it; its earlier training call's keys
    (call 0) do not count for this one (call 1)."""
    from td3_jax.common.errors import ProcessLostError
    from td3_jax.runner.sharding import STOP_KEY, stop_agreed, stop_failed

    store = _Store({f"{STOP_KEY}/1/4/start/0": "", f"{STOP_KEY}/0/4/end/0": ""})
    _as_process(monkeypatch, 0, 2, store)
    stop_failed(4, call=1)
    assert {k: v for k, v in store.published.items() if k.startswith(f"{STOP_KEY}/1/")} == {
        f"{STOP_KEY}/1/4/start/0": "", f"{STOP_KEY}/1/4/end/0": "error",
        f"{STOP_KEY}/1/5/start/0": "error"}  # fmt: skip
    _as_process(monkeypatch, 1, 2, store)
    with pytest.raises(ProcessLostError) as err:
        stop_agreed("", 4, end=True, call=1)
    assert str(err.value) == ("process 0 stopped with an error before the end of chunk 5 (its "
                              "own output says which); this process stops too")  # fmt: skip
    assert stop_agreed("", 4, end=True, call=0) == ""  # (call 0: process 0 went on there)


def test_a_stop_asked_while_the_processes_start_stops_all_before_any_program_runs(
    monkeypatch,
):
    """A Ctrl-C that reached process 0 while it compiled: process 1, compiled, learns it where
    they agree to start (before any program of the run executes), and stops as interrupted
    instead of waiting for process 0 at its first collective."""
    from td3_jax.runner import run as run_module
    from td3_jax.runner.sharding import STOP_KEY

    run = _stop_run()
    store = _Store({f"{STOP_KEY}/0/-1/start/0": "token"})
    _as_process(monkeypatch, 1, 2, store)
    with pytest.raises(KeyboardInterrupt):
        run_module._agree_to_start(run)
    assert run.stop.is_set() and store.published[f"{STOP_KEY}/0/-1/start/1"] == ""


def test_processes_that_all_start_go_on_and_one_alone_needs_no_store(monkeypatch):
    from td3_jax.common import upstream
    from td3_jax.runner import run as run_module
    from td3_jax.runner.sharding import STOP_KEY

    run = _stop_run()
    _as_process(monkeypatch, 1, 2, _Store({f"{STOP_KEY}/0/-1/start/0": ""}))
    run_module._agree_to_start(run)
    assert not run.stop.is_set() and run.started_together
    monkeypatch.setattr(jax, "process_count", lambda: 1)
    monkeypatch.setattr(jax, "process_index", lambda: 0)
    monkeypatch.setattr(upstream, "distributed_store", lambda: pytest.fail("store asked"))
    run_module._agree_to_start(run)
    run.stop.set()
    with pytest.raises(KeyboardInterrupt):
        run_module._agree_to_start(run)


def test_a_process_that_fails_after_the_processes_agreed_to_start_tells_the_others(
    monkeypatch,
):
    """Process 0 agreed to start, then failed before its first chunk (its config.json not
    written: a full disk, say): process 1, at that chunk's start, stops with one line instead
    of waiting there for it."""
    from td3_jax.common.errors import ProcessLostError
    from td3_jax.runner import run as run_module
    from td3_jax.runner.sharding import STOP_KEY, stop_agreed

    def agreed_then_failed(run, *args, **kwargs):
        run_module._agree_to_start(run)
        raise OSError("No space left on device")

    store = _Store({f"{STOP_KEY}/0/-1/start/1": ""})
    _as_process(monkeypatch, 0, 2, store)
    monkeypatch.setattr(run_module, "_start", lambda run, source, resume: None)
    monkeypatch.setattr(run_module.tracking, "start", lambda *a, **k: None)
    monkeypatch.setattr(run_module, "_compiled_and_state",
                        lambda run, *a, **k: (agreed_then_failed(run), None))  # fmt: skip
    with pytest.raises(OSError):
        run_module._start_and_train(_stop_run(), None, False, False, preset=None, changes=None)
    _as_process(monkeypatch, 1, 2, store)
    with pytest.raises(ProcessLostError) as err:
        stop_agreed("", 0, end=False)
    assert str(err.value).startswith("process 0 stopped with an error before the start of chunk 1")


def test_a_process_whose_own_checks_stop_it_before_its_run_starts_tells_the_others(
    monkeypatch, tmp_path
):
    """A check that only the writing process makes (its --out holding another run, say) stops
    process 0 before its run exists: process 1 learns it where they agree to start."""
    from td3_jax.common.errors import ProcessLostError
    from td3_jax.runner import run as run_module

    store = _Store({})
    _as_process(monkeypatch, 0, 2, store)

    def refused(*args, **kwargs):
        raise ConfigError("runs/x already holds a run")

    monkeypatch.setattr(run_module, "_prepare", refused)
    with pytest.raises(ConfigError):
        run_module.train(SMALL_CFG, tmp_path / "run", progress=False)
    _as_process(monkeypatch, 1, 2, store)
    other = _stop_run()
    other.call = next(k for k in store.published if k.endswith("/start/0")).split("/")[2]
    for agree in (run_module._agree_prepared, run_module._agree_to_start):
        with pytest.raises(ProcessLostError) as err:  # (before it compiles, where it did)
            agree(other)
        assert str(err.value).startswith("process 0 stopped with an error before the start "
                                         "of training")  # fmt: skip


def test_a_process_that_fails_between_joining_and_training_tells_the_others(monkeypatch):
    """A check the command makes before training (its own host's run directory, say) stops
    process 1 after it joined: process 0 learns it where its next run would agree to go on,
    before anything of that run needs process 1 (it waited in orbax's first collective for it
    and failed with a traceback)."""
    from td3_jax.common.errors import ProcessLostError
    from td3_jax.runner import run as run_module

    store = _Store({})
    _as_process(monkeypatch, 1, 2, store)
    monkeypatch.setattr(run_module, "_TRAIN_CALLS", run_module._CallCounter())
    run_module.stop_before_next_training("error")
    _as_process(monkeypatch, 0, 2, store)
    waiting = _stop_run()
    waiting.call = next(run_module._TRAIN_CALLS)  # (its next training call)
    with pytest.raises(ProcessLostError, match=r"^process 1 stopped with an error before the "
                                               r"start of training"):  # fmt: skip
        run_module._agree_prepared(waiting)


def test_a_stop_asked_while_the_processes_prepare_stops_all_before_they_compile(monkeypatch):
    from td3_jax.runner import run as run_module

    store = _Store({f"{STOP_KEY}/0/-2/start/1": "token"})
    _as_process(monkeypatch, 0, 2, store)
    run = _stop_run()
    with pytest.raises(KeyboardInterrupt):
        run_module._agree_prepared(run)
    assert run.stop.is_set() and store.published[f"{STOP_KEY}/0/-2/start/0"] == ""
    _as_process(monkeypatch, 0, 1, None)
    alone = _stop_run()
    run_module._agree_prepared(alone)  # (one process: goes on, nothing asked)
    assert not alone.stop.is_set()


@pytest.mark.parametrize(("stopped", "raised", "reason"),
                         [(False, RuntimeError("disk"), "error"),
                          (True, KeyboardInterrupt(), "token")])  # fmt: skip
def test_a_process_that_stops_while_starting_tells_the_others_why(monkeypatch, stopped, raised,
                                                                   reason):  # fmt: skip
    """Process 0 fails (or is stopped) before it trains: it publishes why where the processes
    agree to start, and process 1 stops there: with ProcessLostError naming it, or as
    interrupted."""
    from td3_jax.common.errors import ProcessLostError
    from td3_jax.runner import run as run_module

    def start(run, source, resume):
        if stopped:
            run.stop.set()
        raise raised

    store = _Store({})
    _as_process(monkeypatch, 0, 2, store)
    monkeypatch.setattr(run_module, "_start", start)
    with pytest.raises(type(raised)):
        run_module._start_and_train(_stop_run(), None, False, False, preset=None, changes=None)
    _as_process(monkeypatch, 1, 2, store)
    other = _stop_run()
    if reason == "error":
        with pytest.raises(ProcessLostError) as err:
            run_module._agree_to_start(other)
        assert str(err.value).startswith("process 0 stopped with an error before the start of "
                                         "training (its own output says which)")  # fmt: skip
    else:
        with pytest.raises(KeyboardInterrupt):
            run_module._agree_to_start(other)
        assert other.stop.is_set()


@pytest.mark.timeout(400)
@pytest.mark.processes
@pytest.mark.parametrize(("signum", "code", "said"), [
    ("SIGTERM", 143, "terminated (SIGTERM); the newest checkpoint is"),
    ("SIGINT", 130, "interrupted; the newest checkpoint is")])  # fmt: skip
def test_a_signal_that_reaches_one_process_stops_both_at_one_chunk_checkpointed(
    tmp_path, signum, code, said
):
    """Two CPU processes; SIGTERM (or a Ctrl-C's SIGINT) to process 1 alone once training
    runs. Each process decided alone before (and a Ctrl-C left at once), so process 0 went on
    into a chunk process 1 never joined and waited there until JAX aborted it. Now both stop
    after the same chunk, its checkpoint written: process 1 as its signal says, process 0
    saying it stopped with the other (130)."""
    import signal
    import time

    from benchmarks.multiprocess import free_port

    out = tmp_path / "run"
    flags = ["--env", "gymnax/Pendulum-v1", "--num-envs", "8", "--eval-every", "256",
             "--total-steps", "51200", "--batch-size", "64", "--hidden-sizes", "8",
             "--eval-envs", "4", "--buffer-size", "512", "--replay-shards", "2",
             "--compile-cache", "off", "--quiet", "--out", str(out), "--coordinator-address",
             f"localhost:{free_port()}", "--num-processes", "2"]  # fmt: skip
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    procs = [subprocess.Popen([sys.executable, "-m", "td3_jax", "train", *flags, "--process-id",
                               str(i)], env=env, text=True, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE) for i in (0, 1)]  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while not (out / "metrics.jsonl").exists() or not (out / "metrics.jsonl").read_text():
            assert time.monotonic() < deadline and all(p.poll() is None for p in procs)
            time.sleep(0.2)
        procs[1].send_signal(getattr(signal, signum))
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:
            p.kill()
    codes = [p.returncode for p in procs]
    assert codes == [130, code], [o[1][-2000:] for o in outs]
    assert "stopped with another process of the run, which was stopped (Ctrl-C or SIGTERM); " \
           "the newest checkpoint is" in outs[0][1]  # fmt: skip
    assert said in outs[1][1]
    records = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    saved = sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit())
    assert saved and records[-1]["env_steps"] == saved[-1] * 256 < 51200


def test_a_process_leaves_the_distributed_runtime_only_where_it_joined_one(monkeypatch):
    """Leaving waits for the other processes (so the first, which holds the coordination
    service, does not end under another's call): only where this process joined a run."""
    from td3_jax.common import library_noise
    from td3_jax.runner import sharding

    left: list[bool] = []
    filtered: list[tuple] = []
    monkeypatch.setattr(library_noise, "filtered_stderr_until_exit", filtered.append)
    monkeypatch.setattr(jax.distributed, "shutdown", lambda: left.append(True))
    monkeypatch.setattr(jax.distributed, "is_initialized", lambda: False)
    sharding.leave_distributed()
    assert left == []
    monkeypatch.setattr(jax.distributed, "is_initialized", lambda: True)
    sharding.leave_distributed()
    assert left == [True] and filtered == [library_noise.LEAVING]
