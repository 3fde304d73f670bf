"""What several test files share: the tiny CLI run's flags, the command line run in this process
or in a child process, a run directory's records and TensorBoard events, and a fixture that puts
back the library logging the CLI quiets.

One set of tiny flags keeps the programs of the tests' small runs identical, so that the test
run's compilation cache (tests/conftest.py) compiles them once.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import struct
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from td3_jax.cli import app as cli

#: A run of 128 steps of 4 Pendulums in two chunks of 64: one evaluation and checkpoint each.
TINY_FLAGS = [
    "--env", "gymnax/Pendulum-v1", "--num-envs", "4", "--total-steps", "128",
    "--eval-every", "64", "--warmup-steps", "32", "--batch-size", "16",
    "--updates-per-iter", "1", "--hidden-sizes", "16", "16", "--eval-envs", "2",
    "--episode-length", "16", "--seed", "7", "--buffer-size", "256",
]  # fmt: skip


def with_flags(flags: list[str], **values: str) -> list[str]:
    """``flags`` with the value of each ``--name`` given as ``name=value`` replaced."""
    changed = list(flags)
    for name, value in values.items():
        changed[changed.index(f"--{name.replace('_', '-')}") + 1] = value
    return changed


def td3_jax(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    """``python -m td3_jax ARGS`` in a child process, its output captured as text."""
    return subprocess.run(
        [sys.executable, "-m", "td3_jax", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def python(
    code: str, timeout: float = 240, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """``python -c CODE`` in a child process (a fresh interpreter: nothing imported yet), its
    output captured as text."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=timeout, env=env)  # fmt: skip


def optimised_env() -> dict[str, str]:
    """This process's environment without the XLA flag that tests/conftest.py adds (programs
    compiled unoptimised): for child processes that train long enough for optimised code to
    pay, and whose learning thresholds were measured on it, as the CLI compiles by default."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    kept = [flag for flag in flags if not flag.startswith("--xla_backend_optimization_level")]
    return {**os.environ, "XLA_FLAGS": " ".join(kept)}


def main(args: list[str], capsys=None) -> tuple[int, str, str]:
    """Runs ``cli.main(args)`` in-process: (exit code, stdout, stderr), read from pytest's
    ``capsys`` where given, else captured here (for a fixture wider than one test)."""
    if capsys is None:
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = _exit_code(args)
        return code, out.getvalue(), err.getvalue()
    capsys.readouterr()
    code = _exit_code(args)
    out, err = capsys.readouterr()
    return code, out, err


def _exit_code(args: list[str]) -> int:
    try:
        cli.main(args)
    except SystemExit as exit_:
        return exit_.code if isinstance(exit_.code, int) else 1
    return 0


def assert_one_line_error(code: int, err: str, *needles: str) -> None:
    """A refused command: exit code 2 and one ``td3-jax: error:`` line holding each needle."""
    assert code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("td3-jax: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, err)


def read_records(run_dir: Path) -> list[dict]:
    """The run's metrics.jsonl, one dict per record."""
    text = (run_dir / "metrics.jsonl").read_text()
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def tensorboard_events(run_dir: Path) -> list:
    """The events of the run's TensorBoard files (``tensorboardX.proto.event_pb2.Event``), the
    files read in name order, as TensorBoard reads them, each parsed from its TFRecord framing."""
    from tensorboardX.proto import event_pb2

    events = []
    for path in sorted((run_dir / "tensorboard").glob("events.out.tfevents.*")):
        data, pos = path.read_bytes(), 0
        while pos < len(data):
            (length,) = struct.unpack("<Q", data[pos : pos + 8])
            events.append(event_pb2.Event.FromString(data[pos + 12 : pos + 12 + length]))
            pos += 12 + length + 4
    return events


@pytest.fixture
def restored_logging(monkeypatch):
    """Puts back what :func:`td3_jax.common.runtime.quiet_library_logs` changes: the absl and
    asyncio loggers' levels and filters, the warning filters and ``sys.unraisablehook``."""
    import absl.logging  # noqa: F401  (its logger class first)

    loggers = [logging.getLogger(name) for name in ("absl", "asyncio")]
    saved = [(logger.level, list(logger.filters)) for logger in loggers]
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
    with warnings.catch_warnings():
        yield
    for logger, (level, filters) in zip(loggers, saved, strict=True):
        logger.setLevel(level)
        logger.filters[:] = filters
