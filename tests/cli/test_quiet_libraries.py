"""td3-jax speaks, not its libraries: XLA's slow-compile alarm becomes one line of td3-jax's,
MLIR's lines about a damaged stored program are dropped where td3-jax warns of it itself (and
XLA's GSPMD notice where td3-jax chose GSPMD), and
render checks ``MUJOCO_GL`` before MuJoCo's import refuses it in its own words."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
from support import TINY_FLAGS, assert_one_line_error, main, python

from td3_jax.cli import app as cli
from td3_jax.common.library_noise import PROCESS_LOST, STILL_COMPILING

#: What XLA writes when a compile takes minutes (jaxlib 0.9, a T1 chunk on a CPU).
ALARM = (
    "E1129 04:22:11.256265   21347 slow_operation_alarm.cc:73] \n"
    "********************************\n"
    "[Compiling module jit_call for CPU] Very slow compile? If you want to file a bug, run with "
    "envvar XLA_FLAGS=--xla_dump_to=/tmp/foo and attach the results.\n"
    "********************************\n"
    "\n"
)
#: What MLIR writes when a stored program's bytes are damaged (then JAX raises).
MLIR = (
    'loc("-":0:0): error: invalid Type index: 16047\n'
    'loc("-":0:0): error: invalid Attribute index: 15641\n'
    "error: failed to deserialize portable artifact using StableHLO_v1.17.0\n"
)
#: What XLA writes compiling with GSPMD (MuJoCo Warp split over two GPUs, jax 0.11.2).
GSPMD = (
    "W1129 13:40:46.478723   10123 sharding_propagation.cc:3197] GSPMD sharding propagation is "
    "going to be deprecated and not supported in the future. Please consider migrating to "
    "Shardy (https://openxla.org/shardy/getting_started_jax#migrating_to_shardy).\n"
)
#: What XLA's GPU autotuner writes when its timer is inaccurate (two H200s, jax 0.11.2).
AUTOTUNER = (
    "W1130 04:12:21.074842    4162 cuda_timer.cc:88] Delay kernel timed out: measured time has "
    "sub-optimal accuracy. There may be a missing warmup execution, please investigate in "
    "Nsight Systems.\n"
)

FILTERED = f"""
import os, sys
from td3_jax.common.library_noise import filtered_stderr
print("before", file=sys.stderr, flush=True)
with filtered_stderr():
    os.write(2, {ALARM.encode()!r})
    print("ours, in order", file=sys.stderr, flush=True)
    os.write(2, {MLIR.encode()!r} + b"a line of its own\\n\\n" + {GSPMD.encode()!r})
    os.write(2, {AUTOTUNER.encode()!r})
    os.write(2, {ALARM.encode()!r})  # (said once)
    sys.stderr.write("unfinished")
print(" line", file=sys.stderr)
"""


def test_the_alarm_becomes_one_line_and_mlirs_lines_go_while_the_rest_passes_in_order():
    proc = python(FILTERED)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == (
        f"before\n{STILL_COMPILING}\nours, in order\na line of its own\n\nunfinished line\n"
    )


#: What JAX's coordination service writes as the processes of a jax.distributed run leave it
#: (two H200s, jax 0.11.2, after the run's last line).
LEAVING = (
    "W1130 01:39:11.257417    1170 pjrt_client.cc:1605] WatchTasksAsync failed for task 0: "
    "CANCELLED: CANCELLED\n"
    "Additional GRPC error information from remote target coordination_service while calling "
    "/xla.coordination.CoordinationService/WatchTasks:\n"
    ":CANCELLED:CANCELLED [type.googleapis.com/tensorflow.DerivedStatus='']\n"
    "=== Source Location Trace: ===\n"
    "external/xla+/xla/tsl/distributed_runtime/rpc/grpc_util.h:89\n"
    "\n"
    ":UNAVAILABLE:failed to connect to all addresses; last error: UNKNOWN: ipv4:127.0.0.1:43645: "
    "Failed to connect to remote host: Connection refused\n"
)


def test_the_coordination_services_lines_go_once_the_processes_leave_and_only_then():
    """Kept while training (news then), dropped from the moment the process leaves the runtime
    to its end (:data:`LEAVING`: the service's threads write them as the process ends); the
    process's own lines still pass, in order, the last one too."""
    code = ("import os, sys\n"
            "from td3_jax.common.library_noise import LEAVING, filtered_stderr_until_exit\n"
            f"os.write(2, {LEAVING.splitlines()[0].encode()!r} + b'\\n')\n"
            "filtered_stderr_until_exit(LEAVING)\n"
            f"os.write(2, {LEAVING.encode()!r} + b'ours\\n')\n"
            "print('and the last', file=sys.stderr)\n")  # fmt: skip
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == LEAVING.splitlines()[0] + "\nours\nand the last\n"


#: What JAX's coordination service writes as it ends a process whose partner was killed (two
#: CPU processes, jax 0.10.2): the check failure's line, its status, then a stack trace.
COORDINATION_ABORT = (
    "F1130 04:10:05.087866    9400 client.h:80] Terminating process because the JAX distributed "
    "service detected fatal errors. This most likely indicates that another task died; see the "
    "other task logs for more details. absl::Status: UNAVAILABLE: The following tasks are "
    "unhealthy (stopped sending heartbeats):\n1\nThe tasks have crashed.\n"
    "*** Check failure stack trace: ***\n"
    "    @     0x7f4d64040634  absl::lts_20260107::log_internal::LogMessage::SendToLog()\n"
)


def test_the_coordination_services_fatal_end_is_one_line_of_td3_jaxs_and_the_process_aborts():
    """A process of several that JAX's coordination service ends (another was killed, or did
    not join in time) says so in one line instead of a C++ stack trace; what it wrote before
    passes, and a second filter chained after it (the leave's) passes it on."""
    code = ("import os, sys\n"
            "from td3_jax.common import library_noise as noise\n"
            "noise.filtered_stderr_until_exit((), fatal=(noise.COORDINATION_FATAL, "
            "noise.PROCESS_LOST))\n"
            "print('td3 before', file=sys.stderr, flush=True)\n"
            "noise.filtered_stderr_until_exit(noise.LEAVING)\n"
            f"os.write(2, {COORDINATION_ABORT.encode()!r})\n"
            "os.write(2, b'more of the trace\\n')\n"
            "os.abort()\n")  # fmt: skip
    proc = python(code)
    assert proc.returncode == -signal.SIGABRT
    assert proc.stderr == f"td3 before\n{PROCESS_LOST}\n"


def test_chained_filters_for_the_process_life_pass_its_lines_and_drain_at_its_end():
    """A process of several runs with two filters at its end (the coordination service's fatal
    line, then the leave's lines): its own lines pass in order, a line of asterisks too (that
    rule is the compile alarm's banner, dropped only while compiling), and both filters drain
    at once as it exits (the later writes into the earlier: drained first, not waited out)."""
    code = ("import os, sys\n"
            "from td3_jax.common import library_noise as noise\n"
            "noise.filtered_stderr_until_exit((), fatal=(noise.COORDINATION_FATAL, "
            "noise.PROCESS_LOST))\n"
            "noise.filtered_stderr_until_exit(noise.LEAVING)\n"
            "print('*****', file=sys.stderr)\n"
            "print('ours', file=sys.stderr)\n"
            "print('the last', file=sys.stderr)\n")  # fmt: skip
    start = time.monotonic()
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == "*****\nours\nthe last\n"
    assert time.monotonic() - start < 4  # (a filter waited for was given 5 s)


def test_a_process_ending_at_once_inside_the_block_loses_nothing_it_wrote():
    """A second Ctrl-C ends the process with os._exit while the filter holds its stderr: the
    line said just before still arrives (the filter is a process that drains the pipe)."""
    code = ("import os, sys\nfrom td3_jax.common.library_noise import filtered_stderr\n"
            "with filtered_stderr():\n"
            "    print('td3-jax: interrupted again: stopping now', file=sys.stderr, flush=True)\n"
            "    os._exit(130)\n")  # fmt: skip
    proc = python(code)
    assert proc.returncode == 130
    assert proc.stderr == "td3-jax: interrupted again: stopping now\n"


def test_a_signal_to_the_whole_process_group_leaves_the_filter_running():
    """Ctrl-C in a terminal, or ``timeout``, signals a whole process group, at once: what the
    process says as it stops still arrives (the filter, killed with it, lost that line)."""
    code = ("import os, signal, sys, time\n"
            "from td3_jax.common.library_noise import filtered_stderr\n"
            "say = lambda text: print(text, file=sys.stderr, flush=True)\n"
            "signal.signal(signal.SIGTERM, lambda *_: say('td3-jax: terminated (SIGTERM)'))\n"
            # (Python's own Ctrl-C: a process started with SIGINT ignored, as a test runner's
            # worker may leave it for its children, would never raise KeyboardInterrupt)
            "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
            "with filtered_stderr():\n"
            "    os.killpg(os.getpgid(0), signal.SIGTERM)\n"
            "    time.sleep(0.2)\n"
            "    try:\n"
            "        os.killpg(os.getpgid(0), signal.SIGINT)\n"
            "        time.sleep(5)\n"
            "    except KeyboardInterrupt:\n"
            "        say('td3-jax: interrupted')\n")  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, process_group=0)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == "td3-jax: terminated (SIGTERM)\ntd3-jax: interrupted\n"


def _exit_code(args: list[str]) -> int:
    try:
        cli.main(args)
    except SystemExit as exit_:
        return exit_.code if isinstance(exit_.code, int) else 1
    return 0


@pytest.mark.runs
def test_a_damaged_stored_program_is_td3_jaxs_one_warning_without_mlirs_lines(tmp_path, capfd):
    """The program store's entry, its chunk's bytes flipped, is warned of and traced again;
    MLIR's own lines about it, written below Python, do not reach stderr."""
    cache = tmp_path / "cache"
    flags = [*TINY_FLAGS, "--quiet", "--compile-cache", str(cache)]
    assert _exit_code(["train", *flags, "--out", str(tmp_path / "first")]) == 0
    (chunk,) = (cache / "programs").glob("*/chunk.bin")
    data = bytearray(chunk.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 40] = bytes(b ^ 0xFF for b in data[middle : middle + 40])
    chunk.write_bytes(bytes(data))
    capfd.readouterr()
    assert _exit_code(["train", *flags, "--out", str(tmp_path / "second")]) == 0
    err = capfd.readouterr().err
    assert "td3-jax: warning: ignored the unusable traced programs in" in err, err
    assert 'loc("-"' not in err and "deserialize portable artifact" not in err, err


def test_render_checks_mujoco_gl_before_mujoco_does(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MUJOCO_GL", "bogus")
    code, _, err = main(["render", "--run", str(tmp_path / "run")], capsys)
    assert_one_line_error(code, err, "MUJOCO_GL=bogus is not one of egl, osmesa, glfw", "unset")
    from td3_jax.cli.finished import check_mujoco_gl

    for value in ("", "egl", " OSMesa ", "glfw"):  # (as MuJoCo reads it: any case, trimmed)
        check_mujoco_gl(value, ("egl", "osmesa", "glfw"))
