"""The host process around a run: stopping it, its compile threads, JAX's compilation cache,
the signals that stop it, and the log noise of the libraries it uses.

Importing this module (or any other ``td3_jax`` module) changes no process-wide state: log
levels and filters, hooks, signal handlers and ``sys.modules`` are changed only by the
functions here that say so, which the command line (:mod:`td3_jax.cli.app`) calls. A library user
stops a run with a :class:`StopToken` passed to :func:`td3_jax.runner.run.train`; nothing global is
shared between runs. This module imports only the standard library.
"""

from __future__ import annotations

import _thread
import contextlib
import importlib.util
import logging
import math
import os
import signal
import sys
import tempfile
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def root_logging_kept() -> Iterator[None]:
    """Leaves the root logger's handlers as they were around imports that configure it
    (orbax's import reaches absl, which calls ``logging.basicConfig()``): importing td3_jax
    must not change the user's logging."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        yield
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


__all__ = [
    "CACHE_MAX_BYTES",
    "LOCAL_PROCESSES_ENV",
    "PROGRAMS_FOLDER",
    "StopToken",
    "background_work_running",
    "enable_compile_cache",
    "in_background",
    "joined_others",
    "local_processes",
    "quiet_library_logs",
    "result",
    "root_logging_kept",
    "stop_signals",
]


# --------------------------------------------------------------------------------------------
# stopping a run
# --------------------------------------------------------------------------------------------


#: Set in each process that ``td3-jax train|sweep --local-processes N`` starts: N.
LOCAL_PROCESSES_ENV = "TD3_JAX_LOCAL_PROCESSES"


def local_processes() -> int | None:
    """N where this process is one of the N that ``--local-processes N`` started (read from
    :data:`LOCAL_PROCESSES_ENV`), else None."""
    text = os.environ.get(LOCAL_PROCESSES_ENV, "")
    return int(text) if text.isdigit() else None


def joined_others() -> bool:
    """Whether this process joined other processes through ``jax.distributed`` (asked without
    importing JAX, or starting its backend, which the join must come before)."""
    return "jax" in sys.modules and sys.modules["jax"].distributed.is_initialized()


class StopToken:
    """Asks a run to stop, as a Ctrl-C would: set it (from any thread, or a signal handler) and
    :func:`td3_jax.runner.run.train` stops waiting for compiles and stops at its next chunk
    boundary, once that chunk is checkpointed, raising KeyboardInterrupt. It stays set until
    cleared."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self._training = threading.Event()
        self._shielded = threading.Event()

    def mark_training(self) -> None:
        """Says the run has compiled and is training (:func:`td3_jax.runner.run.train` calls it
        before its first chunk): a stop from now on waits for the chunk in flight and its
        checkpoint; before, nothing has been trained, so there is nothing to wait for or save."""
        self._training.set()

    def training(self) -> bool:
        """Whether the run has started training (:meth:`mark_training`)."""
        return self._training.is_set()

    @contextlib.contextmanager
    def shielded(self) -> Iterator[None]:
        """While inside (a checkpoint being written), a first Ctrl-C only sets the token, as a
        SIGTERM does: the write finishes, and the run stops at its next chunk boundary (a run
        whose last chunk it was ends as usual). A second Ctrl-C still stops at once."""
        self._shielded.set()
        try:
            yield
        finally:
            self._shielded.clear()

    def is_shielded(self) -> bool:
        """Whether a first Ctrl-C must not raise now (:meth:`shielded`)."""
        return self._shielded.is_set()

    def set(self) -> None:
        """Asks the run to stop."""
        self._event.set()

    def is_set(self) -> bool:
        """Whether the run was asked to stop."""
        return self._event.is_set()

    def clear(self) -> None:
        """Takes the request back (a run already stopped stays stopped)."""
        self._event.clear()

    def raise_if_set(self) -> None:
        """Raises KeyboardInterrupt when the run was asked to stop."""
        if self._event.is_set():
            raise KeyboardInterrupt


def env_switch(variable: str) -> bool | None:
    """The on/off environment variable ``variable``, read with the words JAX reads in its own:
    ``True`` for 1, t, true, on, y or yes, ``False`` for 0, f, false, off, n or no (any case),
    ``None`` where unset or anything else."""
    value = os.environ.get(variable, "").strip().lower()
    return True if value in ("1", "t", "true", "on", "y", "yes") else False if value in (
        "0", "f", "false", "off", "n", "no") else None  # fmt: skip


# --------------------------------------------------------------------------------------------
# compile threads
# --------------------------------------------------------------------------------------------

_BACKGROUND: set[threading.Thread] = set()


def result(future: Future, stop: StopToken | None = None) -> Any:
    """``future.result()``, given up with KeyboardInterrupt once ``stop`` is set."""
    while True:
        try:
            return future.result(timeout=0.2)
        except TimeoutError:
            if future.done():  # (the function's own TimeoutError, not the wait's)
                raise
            if stop is not None:
                stop.raise_if_set()


def in_background(function: Callable[..., Any], *args: Any, name: str = "td3-jax compile"
                  ) -> Future:  # fmt: skip
    """``function(*args)`` on a thread of its own (called ``name``), as a future.

    The thread is not a daemon (a daemon thread still compiling when the interpreter exits
    aborts the process); the CLI ends a stopped run with ``os._exit`` instead of waiting for
    it (see :func:`background_work_running`).
    """
    future: Future = Future()

    def work() -> None:
        value, error = None, None
        try:
            value = function(*args)
        except BaseException as err:  # handed to whoever waits for the result
            error = err
        # (no longer running work once its result is handed over: a caller that has it
        # finds none running, though the thread is still ending)
        _BACKGROUND.discard(threading.current_thread())
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(value)

    thread = threading.Thread(target=work, name=name)
    _BACKGROUND.add(thread)
    thread.start()
    return future


def background_work_running() -> bool:
    """Whether work that a Ctrl-C cannot stop may still be running: a thread of
    :func:`in_background` (e.g. compiling), or a device computation whose wait a Ctrl-C broke
    (:func:`awaiting_device`). Exiting the interpreter under either waits for it, and tearing
    down the XLA client under a running computation can crash the process (SIGSEGV)."""
    return _ABANDONED.is_set() or any(thread.is_alive() for thread in list(_BACKGROUND))


_ABANDONED = threading.Event()
#: The futures of :func:`in_background` whose owner no longer wants their result (:func:`drop`).
_DROPPED: set[Future] = set()


def drop(future: Future) -> None:
    """Marks the work of ``future`` (of :func:`in_background`) as no longer wanted: a process
    that ends need not wait for it (:func:`dropped_work_running`), even where it fails."""
    if not future.done():
        _DROPPED.add(future)


def dropped_work_running() -> bool:
    """Whether work marked by :func:`drop` still runs (the finished is forgotten)."""
    for future in list(_DROPPED):
        if future.done():
            _DROPPED.discard(future)
    return bool(_DROPPED)


@contextlib.contextmanager
def awaiting_device() -> Iterator[None]:
    """Around a wait for a device computation (a chunk, an evaluation): a KeyboardInterrupt
    that leaves it leaves the computation running, which :func:`background_work_running` then
    reports (until :func:`forget_abandoned_work`)."""
    try:
        yield
    except KeyboardInterrupt:
        _ABANDONED.set()
        raise


def forget_abandoned_work() -> None:
    """Clears what :func:`awaiting_device` recorded (once the process has dealt with it)."""
    _ABANDONED.clear()


# --------------------------------------------------------------------------------------------
# JAX's persistent compilation cache
# --------------------------------------------------------------------------------------------

#: The persistent compilation cache's size cap (least recently used entries are evicted).
CACHE_MAX_BYTES = 4 * 1024**3
#: The folder of the compilation cache that holds the traced programs
#: (td3_jax.runner.program_cache).
PROGRAMS_FOLDER = "programs"


def enable_compile_cache(directory: str, given: bool = True) -> Path | None:
    """Points JAX's persistent compilation cache at ``directory`` (``off``: leave it off) and
    returns where the traced programs are kept (``directory/programs``; ``None`` when off).
    A directory that cannot be made or written raises a one-line ConfigError where the user
    ``given`` it, else (the default one, in a read-only or full home) warns and leaves the
    cache off. JAX's settings are process-wide: the CLI calls this once, before compiling."""
    if directory.strip().lower() in ("off", "none", ""):
        return None
    import jax

    from td3_jax.common.errors import ConfigError
    from td3_jax.common.upstream import stamp_jax_cache_entries

    path = Path(directory).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.NamedTemporaryFile(dir=path).close()
    except OSError as err:
        reason = err.strerror or str(err)
        if given:
            raise ConfigError(f"--compile-cache {directory}: cannot write there ({reason}); "
                              "choose another directory, or off") from err  # fmt: skip
        print(f"td3-jax: warning: the compile cache {directory} cannot be written ({reason}): "
              "this run compiles without it; --compile-cache DIR puts it elsewhere",
              file=sys.stderr)  # fmt: skip
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Everything the run compiles, however quick: a second identical run then compiles nothing.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if importlib.util.find_spec("filelock") is not None:  # JAX's cache eviction needs it
        stamp_jax_cache_entries(path)
        jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)
    return path / PROGRAMS_FOLDER


# --------------------------------------------------------------------------------------------
# signals
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def stop_signals(
    stop: StopToken,
    received: list[int],
    say: bool = True,
    aftermath: Callable[[str], str] | None = None,
    several: bool = False,
) -> Iterator[None]:
    """While training: the first Ctrl-C says it is stopping, raises KeyboardInterrupt and sets
    ``stop`` (so the run stops at its next chunk boundary even where Python discards that
    exception); SIGTERM (what ``timeout``, SLURM and Kubernetes send before a kill) sets
    ``stop`` alone, so the chunk in flight finishes and is checkpointed before the run stops.
    A second signal of either kind ends the process at once, except the same signal within
    :data:`REPEAT_SIGNAL_S` (SIGINT: :data:`REPEAT_SIGINT_S`) of the first: GNU ``timeout``
    (``-s INT`` too) signals its child and then its own process group, so one request arrives
    twice. The signals received are appended to ``received``; ``say``: whether this process
    prints (several processes: one speaks). ``aftermath(cause)``: the line said when a second
    signal ends the process (what it leaves behind: the newest checkpoint, how to resume);
    default: ``cause`` alone. ``several``: a process of a several-process run, where a first
    Ctrl-C sets ``stop`` alone too, so that the processes stop together at a chunk boundary
    (one that left at once would leave the others waiting for it at a collective).

    The handlers, and an unraisable-exception hook for a Ctrl-C Python discarded (raised
    inside a finalizer, as during a garbage collection), are installed only on the main thread,
    and the previous ones are put back on exit. Such a Ctrl-C is raised again before training
    (:class:`_Rearm`: tracing the programs, seconds of Python with frequent collections, went
    on to its end otherwise, 16 s for G1 on a CPU); while training the run stops through
    ``stop``.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    rearm = _Rearm()
    on_signal = _signal_handler(stop, received, say, aftermath, rearm, several)
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    previous_hook = sys.unraisablehook

    def unraisable(args: Any) -> None:
        if not isinstance(args.exc_value, KeyboardInterrupt):
            previous_hook(args)
        elif not stop.training():
            rearm.request()

    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        rearm.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sys.unraisablehook = previous_hook


class _Rearm:
    """A Ctrl-C that Python discarded (its KeyboardInterrupt raised inside a finalizer), to be
    raised again in the main thread's own code: another thread trips SIGINT once the
    finalizer has returned (tripped from the finalizer itself, the handler would run and raise
    inside it again), and the handler then raises (:meth:`take`) instead of taking it for a
    second Ctrl-C."""

    def __init__(self) -> None:
        self.pending = False
        self.closed = False
        self._lock = threading.Lock()

    def request(self) -> None:
        """Raises the discarded Ctrl-C again, soon, from the main thread's code."""
        if not self.pending:
            self.pending = True
            _thread.start_new_thread(self._trip, ())

    def _trip(self) -> None:
        with self._lock:
            if self.pending and not self.closed:
                _thread.interrupt_main()  # the main thread's SIGINT handler runs next

    def take(self) -> bool:
        """Whether the SIGINT being handled is this re-raise (then no longer pending)."""
        pending, self.pending = self.pending, False
        return pending

    def close(self) -> None:
        """No re-raise from now on (the handlers are put back next)."""
        self.closed = True
        with self._lock:  # a trip in flight has tripped by now, and is handled as a re-raise
            pass


#: Seconds after a SIGTERM in which another is the same request, delivered twice.
REPEAT_SIGNAL_S = 0.5
#: The same for SIGINT, shorter: a person's second Ctrl-C comes a tenth of a second or more
#: after the first, ``timeout``'s second delivery within a millisecond.
REPEAT_SIGINT_S = 0.05


def _signal_handler(
    stop: StopToken,
    received: list[int],
    say: bool,
    aftermath: Callable[[str], str] | None = None,
    rearm: _Rearm | None = None,
    several: bool = False,
) -> Callable[..., None]:
    """The SIGINT/SIGTERM handler of :func:`stop_signals`; ``rearm``: a discarded Ctrl-C that
    its next SIGINT raises again (:class:`_Rearm`); ``several``: a first Ctrl-C only sets
    ``stop``, as a SIGTERM does."""
    first_at: dict[int, float] = {}  # (when each signal first came)
    rearm = _Rearm() if rearm is None else rearm

    def on_signal(signum: int, frame: Any) -> None:
        if signum == signal.SIGINT and rearm.take():
            if not rearm.closed:
                raise KeyboardInterrupt
            return
        since = time.monotonic() - first_at.get(signum, -math.inf)
        window = REPEAT_SIGINT_S if signum == signal.SIGINT else REPEAT_SIGNAL_S
        if stop.is_set() and since < window:
            return  # the same request delivered twice (timeout: child, then process group)
        if stop.is_set():
            if say:
                print(f"td3-jax: {_last_words(signum, aftermath)}", file=sys.stderr, flush=True)
            os._exit(128 + signum)
        first_at[signum] = time.monotonic()  # (before the token: a repeat may come at once)
        received.append(signum)
        stop.set()
        if signum == signal.SIGTERM:
            if say:
                print(f"td3-jax: terminated (SIGTERM): {_what_stopping_does(stop)} (SIGTERM "
                      "again to stop at once)", file=sys.stderr, flush=True)  # fmt: skip
            return
        if say:
            what = f"interrupted: {_what_stopping_does(stop)}" if several else "stopping"
            print(f"td3-jax: {what} (Ctrl-C again to stop at once)", file=sys.stderr, flush=True)
        if not stop.is_shielded() and not several:  # (a checkpoint being written is finished)
            raise KeyboardInterrupt

    return on_signal


def _last_words(signum: int, aftermath: Callable[[str], str] | None) -> str:
    """What a second signal says as it ends the process (``aftermath`` of its cause, or the
    cause alone where there is none or it fails: the process stops either way)."""
    cause = ("terminated" if signum == signal.SIGTERM else "interrupted") + " again: stopping now"
    try:
        return cause if aftermath is None else aftermath(cause)
    except Exception:  # (a directory that cannot be read must not keep the process running)
        return cause


def _what_stopping_does(stop: StopToken) -> str:
    """What a SIGTERM does now: wait for the chunk in flight and checkpoint it, or, before the
    run trains (making the environment, restoring, compiling), stop with nothing to save."""
    if stop.training():
        return "stopping once the chunk in flight is checkpointed"
    return "nothing trained yet, so nothing to save: stopping before training starts"


# --------------------------------------------------------------------------------------------
# the libraries' log noise
# --------------------------------------------------------------------------------------------


class _OrbaxLogFilter(logging.Filter):
    """Drops orbax's own log records: every failure they report surfaces as a CheckpointError."""

    def filter(self, record: logging.LogRecord) -> bool:
        return f"{os.sep}orbax{os.sep}" not in record.pathname


def _closed_loop_callback(args: Any) -> bool:
    """Whether an unraisable error is tensorstore completing a future of orbax's closed event
    loop: ``Event loop is closed`` raised in asyncio's ``call_soon_threadsafe``, with no object
    (a closed loop of anyone else's code still reaches the previous hook)."""
    tb = args.exc_traceback
    return (
        args.object is None
        and isinstance(args.exc_value, RuntimeError)
        and str(args.exc_value) == "Event loop is closed"
        and tb is not None
        and tb.tb_frame.f_code.co_name == "call_soon_threadsafe"
    )


def _stray_read_error(args: Any) -> bool:
    """Whether an unraisable error is what a failed checkpoint read leaves behind.

    Orbax runs each read in a fresh asyncio loop and closes it as soon as one operation fails;
    those still in flight finish later on tensorstore's threads (their callbacks find the loop
    closed), and their coroutines and tasks are dropped unfinished. Nothing waits for any of
    them any more, and the failed read itself is reported (a CheckpointError), so their errors
    say nothing new: ``Event loop is closed``, or an error raised in orbax's or tensorstore's
    code or by one of their coroutines. (Python's warning about the coroutines never awaited
    is silenced by :func:`quiet_library_logs` for the whole process: the CLI's only.)
    """
    if _closed_loop_callback(args):
        return True
    code = getattr(args.object, "cr_code", None) or getattr(
        getattr(args.object, "get_coro", lambda: None)(), "cr_code", None
    )
    files = [frame.filename for frame in traceback.extract_tb(args.exc_traceback)]
    files.append(getattr(code, "co_filename", ""))
    return any(f"{os.sep}{package}{os.sep}" in name for name in files
               for package in ("orbax", "tensorstore"))  # fmt: skip


def quiet_library_logs() -> None:
    """Silences what the libraries say that td3-jax says better, for the whole process (the CLI
    calls it; a library user may): absl's logger at ERROR without orbax's records, asyncio's
    at CRITICAL (after a failed read of a corrupt checkpoint, tensorstore callbacks still in
    flight hit orbax's closed event loop; the CheckpointError says it all), an
    unraisable-exception hook that drops those callbacks' errors and those of the coroutines
    the read left behind (they can arrive after the failed restore has returned, so it stays;
    :func:`_stray_read_error`), Python's warning about those never awaited, and Brax's notice
    that its own physics pipelines are unmaintained (td3-jax steps Brax's tasks on MJX by
    default). Calling it again adds nothing."""
    import absl.logging  # noqa: F401  (absl's own logger class, not a plain one made here)

    absl_logger = logging.getLogger("absl")
    absl_logger.setLevel(logging.ERROR)
    if not any(isinstance(f, _OrbaxLogFilter) for f in absl_logger.filters):
        absl_logger.addFilter(_OrbaxLogFilter())
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    warnings.filterwarnings("ignore", message="Brax System, piplines and environments")
    # (orbax's coroutines that a failed read left unstarted, collected later)
    warnings.filterwarnings(
        "ignore", message="coroutine .* was never awaited", category=RuntimeWarning
    )
    previous = sys.unraisablehook
    if getattr(previous, "td3_jax_quiet", False):
        return

    def hook(args: Any) -> None:
        if not _stray_read_error(args):
            previous(args)

    hook.td3_jax_quiet = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook
