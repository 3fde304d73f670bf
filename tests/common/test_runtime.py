"""The host lifecycle (``td3_jax.common.runtime``): importing td3_jax changes no process-wide state,
a stop token reaches the run, the signal handlers set it, the CLI's log quieting."""

from __future__ import annotations

import gc
import json
import logging
import signal
import subprocess
import sys
import threading
import time
import warnings

import pytest
from configs import tiny_config
from support import TINY_FLAGS

from td3_jax.cli import app as cli
from td3_jax.common import runtime
from td3_jax.runner import run as run_module
from td3_jax.runner.logger import read_metrics
from td3_jax.runner.rundir import interrupted_message

# What a process holds that an import could change: the loggers (levels, filters, handlers),
# hooks, signal handlers, warnings filters, sys.modules entries set to None, the environment.
SNAPSHOT = r"""
import logging, os, signal, sys, threading, warnings

def loggers():
    found = {"": logging.getLogger()}
    found.update((n, l) for n, l in logging.root.manager.loggerDict.items()
                 if isinstance(l, logging.Logger))
    return {n: (l.level, list(l.filters), list(l.handlers), l.propagate, l.disabled)
            for n, l in found.items()}

def snapshot():
    catchable = set(signal.valid_signals()) - {signal.SIGKILL, signal.SIGSTOP}
    return {
        "loggers": loggers(),
        "logging": (logging.root.manager.disable, logging.getLoggerClass()),
        "hooks": (sys.unraisablehook, sys.excepthook, threading.excepthook, sys.displayhook,
                  sys.gettrace(), sys.getprofile(), list(sys.meta_path), list(sys.path_hooks)),
        "signals": {int(s): signal.getsignal(s) for s in catchable},
        "warnings": list(warnings.filters),
        "modules set to None": {n for n, m in sys.modules.items() if m is None},
        "environment": dict(os.environ),
    }

def changes(before, after):
    found = {}
    for key in before:
        if before[key] == after[key]:
            continue
        if key == "loggers":
            plain = (logging.NOTSET, [], [], True, False)
            found[key] = {n: repr(v) for n, v in after[key].items()
                          if before[key].get(n, plain) != v}
        else:
            found[key] = repr(after[key])
    return found
"""

# Prints the modules that importing every td3_jax module loads besides td3_jax's own.
LOADED = r"""
import importlib, json, pkgutil, sys
import td3_jax
for m in pkgutil.walk_packages(td3_jax.__path__, "td3_jax."):
    if m.name != "td3_jax.__main__":
        importlib.import_module(m.name)
print("LOADED " + json.dumps([n for n in sys.modules if n.split(".")[0] not in ("td3_jax",
                                                                              "__main__")]))
"""

# Imports those first (what they change is theirs), then every td3_jax module, and prints
# what the latter changed.
COMPARE = r"""
import importlib, json, pkgutil
for name in json.loads(sys.argv[1]):
    try:
        importlib.import_module(name)
    except BaseException:  # a module that only its package imports (it is loaded anyway)
        pass
before = snapshot()
import td3_jax
for m in pkgutil.walk_packages(td3_jax.__path__, "td3_jax."):
    if m.name != "td3_jax.__main__":
        importlib.import_module(m.name)
print("CHANGES " + json.dumps(changes(before, snapshot())))
"""


def _python(code: str, *args: str) -> str:
    """The line of ``code``'s output that follows its marker (the first word of ``code``'s
    last print), from a fresh interpreter."""
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    (line,) = [x for x in proc.stdout.splitlines() if x.startswith(("LOADED ", "CHANGES "))]
    return line.split(" ", 1)[1]


@pytest.fixture(scope="module")
def loaded() -> str:
    """The modules (JSON) that importing td3_jax loads besides its own."""
    return _python(LOADED)


def test_importing_every_td3_jax_module_changes_no_process_wide_state(loaded):
    """Log levels, filters and handlers, hooks, signal handlers, warnings filters,
    ``sys.modules`` and the environment are as they were after the libraries td3_jax uses are
    imported (what those change at import is theirs): only the CLI changes such state."""
    assert json.loads(_python(SNAPSHOT + COMPARE, loaded)) == {}


def test_importing_td3_jax_first_leaves_the_root_logger_alone():
    """Imported before anything else (orbax, under td3_jax.runner.checkpoint, reaches absl, which
    calls ``logging.basicConfig()``), td3_jax leaves the root logger without handlers and at
    its level, as a fresh interpreter has it."""
    code = ("import logging, json\nimport td3_jax.runner.run, td3_jax.runner.checkpoint\n"
            "root = logging.getLogger()\n"
            "print('CHANGES ' + json.dumps([len(root.handlers), root.level]))\n")  # fmt: skip
    assert json.loads(_python(code)) == [0, 30]


def test_the_comparison_sees_a_change(loaded):
    """The same check does find what an import-time change would leave."""
    code = SNAPSHOT + COMPARE.replace(
        "before = snapshot()",
        "before = snapshot()\nfrom td3_jax.common import runtime; runtime.quiet_library_logs()\n"
        "sys.modules['torch'] = None",
    )
    found = json.loads(_python(code, loaded))
    assert set(found) == {"loggers", "hooks", "warnings", "modules set to None"}
    assert set(found["loggers"]) == {"absl", "asyncio"}


def test_a_stop_token_set_before_train_stops_it_before_anything_compiles(tmp_path):
    stop = runtime.StopToken()
    stop.set()
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_module.train(tiny_config(), out, progress=False, stop=stop)
    assert read_metrics(out / "metrics.jsonl") == [] and stop.is_set()
    assert interrupted_message(out).startswith("interrupted before the first checkpoint")


def test_the_cli_passes_its_stop_token_to_train(tmp_path, capsys, monkeypatch):
    """The token the CLI's signal handlers set is the one train checks: set, the run ends
    as a Ctrl-C would (exit 130, nothing to resume), and the handlers are put back."""
    real_train = run_module.train
    tokens = []

    def train_asked_to_stop(*args, stop, **kwargs):
        tokens.append(stop)
        stop.set()
        return real_train(*args, stop=stop, **kwargs)

    monkeypatch.setattr(run_module, "train", train_asked_to_stop)
    before = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train", *TINY_FLAGS, "--out", str(out), "--quiet", "--compile-cache", "off"])
    err = capsys.readouterr().err
    assert exit_.value.code == 130 and isinstance(tokens[0], runtime.StopToken)
    assert err.strip().splitlines()[-1] == f"td3-jax: {interrupted_message(out)}"
    assert signal.getsignal(signal.SIGTERM) is before


def test_stop_signals_set_the_token_and_are_put_back(monkeypatch, capsys):
    """SIGTERM sets the token alone; Ctrl-C sets it and raises; a second signal ends the
    process at once (os._exit); the handlers and the unraisable hook are put back."""
    exits = []
    monkeypatch.setattr(runtime.os, "_exit", lambda code: exits.append(code))
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    hook = sys.unraisablehook
    stop, received = runtime.StopToken(), []
    with runtime.stop_signals(stop, received, say=False):
        signal.raise_signal(signal.SIGTERM)
        assert stop.is_set() and received == [signal.SIGTERM] and exits == []
        signal.raise_signal(signal.SIGTERM)  # at once: timeout's second delivery, ignored
        assert exits == [] and received == [signal.SIGTERM]
        time.sleep(runtime.REPEAT_SIGNAL_S + 0.1)
        signal.raise_signal(signal.SIGTERM)
        assert exits == [128 + signal.SIGTERM]
    assert {s: signal.getsignal(s) for s in handlers} == handlers and sys.unraisablehook is hook
    stop.clear()
    with pytest.raises(KeyboardInterrupt), runtime.stop_signals(stop, received, say=True):
        signal.raise_signal(signal.SIGINT)
    assert stop.is_set() and received[-1] == signal.SIGINT
    assert capsys.readouterr().err == "td3-jax: stopping (Ctrl-C again to stop at once)\n"
    assert {s: signal.getsignal(s) for s in handlers} == handlers


def test_in_several_processes_a_first_ctrl_c_sets_the_token_alone(monkeypatch, capsys):
    """A process of a several-process run does not raise on a first Ctrl-C (it would leave at
    once, and the others wait for it at a collective): the token stops it at the chunk
    boundary the processes agree on; a second Ctrl-C still ends it at once."""
    exits = []
    monkeypatch.setattr(runtime.os, "_exit", exits.append)
    stop, received = runtime.StopToken(), []
    stop.mark_training()
    with runtime.stop_signals(stop, received, say=True, several=True):
        signal.raise_signal(signal.SIGINT)
        assert stop.is_set() and received == [signal.SIGINT] and exits == []
        signal.raise_signal(signal.SIGINT)  # at once: timeout -s INT's second delivery, ignored
        assert exits == [] and received == [signal.SIGINT]
        time.sleep(runtime.REPEAT_SIGNAL_S + 0.1)
        signal.raise_signal(signal.SIGINT)
        assert exits == [128 + signal.SIGINT]
    assert capsys.readouterr().err.startswith(
        "td3-jax: interrupted: stopping once the chunk in flight is checkpointed (Ctrl-C again to "
        "stop at once)\n")  # fmt: skip


def test_a_second_signal_says_what_the_stop_leaves(monkeypatch, capsys):
    """The line a second signal ends the process with is ``aftermath`` of its cause (the run's
    newest checkpoint and how to resume, in the CLI), or the cause alone if that fails."""

    def exit_now(code: int) -> None:
        raise SystemExit(code)  # as os._exit would end the process, the handler goes no further

    monkeypatch.setattr(runtime.os, "_exit", exit_now)

    def leaves(cause: str) -> str:
        return f"{cause}; the newest checkpoint is ckpt/7"

    stop = runtime.StopToken()
    with pytest.raises(SystemExit) as ended, runtime.stop_signals(stop, [], aftermath=leaves):
        signal.raise_signal(signal.SIGTERM)
        time.sleep(runtime.REPEAT_SIGNAL_S + 0.1)
        signal.raise_signal(signal.SIGTERM)
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert ended.value.code == 128 + signal.SIGTERM
    assert last == "td3-jax: terminated again: stopping now; the newest checkpoint is ckpt/7"

    def unreadable(cause: str) -> str:
        raise PermissionError("run directory")

    stop.set()  # a first Ctrl-C was received: the next one ends the process
    with pytest.raises(SystemExit) as ended, runtime.stop_signals(stop, [], aftermath=unreadable):
        signal.raise_signal(signal.SIGINT)
    assert ended.value.code == 128 + signal.SIGINT
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == "td3-jax: interrupted again: stopping now"


def test_a_stopped_wait_gives_up_the_compile_thread():
    stop, unblock = runtime.StopToken(), threading.Event()
    future = runtime.in_background(unblock.wait, 30)
    assert runtime.background_work_running()
    threading.Timer(0.1, stop.set).start()
    with pytest.raises(KeyboardInterrupt):
        runtime.result(future, stop)
    unblock.set()
    assert runtime.result(future) is True


def test_a_timeout_the_work_itself_raised_is_its_result_not_a_wait_to_repeat():
    """(``result`` waits in steps of 0.2 s, each ending in TimeoutError while the work runs.)"""

    def times_out():
        raise TimeoutError("a lock held elsewhere")

    future = runtime.in_background(times_out)
    with pytest.raises(TimeoutError, match="a lock held elsewhere"):
        runtime.result(future, runtime.StopToken())


def test_a_ctrl_c_that_leaves_a_device_wait_is_reported_as_uninterruptible_work():
    """A KeyboardInterrupt out of a device wait leaves the computation running: reported until
    forgotten; another exception, or a wait that ends, reports nothing."""
    assert not runtime.background_work_running()
    with runtime.awaiting_device():
        pass
    with pytest.raises(ValueError), runtime.awaiting_device():
        raise ValueError("not a Ctrl-C")
    assert not runtime.background_work_running()
    try:
        with pytest.raises(KeyboardInterrupt), runtime.awaiting_device():
            raise KeyboardInterrupt
        assert runtime.background_work_running()
    finally:
        runtime.forget_abandoned_work()
    assert not runtime.background_work_running()


@pytest.fixture
def restored_logging(monkeypatch):
    """Puts back what :func:`runtime.quiet_library_logs` changes."""
    import absl.logging  # noqa: F401  (its logger class first)

    loggers = [logging.getLogger(name) for name in ("absl", "asyncio")]
    saved = [(logger.level, list(logger.filters)) for logger in loggers]
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
    with warnings.catch_warnings():
        yield
    for logger, (level, filters) in zip(loggers, saved, strict=True):
        logger.setLevel(level)
        logger.filters[:] = filters


def call_soon_threadsafe() -> RuntimeError:
    """The error tensorstore's callbacks raise into orbax's closed event loop."""
    try:
        raise RuntimeError("Event loop is closed")
    except RuntimeError as err:
        return err


class _CtrlCInFinalizer:
    """An object in a reference cycle whose finalizer gets a Ctrl-C (run by a collection)."""

    def __init__(self) -> None:
        self.cycle = self

    def __del__(self) -> None:
        signal.raise_signal(signal.SIGINT)  # its KeyboardInterrupt is raised in here
        sum(range(10))


def _collect_a_ctrl_c(wait_s: float) -> list[str]:
    """Where the Ctrl-C a collection's finalizer got surfaces: ``["raised", "after"]`` when it
    came back in the code after the collection (within ``wait_s``), ``["collected"]`` when
    not."""
    seen: list[str] = []
    _CtrlCInFinalizer()
    try:
        gc.collect()
        seen.append("collected")
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            time.sleep(0.001)
    except KeyboardInterrupt:
        seen[:] = ["raised", "after"] if seen == ["collected"] else ["raised", "during"]
    return seen


def test_a_ctrl_c_discarded_before_training_is_raised_again(monkeypatch, capfd):
    """A Ctrl-C raised inside a finalizer (a garbage collection while JAX traces) is discarded
    by Python: before training it is raised again in the code that runs after the collection
    (a trace stops there, not at its end); while training it is dropped, as the run stops
    through its token. Neither is taken for a second Ctrl-C (which ends the process)."""
    exits = []
    monkeypatch.setattr(runtime.os, "_exit", exits.append)
    stop = runtime.StopToken()
    with runtime.stop_signals(stop, [], say=False):
        assert _collect_a_ctrl_c(5.0) == ["raised", "after"]  # (at once: 5 s for a busy CI)
        assert stop.is_set()
        stop.clear()
        stop.mark_training()
        assert _collect_a_ctrl_c(0.5) == ["collected"] and stop.is_set()
    assert exits == []
    assert "Exception ignored" not in capfd.readouterr().err


def test_quiet_library_logs_drops_only_what_td3_jax_says_better(restored_logging, monkeypatch):
    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)
    runtime.quiet_library_logs()
    runtime.quiet_library_logs()  # a second call adds nothing
    absl = logging.getLogger("absl")
    assert absl.level == logging.ERROR and len(absl.filters) == 1
    assert logging.getLogger("asyncio").level == logging.CRITICAL
    closed = call_soon_threadsafe()
    other = ValueError("kept")
    for err in (closed, other):
        sys.unraisablehook(type("Args", (), {"exc_value": err, "exc_traceback":
                           err.__traceback__, "object": None})())  # fmt: skip
    assert [args.exc_value for args in seen] == [other]


def test_an_on_off_variable_reads_the_usual_words_and_nothing_else(monkeypatch):
    """(TD3_JAX_WARP_BESIDE, TD3_JAX_WARP_PRECOMPILE, TD3_JAX_WARP_ON_CPU read it.)"""
    monkeypatch.delenv("TD3_JAX_TEST_SWITCH", raising=False)
    assert runtime.env_switch("TD3_JAX_TEST_SWITCH") is None
    for value, meaning in [("1", True), (" Yes", True), ("ON", True), ("true", True),
                           ("0", False), ("no", False), ("Off ", False), ("FALSE", False),
                           ("t", True), ("Y", True), ("f", False), ("N", False),
                           ("", None), ("2", None), ("maybe", None)]:  # fmt: skip
        monkeypatch.setenv("TD3_JAX_TEST_SWITCH", value)
        assert runtime.env_switch("TD3_JAX_TEST_SWITCH") is meaning, value


def test_an_unwritable_compile_cache_is_refused_if_asked_for_and_skipped_if_default(
    tmp_path, capsys
):
    """A cache directory that cannot be made (under a file here; a read-only or full home in
    use): one line naming it where --compile-cache asked for it; the default one instead warns
    and leaves the cache off (None: no programs folder), so training still starts."""
    from td3_jax.common.runtime import enable_compile_cache
    from td3_jax.config.schema import ConfigError

    (tmp_path / "home").write_text("a file, not a folder")
    wanted = str(tmp_path / "home" / "cache")
    with pytest.raises(ConfigError, match=r"cannot write there .*choose another directory, or off"):
        enable_compile_cache(wanted)
    assert enable_compile_cache(wanted, given=False) is None
    assert "cannot be written" in capsys.readouterr().err
    assert enable_compile_cache("off") is None and not (tmp_path / "home").is_dir()
