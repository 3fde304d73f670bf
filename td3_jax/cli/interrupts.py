"""Stopping a run from outside: a SIGTERM (or, in a run of several processes, a Ctrl-C) stops
training at the next chunk boundary, that chunk checkpointed; a Ctrl-C in a run of one process
stops at once, the run left at its last checkpoint; a second signal stops at once
(:func:`td3_jax.common.runtime.stop_signals`). The command ends with one line saying what the
run directory holds and the shell's exit status for the signal."""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import warnings
from collections.abc import Iterator
from typing import Any

from td3_jax.common import library_noise, runtime
from td3_jax.common.runtime import joined_others
from td3_jax.config.schema import TrainConfig

__all__ = ["FIRST_PROCESS_LEAVE_S", "STOPPED_LEAVE_S", "Interrupted", "exit_process",
           "leave_processes", "process_stop", "signals_while_starting", "train_stoppably"]


class Interrupted(Exception):
    """Ctrl-C or SIGTERM during a run; the message says what the run directory holds and
    ``code`` is the exit status (130 for Ctrl-C, 143 for SIGTERM, as shells report them)."""

    def __init__(self, message: str, code: int = 130):
        super().__init__(message)
        self.code = code


def train_stoppably(
    cfg: TrainConfig,
    command: Any,
    stop: runtime.StopToken | None = None,
    received: list[int] | None = None,
    **train_options: Any,
) -> list[dict[str, Any]]:
    """``run.train`` of ``cfg`` into ``command.out`` (a train command: its resume, quiet and
    time-budget flags) under handlers that turn SIGINT and SIGTERM into a stop at the next
    chunk (a second signal stops at once); a stop leaves the last checkpoint and says, in one
    line, what it left (``Interrupted``, exit 130, or 143 for SIGTERM; 130 too for a process
    of a several-process run stopped because another was). ``stop`` and ``received``: the
    token and the signals of handlers already installed while the process started
    (:func:`signals_while_starting`). Returns the run's records, one per chunk."""
    import jax  # lazy: JAX, only for a run

    from td3_jax.runner.run import RunCompleteWarning, train  # lazy: imports JAX
    from td3_jax.runner.rundir import interrupted_message  # lazy: imports JAX

    received = [] if received is None else received
    stop = runtime.StopToken() if stop is None else stop  # (the run's only way to be stopped)
    ended = functools.partial(interrupted_message, command.out)  # what a stop leaves, one line
    try:
        several = jax.process_count() > 1  # (a first Ctrl-C too stops at an agreed boundary)
        signals = runtime.stop_signals(stop, received, say=jax.process_index() == 0,
                                       aftermath=ended, several=several)  # fmt: skip
        with signals, warnings.catch_warnings():  # (the command says it in its own words)
            warnings.filterwarnings("ignore", category=RunCompleteWarning)
            return train(cfg, command.out, resume=command.resume, stop=stop,
                         progress=not command.quiet, time_budget_s=command.time_budget_s,
                         **train_options)  # fmt: skip
    except KeyboardInterrupt:
        if signal.SIGTERM in received:
            raise Interrupted(ended("terminated (SIGTERM)"), 128 + signal.SIGTERM) from None
        if not received and jax.process_count() > 1:  # (another process was stopped)
            raise Interrupted(ended("stopped with another process of the run, which was "
                                    "stopped (Ctrl-C or SIGTERM)")) from None  # fmt: skip
        raise Interrupted(ended()) from None


#: The stop token and signals of this process's handlers while it starts
#: (:func:`signals_while_starting`), for the run it then trains (:func:`process_stop`).
_STARTING: list[tuple[runtime.StopToken, list[int]]] = []


@contextlib.contextmanager
def signals_while_starting(args: list[str]) -> Iterator[None]:
    """For a train or sweep process that joins others (:func:`~td3_jax.cli.argv.joins_others`),
    from before it imports JAX: the handlers of a run of several processes, so that a Ctrl-C
    while it imports, joins or compiles sets the stop token of :func:`process_stop` (the
    processes then stop together before training, :func:`~td3_jax.runner.sharding.
    start_agreed`) instead of raising where Python may discard it; a second signal stops at
    once. Nothing for a process of its own."""
    from td3_jax.cli.argv import joins_others

    if not joins_others(args):
        yield
        return
    stop, received = runtime.StopToken(), []
    _STARTING.append((stop, received))
    try:
        with runtime.stop_signals(stop, received, several=True):
            yield
    finally:
        _STARTING.remove((stop, received))


def process_stop() -> tuple[runtime.StopToken, list[int]]:
    """The stop token and received signals of :func:`signals_while_starting`, else new ones
    (a process of its own, or the library called directly)."""
    return _STARTING[-1] if _STARTING else (runtime.StopToken(), [])


#: Seconds a process of several that ends early (stopped, or failed) waits for the others to
#: leave JAX's runtime with it (they may still be compiling, or in a chunk); past them it ends
#: without them.
STOPPED_LEAVE_S = 30.0
#: The same for the first process, which holds JAX's coordination service: the others need it
#: until they come to stop themselves (at their next boundary, after a compile or a chunk), and
#: abort (exit status 134) where it ends before. Below JAX's own limit on that wait (300 s),
#: past which JAX aborts the process.
FIRST_PROCESS_LEAVE_S = 240.0


def leave_processes(wait_s: float | None) -> bool:
    """A run of several processes, ended or stopped together: each leaves JAX's runtime once
    all have come to leave it (within ``wait_s``; None: however long). Left at once, the
    first process (it holds the runtime's coordination service) could end while another still
    called it, which then aborted with a C++ stack trace. Nothing where the process joined no
    others (or never imported JAX). False where the others did not come within ``wait_s``."""
    if "jax" not in sys.modules:  # (it stopped before it imported JAX: nothing joined)
        return True
    from td3_jax.runner.sharding import leave_distributed  # lazy: imports JAX

    return leave_distributed(wait_s)


def _first_of_several() -> bool:
    """Whether this is the first process (it holds JAX's coordination service) of several
    (asked without starting JAX's backend, which may fail, or wait for a process that is
    gone)."""
    from td3_jax.common import upstream

    return joined_others() and upstream.distributed_process_id() == 0


def exit_process(message: str | None, code: int, abandon_work: bool = True) -> None:
    """Ends a command that stopped or failed with exit status ``code``, after ``message`` on
    stderr (None: said already). A process of several first leaves JAX's runtime with the
    others, within :data:`STOPPED_LEAVE_S` (:data:`FIRST_PROCESS_LEAVE_S` for the first; JAX's
    own exit hook would wait for one that is gone for minutes, then abort the process); past
    it, the process ends at once (``os._exit``).
    ``abandon_work`` (a stop): work that a Ctrl-C cannot stop is abandoned the same way rather
    than waited for: an XLA compile on a background thread, a chunk or evaluation left running
    on the device (the run's outputs are closed by then). Waiting took the rest of the chunk,
    and tearing down XLA under it could end in SIGSEGV. Work its owner dropped
    (:func:`~td3_jax.common.runtime.drop`: MuJoCo Warp's kernel compiles of a run that ended
    before its first step) is abandoned in either case."""
    if message is not None:
        print(message, file=sys.stderr, flush=True)
    left = leave_processes(FIRST_PROCESS_LEAVE_S if _first_of_several() else STOPPED_LEAVE_S)
    abandons = abandon_work and runtime.background_work_running()
    if not left or abandons or runtime.dropped_work_running():
        sys.stdout.flush()
        library_noise.drain_filters()  # (what a filter of stderr still holds, this line too)
        runtime.forget_abandoned_work()  # (for a caller whose os._exit returns: tests)
        os._exit(code)
    sys.exit(code)
