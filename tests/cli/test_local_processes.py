"""``--local-processes N``: one run as N processes of this host (one per GPU), started, watched
and stopped by the command itself (:mod:`td3_jax.cli.local_processes`)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

import td3_jax
from td3_jax.cli import argv
from td3_jax.cli import local_processes as lp
from td3_jax.common.errors import ConfigError, ProcessLostError

TINY = ["--env", "gymnax/Pendulum-v1", "--num-envs", "8", "--eval-every", "256",
        "--warmup-steps", "64", "--batch-size", "64", "--updates-per-iter", "2",
        "--hidden-sizes", "32", "32", "--eval-envs", "4", "--buffer-size", "512",
        "--replay-shards", "2", "--compile-cache", "off"]  # fmt: skip


@pytest.mark.parametrize("given", [["--local-processes", "2"], ["--local-processes=2"],
                                   ["--local_processes", "2"]])  # fmt: skip
def test_each_process_gets_the_flags_without_the_launcher_and_its_own_join_flags(given):
    args = ["--preset", "t1", *given, "--out", "runs/x"]
    assert lp.child_args(args, 0, 2, 4321) == [
        "--preset", "t1", "--out", "runs/x", "--coordinator-address", "127.0.0.1:4321",
        "--num-processes", "2", "--process-id", "0"]  # fmt: skip
    assert lp.child_args(args, 1, 2, 4321)[-3:] == ["--process-id", "1", "--quiet"]


def test_each_process_sees_its_own_gpu_and_no_join_variables(monkeypatch):
    monkeypatch.setenv("JAX_PROCESS_ID", "7")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    env = lp.process_env("3", 2)
    assert env["CUDA_VISIBLE_DEVICES"] == "3" and "JAX_PROCESS_ID" not in env
    assert env["TD3_JAX_LOCAL_PROCESSES"] == "2"
    assert lp.process_env(None, 4)["CUDA_VISIBLE_DEVICES"] == "2,3"


@pytest.mark.parametrize(
    ("args", "variables", "joins"),
    [(["--seed", "1"], {}, False), (["--num-processes", "2"], {}, True),
     (["--num-processes", "1"], {}, False), (["--num-processes=3"], {}, True),
     ([], {"JAX_NUM_PROCESSES": "1"}, False),
     (["--process_id=1"], {}, True), (["--coordinator-address", "h:1"], {}, True),
     ([], {"JAX_NUM_PROCESSES": "2"}, True), ([], {"TD3_JAX_LOCAL_PROCESSES": "2"}, True),
     (["--local-processes", "2"], {}, False)],
)  # fmt: skip
def test_a_process_joins_others_where_a_join_flag_variable_or_the_launcher_says_so(
    monkeypatch, args, variables, joins
):
    """The launcher itself (--local-processes) joins none: it starts the processes."""
    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID",
                 "TD3_JAX_LOCAL_PROCESSES"):  # fmt: skip
        monkeypatch.delenv(name, raising=False)
    for name, value in variables.items():
        monkeypatch.setenv(name, value)
    assert argv.joins_others(args) is joins


def test_a_process_of_its_own_starts_with_its_signal_handlers_untouched(monkeypatch, capsys):
    """Only a process that joins others takes a first Ctrl-C as a stop request from its
    start (a process of its own raises KeyboardInterrupt, as it always did); both get the
    token the run then uses."""
    import signal as signals

    from td3_jax.cli import interrupts

    for name in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID",
                 "TD3_JAX_LOCAL_PROCESSES"):  # fmt: skip
        monkeypatch.delenv(name, raising=False)
    before = signals.getsignal(signals.SIGINT)
    with interrupts.signals_while_starting(["--seed", "1"]):
        assert signals.getsignal(signals.SIGINT) is before
        assert interrupts.process_stop()[0] is not interrupts.process_stop()[0]  # (new ones)
    with interrupts.signals_while_starting(["--num-processes", "2"]):
        stop, received = interrupts.process_stop()
        assert interrupts.process_stop()[0] is stop
        os.kill(os.getpid(), signals.SIGINT)  # (no KeyboardInterrupt: a stop request)
        time.sleep(0.1)
        assert stop.is_set() and received == [signals.SIGINT]
    assert signals.getsignal(signals.SIGINT) is before
    said = capsys.readouterr().err
    assert "stopping before training starts (Ctrl-C again to stop at once)" in said


def test_a_sigterm_that_stops_a_process_of_several_before_its_run_is_said_as_one(monkeypatch,
                                                                                   capsys):
    """Stopped before its run started (its token set while it joined), a process that a
    SIGTERM stopped ends with 143 and says so (it said "interrupted", with 130)."""
    from td3_jax.cli import app, interrupts

    monkeypatch.setenv("TD3_JAX_LOCAL_PROCESSES", "2")

    def stopped(args):
        raise KeyboardInterrupt

    with interrupts.signals_while_starting(["--seed", "1"]):
        interrupts.process_stop()[1].append(signal.SIGTERM)
        with pytest.raises(SystemExit) as end:
            app.run_reporting_errors(stopped, [])
    assert end.value.code == 143
    assert capsys.readouterr().err.endswith("td3-jax: terminated (SIGTERM)\n")


@pytest.mark.parametrize(("failure", "code", "said"), [
    (lambda: ProcessLostError("process 1 stopped with an error"), 3,
     "td3-jax: error: process 1 stopped with an error\n"),
    (lambda: ValueError("unforeseen"), 1, "ValueError: unforeseen\n"),
])
def test_a_process_of_several_that_fails_says_why_then_leaves_the_others_within_a_limit(
        monkeypatch, capsys, failure, code, said):  # fmt: skip
    """A process of several that fails (another failed: ProcessLostError; or a bug of its own)
    says why first, then waits at most STOPPED_LEAVE_S for the others to leave JAX's runtime
    (JAX's exit hook waited for a process that was gone for five minutes, then aborted with
    134), and ends with the failure's exit status, a traceback's too. The first process, whose
    coordination service the others need until they stop, waits FIRST_PROCESS_LEAVE_S."""
    from td3_jax.cli import app, interrupts
    from td3_jax.common import upstream
    from td3_jax.runner import sharding

    left: list[tuple[float | None, str]] = []
    monkeypatch.setattr(interrupts, "joined_others", lambda: True)
    monkeypatch.setattr(app, "joined_others", lambda: True)
    monkeypatch.setattr(sharding, "leave_distributed",
                        lambda wait_s=None: left.append((wait_s, capsys.readouterr().err)) is None)

    def failing(args):
        raise failure()

    for index, limit in ((1, interrupts.STOPPED_LEAVE_S), (0, interrupts.FIRST_PROCESS_LEAVE_S)):
        monkeypatch.setattr(upstream, "distributed_process_id", lambda index=index: index)
        with pytest.raises(SystemExit) as end:
            app.run_reporting_errors(failing, [])
        assert end.value.code == code
        assert left[-1][0] == limit
        assert left[-1][1].endswith(said)  # (said before it waits for the others)
    assert interrupts.STOPPED_LEAVE_S < interrupts.FIRST_PROCESS_LEAVE_S


def test_a_process_whose_others_do_not_come_to_leave_ends_at_once(monkeypatch, capsys):
    """Past the limit, the failed process ends without them (``os._exit``: the interpreter's
    exit would run JAX's own shutdown, which waits for them for minutes)."""
    from td3_jax.cli import app, interrupts
    from td3_jax.runner import sharding

    ended: list[int] = []

    def os_exit(code):
        ended.append(code)
        raise SystemExit(code)

    monkeypatch.setattr(sharding, "leave_distributed", lambda wait_s=None: False)
    monkeypatch.setattr(interrupts.os, "_exit", os_exit)

    def failing(args):
        raise ProcessLostError("process 1 did not reach the start of chunk 2")

    with pytest.raises(SystemExit):
        app.run_reporting_errors(failing, [])
    assert ended == [3]


def test_a_broken_pipe_in_a_process_of_several_ends_it_with_141_leaving_the_others(
        monkeypatch, tmp_path):  # fmt: skip
    """The reader of a process of several went away (``| head``): exit 141 as a process of its
    own ends, after leaving the others within the limit (JAX's exit would wait for minutes);
    nothing more goes to the closed pipe."""
    from td3_jax.cli import app, interrupts
    from td3_jax.runner import sharding

    left: list[float | None] = []
    monkeypatch.setattr(app, "joined_others", lambda: True)
    monkeypatch.setattr(interrupts, "joined_others", lambda: False)
    monkeypatch.setattr(sharding, "leave_distributed", lambda wait_s=None: not left.append(wait_s))
    saved = os.dup(1)
    try:
        with pytest.raises(SystemExit) as end:
            app.run_reporting_errors(lambda args: (_ for _ in ()).throw(BrokenPipeError()), [])
        os.write(1, b"to /dev/null\n")  # (stdout now writes nowhere: no second error)
    finally:
        os.dup2(saved, 1)
        os.close(saved)
    assert end.value.code == 141 and left == [interrupts.STOPPED_LEAVE_S]


def test_a_process_of_its_own_raises_an_unforeseen_failure_as_it_came(monkeypatch):
    from td3_jax.cli import app

    monkeypatch.setattr(app, "joined_others", lambda: False)

    def failing(args):
        raise ValueError("unforeseen")

    with pytest.raises(ValueError, match=r"^unforeseen$"):
        app.run_reporting_errors(failing, [])


def test_a_launched_process_resumes_with_the_flag_that_started_it(monkeypatch, tmp_path):
    """The run directory does not record how many processes ran it: the resume line a
    process of --local-processes 3 prints names the flag (one of its own names none)."""
    from td3_jax.runner.rundir import resume_command

    monkeypatch.delenv("TD3_JAX_LOCAL_PROCESSES", raising=False)
    assert resume_command(tmp_path / "r") == f"td3-jax train --out {tmp_path / 'r'} --resume"
    monkeypatch.setenv("TD3_JAX_LOCAL_PROCESSES", "3")
    assert resume_command(tmp_path / "r") == (f"td3-jax train --out {tmp_path / 'r'} --resume "
                                              "--local-processes 3")  # fmt: skip
    assert resume_command(tmp_path / "r", " --total-steps 8") == (
        f"td3-jax train --out {tmp_path / 'r'} --resume --total-steps 8 --local-processes 3")


def test_a_process_started_by_hand_resumes_with_its_own_join_flags(monkeypatch, tmp_path):
    """A process of several started by hand (its join flags typed) resumes as it started: the
    line says that each process gives its own (their values differ per process)."""
    import jax

    from td3_jax.runner.rundir import resume_command

    monkeypatch.delenv("TD3_JAX_LOCAL_PROCESSES", raising=False)
    monkeypatch.setattr(jax.distributed, "is_initialized", lambda: True)
    assert resume_command(tmp_path / "r") == (
        f"td3-jax train --out {tmp_path / 'r'} --resume in each process, with its own "
        "--coordinator-address, --num-processes and --process-id")


@pytest.mark.parametrize(
    ("visible", "gpus"), [("0,1", ["0", "1"]), ("2, 5", ["2", "5"]), ("", []), ("-1", [])]
)
def test_the_gpus_are_those_cuda_visible_devices_names(monkeypatch, visible, gpus):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
    assert lp.local_gpus() == gpus


def test_without_nvidia_smi_the_gpus_are_those_the_driver_lists(monkeypatch, tmp_path):
    """A container with the NVIDIA driver and not its tools: the GPUs are the driver's folders
    (one per PCI address; ids 0 to N - 1, as CUDA numbers them); without the driver, none."""
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.setattr(lp.shutil, "which", lambda name: None)
    monkeypatch.setattr(lp, "DRIVER_GPUS", tmp_path / "absent")
    assert lp.local_gpus() == []
    for address in ("0000:18:00.0", "0000:2a:00.0", "0000:3a:00.0"):
        (tmp_path / address).mkdir()
    monkeypatch.setattr(lp, "DRIVER_GPUS", tmp_path)
    assert lp.local_gpus() == ["0", "1", "2"]


@pytest.mark.parametrize(
    ("count", "args", "visible", "message"),
    [(1, [], "0,1", "--local-processes must be at least 2 (one process per GPU), got 1; leave it "
      "out to train in this process"),
     (2, ["--devices", "2"], "0,1", "--devices does not go with --local-processes: each process "
      "gets one GPU and its own id from it"),
     (2, ["--process-id=0"], "0,1", "--process-id does not go with --local-processes"),
     (2, ["--num_processes", "2"], "0,1", "--num-processes does not go with --local-processes"),
     (3, [], "0,1", "--local-processes 3 needs 3 GPUs; this host shows 2 (0, 1)")],
)  # fmt: skip
def test_what_cannot_run_as_local_processes_is_refused_in_one_line(monkeypatch, count, args,
                                                                   visible, message):  # fmt: skip
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
    with pytest.raises(ConfigError) as err:
        lp.check_local_processes(count, args)
    assert str(err.value).startswith(message)


def test_a_host_without_gpus_runs_cpu_processes():
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    code = "from td3_jax.cli import local_processes as lp; print(lp.check_local_processes(2, []))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=60)  # fmt: skip
    assert out.stdout.strip() == "[]", out.stderr


def _sleeper(seconds: float, code: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c",
                             f"import sys, time; time.sleep({seconds}); sys.exit({code})"])


def test_all_ending_well_is_exit_status_0():
    assert lp._wait([_sleeper(0.2, 0), _sleeper(0.5, 0)]) == 0


def test_one_failing_stops_the_others_after_the_grace_and_gives_its_status(monkeypatch, capsys):
    """Process 1 fails (exit 3) while process 0 would wait for it forever (at a collective):
    process 0 is killed once the grace has passed, and the run's status is process 1's."""
    monkeypatch.setattr(lp, "GRACE_S", 0.5)
    procs = [_sleeper(600, 0), _sleeper(0.1, 3)]
    started = time.monotonic()
    assert lp._wait(procs) == 3
    assert time.monotonic() - started < 30
    assert procs[0].returncode == -signal.SIGKILL
    assert ("td3-jax: process 1 ended with exit status 3; stopping process 0, which did not end "
            "within 0.5 s") in capsys.readouterr().err  # fmt: skip


def test_processes_that_fail_alike_are_not_stopped_and_give_the_first_failure():
    """Process 1 fails first; process 0 fails the same way 2 s later, within the grace: it is
    not killed, and the run's status is process 1's."""
    procs = [_sleeper(2.0, 2), _sleeper(0.1, 4)]
    assert lp._wait(procs) == 4 and procs[0].returncode == 2


def test_a_later_process_output_is_shown_marked_only_when_asked_and_never_blocks(capsys):
    """A later process's output is read as it comes (more than a pipe holds, and bytes that
    are not UTF-8, block nothing) and shown marked with its index, its waiting line left out;
    only its last HELD_LINES lines are kept."""
    code = ("import sys; sys.stdout.write('td3-jax: waiting for 2 processes\\n');"
            "sys.stdout.buffer.write(b'\\xff bad byte\\n'); sys.stdout.flush();"
            f"[print('line', i) for i in range({lp.HELD_LINES + 20000})]")  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            errors="replace")  # fmt: skip
    held = lp._Held(proc)
    assert proc.wait(timeout=60) == 0
    held.show(1)
    shown = capsys.readouterr().err.splitlines()
    assert len(shown) == lp.HELD_LINES and shown[-1] == f"[process 1] line {lp.HELD_LINES + 19999}"
    assert not any("waiting for" in line for line in shown)


def test_the_processes_get_the_signals_once_and_are_killed_if_the_launcher_fails():
    """SIGINT and SIGTERM go on as they are, SIGHUP as SIGTERM; leaving on an error of the
    launcher's own kills those still running."""
    code = ("import signal, sys, time\n"
            "got = []\n"
            "for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):\n"
            "    signal.signal(s, lambda n, f: got.append(signal.Signals(n).name))\n"
            "print('ready', flush=True)\n"
            "while len(got) < 3: time.sleep(0.01)\n"
            "print(' '.join(got), flush=True)\n"
            "time.sleep(600)\n")  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    with pytest.raises(RuntimeError), lp._passing_signals([proc]):
        assert proc.stdout.readline() == "ready\n"
        for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            os.kill(os.getpid(), signum)
            time.sleep(0.2)
        assert proc.stdout.readline() == "SIGINT SIGTERM SIGTERM\n"
        raise RuntimeError("the launcher's own failure")
    assert proc.wait(timeout=30) == -signal.SIGKILL


def test_a_process_ends_when_its_launcher_is_killed(tmp_path):
    """A launcher killed outright (SIGKILL: no handler runs) leaves no process behind: Linux
    sends each a SIGTERM as its parent ends."""
    if not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux's")
    pids = tmp_path / "pid"
    launcher = ("import subprocess, sys, time\n"
                "from td3_jax.cli import local_processes as lp\n"
                "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(600)'],"
                " process_group=0, preexec_fn=lp._ends_with_parent())\n"
                f"open({str(pids)!r}, 'w').write(str(child.pid))\n"
                "time.sleep(600)\n")  # fmt: skip
    parent = subprocess.Popen([sys.executable, "-c", launcher])
    deadline = time.monotonic() + 60
    while not pids.exists() or not pids.read_text():
        assert time.monotonic() < deadline
        time.sleep(0.1)
    child = int(pids.read_text())
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 30
    while _alive(child):
        assert time.monotonic() < deadline, "the process outlived its launcher"
        time.sleep(0.1)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return not open(f"/proc/{pid}/stat").read().split()[2] == "Z"  # (a zombie has ended)


def test_the_processes_do_not_import_modules_of_the_folder_they_start_in(tmp_path, monkeypatch):
    """A ``jax.py`` (or an old td3-jax checkout) in the current folder is not what the
    processes import: they start with ``python -P``."""
    (tmp_path / "td3_jax").mkdir()
    (tmp_path / "td3_jax" / "__main__.py").write_text("print('the folder s own td3_jax')\n")
    monkeypatch.chdir(tmp_path)
    started, real = [], subprocess.Popen
    monkeypatch.setattr(lp.subprocess, "Popen", lambda cmd, **kw: started.append(cmd) or
                        real([sys.executable, "-c", "pass"], stdout=kw.get("stdout"),
                             text=True))  # fmt: skip
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert lp.run_local_processes("train", ["--seed", "1"], 2) == 0
    assert [cmd[:4] for cmd in started] == [[sys.executable, "-P", "-m", "td3_jax"]] * 2
    out, _ = real([*started[0][:4], "--version"], stdout=subprocess.PIPE,
                  text=True).communicate(timeout=120)  # fmt: skip
    assert out.startswith("td3-jax ") and "folder" not in out


def test_a_killed_process_gives_the_shells_status():
    assert lp._exit_status(-signal.SIGKILL) == 137 and lp._exit_status(3) == 3


def _train(args: list[str], env: dict, **kw) -> subprocess.Popen:
    kw = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, **kw}
    return subprocess.Popen([sys.executable, "-m", "td3_jax", "train", *args], env=env,
                            text=True, **kw)


def _records(run_dir) -> list[dict]:
    return [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.timeout(600)
@pytest.mark.processes
def test_local_processes_give_the_numbers_of_one_process_over_as_many_devices(tmp_path):
    """Two CPU processes started by --local-processes 2 train what one process of two devices
    trains (the records agree to float rounding: the collectives differ); only the first
    process shows its progress and the run's last line."""
    from benchmarks.multiprocess import compare

    env = {**os.environ, "JAX_PLATFORMS": "cpu", "CUDA_VISIBLE_DEVICES": ""}
    flags = [*TINY, "--total-steps", "512"]
    two = _train([*flags, "--local-processes", "2", "--out", str(tmp_path / "two")], env)
    forced = {**env, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    one = _train([*flags, "--devices", "2", "--quiet", "--out", str(tmp_path / "one")], forced)
    (out, err), (_, one_err) = two.communicate(timeout=500), one.communicate(timeout=500)
    assert two.returncode == 0 and one.returncode == 0, err[-2000:] + one_err[-2000:]
    assert out.startswith("td3-jax: starting 2 processes on this host's CPU (no GPU found), "
                          "joined at 127.0.0.1:")  # fmt: skip
    assert out.count("done: 512 env steps") == 1 and "[process 1]" not in out + err
    result = compare(_records(tmp_path / "two"), _records(tmp_path / "one"), 1e-4, 1e-5)
    assert result["equal"], result


@pytest.mark.timeout(600)
@pytest.mark.processes
def test_a_ctrl_c_stops_every_process_once_after_a_checkpointed_chunk(tmp_path):
    """SIGINT to the command (a terminal's Ctrl-C) reaches each process once, through it: all
    stop after the same chunk, checkpointed, exit status 130, and the line saying what the run
    directory holds is shown once (the second process's, the same, is not)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "CUDA_VISIBLE_DEVICES": ""}
    run = tmp_path / "run"
    proc = _train([*TINY, "--total-steps", "51200", "--local-processes", "2", "--quiet",
                   "--out", str(run)], env)  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while not (run / "metrics.jsonl").exists() or not (run / "metrics.jsonl").read_text():
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=200)
    finally:
        proc.kill()
    assert proc.returncode == 130, err[-3000:]
    assert err.count("interrupted; the newest checkpoint is") == 1, err[-3000:]
    saved = sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit())
    assert saved and _records(run)[-1]["env_steps"] == saved[-1] * 256 < 51200


#: A run whose chunk after the first record takes about a minute on 2 CPU cores.
LONG_CHUNKS = ["--env", "gymnax/Pendulum-v1", "--num-envs", "8", "--eval-every", "4096",
               "--warmup-steps", "64", "--batch-size", "2048", "--updates-per-iter", "4",
               "--hidden-sizes", "512", "512", "--eval-envs", "4", "--buffer-size", "8192",
               "--replay-shards", "2", "--compile-cache", "off", "--total-steps", "40960"]


@pytest.mark.timeout(600)
@pytest.mark.processes
def test_a_ctrl_c_mid_chunk_is_said_at_once_and_a_second_stops_at_once(tmp_path):
    """Mid-chunk, a process of several says its Ctrl-C when it comes, not once the chunk has
    ended (a copy of the chunk's results ran no signal handler: the line came with the chunk's
    record, 115 s later), and a second Ctrl-C ends the processes before the chunk does."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "CUDA_VISIBLE_DEVICES": ""}
    proc = _train([*LONG_CHUNKS, "--local-processes", "2", "--out", str(tmp_path / "run")], env,
                  stderr=subprocess.STDOUT)  # fmt: skip
    lines: list[tuple[float, str]] = []
    reader = threading.Thread(target=lambda: lines.extend((time.monotonic(), line)
                                                          for line in proc.stdout))  # fmt: skip
    reader.start()
    try:
        first = _wait_for(lines, "env steps/s", proc)  # (the early evaluation's record)
        proc.send_signal(signal.SIGINT)
        said = _wait_for(lines, "interrupted: stopping once the chunk", proc)
        records = [line for _, line in lines if "env steps/s" in line]
        time.sleep(2)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)
        stopped = time.monotonic()
    finally:
        proc.kill()
        reader.join(10)
    assert proc.returncode == 130, "".join(line for _, line in lines)[-3000:]
    assert said - first < 20 and len(records) == 1, records  # (said within the chunk)
    assert [line for _, line in lines if "env steps/s" in line] == records  # (stopped in it)
    assert stopped - said < 30


def _wait_for(lines: list[tuple[float, str]], text: str, proc: subprocess.Popen) -> float:
    """When the first line holding ``text`` came (waiting up to 300 s for it)."""
    deadline = time.monotonic() + 300
    while not any(text in line for _, line in list(lines)):
        assert time.monotonic() < deadline and proc.poll() is None, lines[-20:]
        time.sleep(0.05)
    return next(at for at, line in list(lines) if text in line)


@pytest.mark.timeout(400)
@pytest.mark.processes
def test_a_ctrl_c_while_the_processes_start_stops_them_all_before_training(tmp_path):
    """SIGINT to the command while its processes import, join and compile: it is neither lost
    (it could be, raised inside a finalizer Python discards) nor does one process leave the
    other waiting. Both stop before training, with nothing written, exit status 130, and the
    line is shown once."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "CUDA_VISIBLE_DEVICES": ""}
    run = tmp_path / "run"
    proc = _train([*TINY, "--total-steps", "51200", "--local-processes", "2", "--quiet",
                   "--out", str(run)], env)  # fmt: skip
    try:
        time.sleep(6)  # (the processes import JAX and join on 2 cores)
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 130, err[-3000:]
    assert err.count("interrupted before the first checkpoint") == 1, err[-3000:]
    assert "Traceback" not in err and not (run / "metrics.jsonl").exists(), err[-3000:]


@pytest.mark.parametrize(
    ("args", "count"),
    [(["--local-processes", "2"], 2), (["--seed", "1", "--local-processes=4"], 4), ([], None),
     (["--local_processes=3"], 3), (["--local-processes", "2", "--local-processes", "3"], 3)],
)
def test_the_count_is_read_from_the_flag_in_either_form(args, count):
    assert lp.asked_count(args) == count


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--local-processes", "two"], "--local-processes takes a number of processes, e.g. "
      "--local-processes 2; got 'two'"),
     (["--local-processes"], "--local-processes takes a number of processes, e.g. "
      "--local-processes 2")],
)  # fmt: skip
def test_a_count_that_is_not_a_number_is_refused_in_one_line(args, message):
    with pytest.raises(ConfigError) as err:
        lp.asked_count(args)
    assert str(err.value) == message


_CHECKOUT = os.path.dirname(os.path.dirname(os.path.abspath(td3_jax.__file__)))
_LAUNCH_ALONE = """
import os
import sys
from td3_jax.cli import app, local_processes
asked = []
listed = local_processes.local_gpus
local_processes.local_gpus = lambda: asked.append(1) or listed()
status = int(os.environ.get("FAKE_STATUS", "0"))
local_processes.run_local_processes = lambda *a: print("launched", *a) or status
try:
    app.main(sys.argv[1:])
except SystemExit as end:
    print("exit", end.code)
print("jax imported:", "jax" in sys.modules, "GPUs asked:", len(asked))
"""


def test_the_command_starts_its_processes_before_importing_jax(tmp_path):
    """The launching process imports neither JAX nor any environment (seconds that each
    process would wait for it); the processes check the flags themselves. Without --out it
    makes one folder for them all, and asks for the host's GPUs once."""
    out = subprocess.run([sys.executable, "-c", _LAUNCH_ALONE, "sweep", "--preset", "t1",
                          "--local-processes", "2"], capture_output=True, text=True,
                         timeout=120, cwd=tmp_path,
                         env={**os.environ, "PYTHONPATH": _CHECKOUT,
                              "CUDA_VISIBLE_DEVICES": "3,5"})  # fmt: skip
    note, *rest = out.stdout.splitlines()
    assert note.startswith("no --out given: the run goes to runs/t1-"), out.stderr
    chosen = note.rsplit(" ", 1)[1]  # (one folder for all the processes, chosen here)
    assert rest == [
        f"launched sweep ['--preset', 't1', '--local-processes', '2', '--out', '{chosen}'] 2 "
        "['3', '5']", "exit 0", "jax imported: False GPUs asked: 1"], out.stderr  # fmt: skip
    assert (tmp_path / chosen).is_dir()


def test_processes_that_refuse_leave_no_folder(tmp_path):
    """Processes that end with a refusal (status 2) before writing: the folder chosen for them
    goes, with the runs/ made for it."""
    out = subprocess.run([sys.executable, "-c", _LAUNCH_ALONE, "train", "--local-processes",
                          "2"], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         env={**os.environ, "PYTHONPATH": _CHECKOUT, "FAKE_STATUS": "2",
                              "CUDA_VISIBLE_DEVICES": "0,1"})  # fmt: skip
    assert "exit 2" in out.stdout.splitlines(), out.stderr
    assert not (tmp_path / "runs").exists()


def test_its_help_is_the_subcommands_and_a_bad_count_one_line(capsys):
    from td3_jax.cli import app

    with pytest.raises(SystemExit) as end:
        app.main(["train", "--local-processes", "x"])
    assert end.value.code == 2
    assert capsys.readouterr().err.strip() == (
        "td3-jax: error: --local-processes takes a number of processes, e.g. --local-processes "
        "2; got 'x'")  # fmt: skip
    with pytest.raises(SystemExit) as end:
        app.main(["train", "--local-processes", "2", "--help"])
    assert end.value.code == 0 and "--local-processes" in capsys.readouterr().out
