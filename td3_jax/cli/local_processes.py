"""``--local-processes N``: one ``td3-jax train`` (or ``sweep``) run as N processes of this
host, one per GPU, joined through ``jax.distributed``.

This process starts no JAX backend: it picks a free local port, starts the N processes with
``--coordinator-address/--num-processes/--process-id`` (each seeing only its own GPU through
``CUDA_VISIBLE_DEVICES``; on a host without GPUs, each JAX's CPU device), passes its Ctrl-C,
SIGTERM and SIGHUP on to them, and ends with their exit status. One process per GPU is faster
than one process of several GPUs for MuJoCo Warp: a process's GPUs take turns at Warp's
host-side calls.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import functools
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from td3_jax.cli.argv import flag_name
from td3_jax.common import runtime
from td3_jax.common.errors import ConfigError

__all__ = [
    "DRIVER_GPUS",
    "FLAG",
    "GRACE_S",
    "HELD_LINES",
    "asked_count",
    "check_local_processes",
    "child_args",
    "free_port",
    "local_gpus",
    "main",
    "process_env",
    "run_local_processes",
]

FLAG = "--local-processes"
#: Seconds the other processes get to end by themselves after one fails, before they are
#: stopped (they may be waiting for it at a collective).
GRACE_S = 30.0
#: Lines of each later process's output kept to show where it fails.
HELD_LINES = 2000
_PR_SET_PDEATHSIG = 1  # (linux/prctl.h)
#: Flags that the launcher sets in each process, so not given with --local-processes.
_SET_HERE = ("--coordinator-address", "--num-processes", "--process-id", "--devices")


def asked_count(args: list[str]) -> int | None:
    """The N of ``--local-processes N`` (or ``=N``) in ``args``, the last where it is given
    more than once (as the parser takes any flag); None without it. ConfigError when it is not
    a whole number."""
    count = None
    for i, arg in enumerate(args):
        if flag_name(arg) == FLAG:
            equals, value = arg.partition("=")[1:]
            text = value if equals else (args[i + 1] if i + 1 < len(args) else "")
            try:
                count = int(text, 10)
            except ValueError:
                raise ConfigError(f"{FLAG} takes a number of processes, e.g. {FLAG} 2"
                                  + (f"; got {text!r}" if text else "")) from None  # fmt: skip
    return count


def main(subcommand: str, args: list[str]) -> None:
    """``td3-jax train|sweep ... --local-processes N``, started before anything heavy is
    imported here (JAX, the environments): the processes check the flags themselves, and
    one's message is shown once. Exits with the processes' status."""
    from td3_jax.cli.run_folder import out_chosen_note, remove_if_empty, with_run_directory

    count = asked_count(args)
    assert count is not None, f"{FLAG} not in {args}"
    gpus = check_local_processes(count, args)  # (its own refusals before a folder is made)
    args, chosen_out = with_run_directory(args)  # (one folder for all of them)
    if chosen_out is not None:
        print(out_chosen_note(chosen_out), flush=True)
    status = 1
    try:
        status = run_local_processes(subcommand, args, count, gpus)
    finally:
        if status:
            remove_if_empty(chosen_out)  # (refused or stopped before writing anything)
    raise SystemExit(status)


def check_local_processes(count: int, args: list[str]) -> list[str]:
    """The GPUs for ``count`` processes (empty: a host without GPUs); ConfigError for a count
    below 2, more processes than GPUs, or a flag the launcher sets itself."""
    if count < 2:
        raise ConfigError(f"{FLAG} must be at least 2 (one process per GPU), got {count}; "
                          "leave it out to train in this process")  # fmt: skip
    given = [name for name in _SET_HERE if any(flag_name(a) == name for a in args)]
    if given:
        raise ConfigError(f"{given[0]} does not go with {FLAG}: each process gets one GPU and "
                          "its own id from it")  # fmt: skip
    gpus = local_gpus()
    if gpus and count > len(gpus):
        raise ConfigError(f"{FLAG} {count} needs {count} GPUs; this host shows {len(gpus)} "
                          f"({', '.join(gpus)})")  # fmt: skip
    return gpus[:count]


def local_gpus() -> list[str]:
    """The ids of this host's GPUs as ``CUDA_VISIBLE_DEVICES`` names them (else as
    ``nvidia-smi`` lists them, else 0 to N - 1 for the N GPUs of the NVIDIA driver's
    :data:`DRIVER_GPUS`; none without either)."""
    given = os.environ.get("CUDA_VISIBLE_DEVICES")
    if given is not None:
        return [s.strip() for s in given.split(",") if s.strip() and s.strip() != "-1"]
    smi = shutil.which("nvidia-smi")
    if smi is None:  # (a container may have the driver and not its tools)
        return _driver_gpus()
    try:
        listed = subprocess.run([smi, "--query-gpu=index", "--format=csv,noheader"],
                                capture_output=True, text=True, timeout=60)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in listed.stdout.splitlines() if line.strip().isdigit()]


#: Where the NVIDIA driver lists its GPUs on Linux, a folder each (named by PCI address).
DRIVER_GPUS = Path("/proc/driver/nvidia/gpus")


def _driver_gpus() -> list[str]:
    """``0 .. N-1`` for the N GPUs of :data:`DRIVER_GPUS` (none where it cannot be read)."""
    try:
        count = sum(1 for entry in DRIVER_GPUS.iterdir() if entry.is_dir())
    except OSError:
        return []
    return [str(i) for i in range(count)]


def child_args(args: list[str], index: int, count: int, port: int) -> list[str]:
    """Process ``index``'s flags: ``args`` without ``--local-processes N``, with the join flags
    (processes after the first also ``--quiet``: the first shows the progress)."""
    kept, skip = [], False
    for arg in args:
        if skip:
            skip = False
        elif flag_name(arg) == FLAG:
            skip = "=" not in arg  # (its value is the next argument)
        else:
            kept.append(arg)
    join = ["--coordinator-address", f"127.0.0.1:{port}", "--num-processes", str(count),
            "--process-id", str(index)]  # fmt: skip
    return [*kept, *join, *(["--quiet"] if index else [])]


def process_env(gpu: str | None, count: int) -> dict[str, str]:
    """The environment of one of ``count`` processes: this one's, seeing only ``gpu`` (None:
    as it is), and saying how many were started (:data:`~td3_jax.common.runtime.
    LOCAL_PROCESSES_ENV`: its start-up stops together with the others, its resume line names
    the flag)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")}
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    env[runtime.LOCAL_PROCESSES_ENV] = str(count)
    return env


def run_local_processes(subcommand: str, args: list[str], count: int,
                        gpus: list[str] | None = None) -> int:  # fmt: skip
    """Runs ``td3-jax SUBCOMMAND ARGS`` as ``count`` processes of this host and returns the exit
    status: 0 when all end with 0, else the first failure's (the others stopped, if they do
    not end by themselves within :data:`GRACE_S`). The first process's output is this one's;
    another's is shown only where it ended otherwise than the first (its own failure). The
    processes get this one's SIGINT, SIGTERM and SIGHUP (as SIGTERM), and a SIGTERM when it
    ends before them (Linux), so none is left running without it. ``gpus``: what
    :func:`check_local_processes` gave for these flags (default: it is asked now)."""
    if gpus is None:
        gpus = check_local_processes(count, args)
    port = free_port()
    where = f"one per GPU ({', '.join(gpus)})" if gpus else "on this host's CPU (no GPU found)"
    print(f"td3-jax: starting {count} processes {where}, joined at 127.0.0.1:{port}", flush=True)
    procs: list[subprocess.Popen] = []
    with _passing_signals(procs):  # (before the first starts: none misses a Ctrl-C)
        for i in range(count):
            held = {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT} if i else {}
            procs.append(subprocess.Popen(
                [sys.executable, "-P", "-m", "td3_jax", subcommand,  # (-P: not the cwd's modules)
                 *child_args(args, i, count, port)],
                env=process_env(gpus[i] if gpus else None, count), text=True, errors="replace",
                process_group=0, preexec_fn=_ends_with_parent(), **held))  # fmt: skip
        outputs = [_Held(proc) if i else None for i, proc in enumerate(procs)]
        status = _wait(procs)
    for i, output in enumerate(outputs):
        if output is not None and procs[i].returncode not in (0, procs[0].returncode):
            output.show(i)
    return status


class _Held:
    """A process's output, read as it comes (so its pipe never fills) and its last
    :data:`HELD_LINES` lines kept."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: collections.deque[str] = collections.deque(maxlen=HELD_LINES)
        self.reader = threading.Thread(target=self._read, args=(proc.stdout,), daemon=True)
        self.reader.start()

    def _read(self, stream: Any) -> None:
        try:
            for line in stream:
                self.lines.append(line.rstrip("\n"))
        except (OSError, ValueError):  # (the pipe closed under it: what was read is kept)
            pass

    def show(self, index: int) -> None:
        """Prints the output of process ``index`` on stderr, each line marked with it (not its
        line saying it waits for the others)."""
        self.reader.join(timeout=5)
        for line in list(self.lines):
            if not line.startswith("td3-jax: waiting for"):
                print(f"[process {index}] {line}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def _passing_signals(procs: list[subprocess.Popen]) -> Iterator[None]:
    """Within: each SIGINT or SIGTERM this process gets goes to every process of ``procs``
    still running (once: they are in their own process group, so a terminal's Ctrl-C reaches them
    only this way); a SIGHUP (the terminal closed) goes as SIGTERM. On the way out (an error
    of this process's own), those still running are killed."""

    def pass_on(signum: int, frame: Any) -> None:
        sent = signal.SIGTERM if signum == signal.SIGHUP else signum
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(sent)

    saved = {signum: signal.signal(signum, pass_on)
             for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}  # fmt: skip
    try:
        yield
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler)
        for proc in procs:
            if proc.poll() is None:
                proc.kill()


def _ends_with_parent() -> Callable[[], None] | None:
    """What a process runs before ``td3-jax`` starts in it: asks Linux for a SIGTERM when this
    launching process ends (``PR_SET_PDEATHSIG``); None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    libc = ctypes.CDLL(None, use_errno=True)
    return functools.partial(libc.prctl, _PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)


def _wait(procs: list[subprocess.Popen]) -> int:
    """Waits for every process; once one fails, the others get :data:`GRACE_S` to end, then
    are stopped. The first failure's exit status (0: none)."""
    failed: tuple[int, int] | None = None
    deadline = None
    while any([p.poll() is None for p in procs]):  # (a list: every process polled)
        if failed is None:
            failed = next(((i, p.returncode) for i, p in enumerate(procs)
                           if p.returncode not in (None, 0)), None)  # fmt: skip
            deadline = time.monotonic() + GRACE_S if failed else None
        if deadline is not None and time.monotonic() > deadline:
            _stop_rest(procs, failed)
            break
        time.sleep(0.2)
    codes = [p.wait() for p in procs]
    if failed is None:
        failed = next(((i, c) for i, c in enumerate(codes) if c != 0), None)
    return 0 if failed is None else _exit_status(failed[1])


def _stop_rest(procs: list[subprocess.Popen], failed: tuple[int, int]) -> None:
    """Stops the processes still running after process ``failed[0]`` ended with ``failed[1]``:
    SIGKILL (they wait for it at a collective, where a SIGTERM is not acted on); the run's
    newest checkpoint is kept."""
    running = [i for i, p in enumerate(procs) if p.poll() is None]
    print(f"td3-jax: process {failed[0]} ended with exit status {_exit_status(failed[1])}; "
          f"stopping process{'es' if len(running) > 1 else ''} "
          f"{', '.join(map(str, running))}, which did not end within {GRACE_S:g} s (the run's "
          "newest checkpoint is kept)", file=sys.stderr, flush=True)  # fmt: skip
    for i in running:
        procs[i].kill()


def _exit_status(code: int) -> int:
    """A process's exit status as a shell gives it (killed by signal S: 128 + S)."""
    return 128 - code if code < 0 else code


def free_port() -> int:
    """A TCP port of this host that is free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
