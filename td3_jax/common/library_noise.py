"""What the libraries write straight to the process's stderr, below Python, where td3-jax says
it better itself: XLA's slow-compile alarm (a banner of asterisks asking for a bug report, while
a robot's physics compiles on a CPU, which takes minutes) and MLIR's lines about a stored
program it cannot deserialise (the program store warns of the entry itself and traces the
programs again), and XLA's notice that GSPMD is to be deprecated (td3-jax chooses GSPMD for
MuJoCo Warp split over several devices, which Shardy cannot compile: ``envs.per_device``), its
GPU autotuner's warnings about its own timer;
and, as the processes of a ``jax.distributed`` run leave it, its coordination service's
warning that it stopped watching them (:data:`LEAVING`, for the rest of the process:
:func:`filtered_stderr_until_exit`).

:func:`filtered_stderr` passes the process's file descriptor 2 through a small filter process
for the span of a block (``python -I -S``, stdlib only): every other line goes through as it
was written, in order, Python's own writes included; the alarm becomes one line of td3-jax's
(:data:`STILL_COMPILING`, once per block), MLIR's lines are dropped. The filter is a process,
not a thread, so that a process ending at once (a second Ctrl-C's ``os._exit``, an abort)
loses nothing it wrote: the filter drains the pipe until its last writer is gone. It runs
in a process group of its own, out of reach of Ctrl-C and of the SIGTERM
that ``timeout`` sends to a whole process group, so that the lines the process says as it stops
still get through.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator

__all__ = ["ALARM", "COORDINATION_FATAL", "DROPPED", "LEAVING", "PROCESS_LOST",
           "STILL_COMPILING", "drain_filters", "filtered_stderr", "filtered_stderr_until_exit"]

#: The text of XLA's slow-compile alarm: its line becomes :data:`STILL_COMPILING` (once).
ALARM = "Very slow compile?"
#: Text of the lines dropped (besides lines of asterisks alone, the alarm's banner): the
#: alarm's log line, MLIR's deserialisation errors, XLA's GSPMD notice and its GPU autotuner's
#: warnings about the accuracy of its timer.
DROPPED = (
    "slow_operation_alarm.cc",
    'loc("-":0:0): error: ',  # (MLIR's errors in a serialised artifact: "invalid Type index",
    "failed to deserialize portable artifact",  # "invalid Attribute index", ...)
    "GSPMD sharding propagation is going to be deprecated",
    "Delay kernel timed out",  # (XLA's GPU autotuner: its timer's accuracy, while it compiles)
)
#: Text of the lines of JAX's coordination service as the processes of a ``jax.distributed`` run
#: leave it (a warning that its watch of the other processes was cancelled, with its gRPC
#: details and source trace), dropped from the moment a process leaves it
#: (:func:`filtered_stderr_until_exit`).
LEAVING = (
    "WatchTasksAsync failed",
    "Additional GRPC error information from remote target coordination_service",
    ":CANCELLED:",  # (gRPC's status lines: the watch cancelled, or its service gone)
    ":UNAVAILABLE:",
    "=== Source Location Trace: ===",
    "distributed_runtime/rpc/grpc_util.h",
)
#: The line that stands for XLA's slow-compile alarm.
STILL_COMPILING = (
    "td3-jax: still compiling (a robot's physics takes XLA minutes to compile on a CPU; the "
    "compile cache keeps the result for the next run)"
)

#: Text of the line with which JAX's coordination service ends a process of several (a C++
#: check failure: a stack trace follows, then the process aborts, exit status 134) where
#: another did not join in time or stopped answering (:data:`PROCESS_LOST`).
COORDINATION_FATAL = "Terminating process because the JAX distributed service detected fatal"
#: The line that stands for it and its stack trace.
PROCESS_LOST = (
    "td3-jax: error: JAX's coordination service ends this process (exit status 134): another "
    "process of the run did not join in time, or stopped answering (killed or crashed: its own "
    "output says why, where it could); checkpoints already written are kept"
)

# The filter process (arguments: STILL_COMPILING, ALARM or "", a fatal line's text or "", the
# line that stands for it, *DROPPED): lines of stdin to stdout as bytes (any encoding passes),
# each flushed; with the alarm, lines of asterisks alone (its banner) are dropped too, and an
# empty line right after a dropped one (the banner ends with one); from a fatal line on, its
# own line stands for the rest (a stack trace).
_FILTER = r"""
import sys
ours, alarm, fatal, fatal_ours, *dropped = [text.encode() for text in sys.argv[1:]]
dropped = [text for text in (alarm, *dropped) if text]
said, after, ended, out = False, False, False, sys.stdout.buffer
for line in sys.stdin.buffer:
    if ended:
        continue
    if fatal and fatal in line:
        out.write(fatal_ours + b"\n")
        out.flush()
        ended = True
        continue
    stripped = line.strip()
    drop = bool(alarm and stripped and not stripped.strip(b"*")) or any(t in line for t in dropped)
    if drop and alarm and alarm in line and not said:
        said = True
        out.write(ours + b"\n")
    elif not drop and (stripped or not after):
        out.write(line)
    after = drop
    out.flush()
"""


@contextlib.contextmanager
def filtered_stderr(dropped: tuple[str, ...] = DROPPED) -> Iterator[None]:
    """Passes file descriptor 2 through the filter process for the block (see the module's
    docstring), dropping the lines that hold any text of ``dropped``; where there is no fd 2
    or the filter cannot start, the block runs as it is."""
    started = _start_filter(dropped)
    if started is None:
        yield
        return
    saved, child = started
    os.dup2(child.stdin.fileno(), 2)
    try:
        yield
    finally:
        _flush_stderr()
        os.dup2(saved, 2)
        os.close(saved)
        child.stdin.close()  # its last line written, the filter ends
        with contextlib.suppress(subprocess.TimeoutExpired):  # (a child process of the
            child.wait(timeout=5)  # block may still hold the pipe: the filter outlives it)


#: The filters started by :func:`filtered_stderr_until_exit` (each ends with the process).
_UNTIL_EXIT: list[subprocess.Popen] = []


def filtered_stderr_until_exit(dropped: tuple[str, ...],
                               fatal: tuple[str, str] | None = None) -> None:  # fmt: skip
    """Passes file descriptor 2 through the filter process, dropping the lines that hold any
    text of ``dropped``, for the rest of this process's life: for lines that libraries write
    on their own threads as the process ends (nothing where the filter cannot start).
    ``fatal``: ``(text, line)``: from a line holding ``text`` on (a library's fatal error,
    before its stack trace and abort), ``line`` stands for the rest."""
    started = _start_filter(dropped, fatal, alarm=False)
    if started is None:
        return
    saved, child = started
    os.dup2(child.stdin.fileno(), 2)
    os.close(saved)  # (the filter writes to its own copy; it ends once fd 2 closes)
    if not _UNTIL_EXIT:
        atexit.register(drain_filters)
    _UNTIL_EXIT.append(child)


def drain_filters(timeout_s: float = 5.0) -> None:
    """Lets the filters of :func:`filtered_stderr_until_exit` write out all they were given
    before the process ends (else its last line could come after the shell's prompt): fd 2
    then writes nowhere, and each filter is waited for up to ``timeout_s``."""
    if not _UNTIL_EXIT:
        return
    _flush_stderr()
    os.dup2(os.open(os.devnull, os.O_WRONLY), 2)
    for child in reversed(_UNTIL_EXIT):  # (a later filter writes into an earlier one)
        child.stdin.close()
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.wait(timeout=timeout_s)
    _UNTIL_EXIT.clear()


def _start_filter(dropped: tuple[str, ...], fatal: tuple[str, str] | None = None,
                  alarm: bool = True) -> tuple[int, subprocess.Popen] | None:  # fmt: skip
    """``(a copy of fd 2, the filter process writing to it)``, or ``None`` where either cannot
    be had. The filter drops lines with any text of ``dropped``; from a line holding
    ``fatal[0]`` on, ``fatal[1]`` stands for the rest; ``alarm``: XLA's slow-compile alarm
    becomes :data:`STILL_COMPILING` and its banner is dropped."""
    _flush_stderr()
    try:
        saved = os.dup(2)
    except OSError:  # (no fd 2: a daemon's)
        return None
    try:
        child = subprocess.Popen([sys.executable, "-I", "-S", "-c", _FILTER, STILL_COMPILING,
                                  ALARM if alarm else "", *(fatal or ("", "")), *dropped],
                                 stdin=subprocess.PIPE, stdout=saved,
                                 stderr=saved, process_group=0)  # fmt: skip
    except OSError:
        os.close(saved)
        return None
    return saved, child


def _flush_stderr() -> None:
    """Writes out what Python holds for stderr (none where it is closed or missing)."""
    with contextlib.suppress(Exception):
        sys.stderr.flush()
