"""The run's outputs (``td3_jax.logger``) when the disk refuses them: one error, nothing more."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import textwrap

# A process that logs one record, then finds the disk full: TensorBoard's flush fails.
_FULL_DISK = textwrap.dedent(
    """
    import errno, os, sys
    from tensorboardX import record_writer
    from td3_jax.logger import MetricsLogger

    logger = MetricsLogger(sys.argv[1])
    logger.write({"env_steps": 8, "eval_return_mean": -1.0})

    def full(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    record_writer.RecordWriter.flush = full
    for step in ("write", "close", "close again"):
        try:
            logger.write({"env_steps": 16, "eval_return_mean": -2.0}) if step == "write" \\
                else logger.close()
            print(step, "ok")
        except OSError as err:
            print(step, "failed:", err.errno == errno.ENOSPC, err.filename)
    """
)


def test_a_full_disk_fails_the_tensorboard_writer_once_and_leaves_nothing_for_exit(tmp_path):
    """The write and the close each raise one OSError naming the folder; once closed, the
    writer is done (a second close is nothing), and the process exits without tensorboardX's
    exit hook or thread printing a traceback."""
    done = subprocess.run([sys.executable, "-c", _FULL_DISK, str(tmp_path)], capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    folder = str(tmp_path / "tensorboard")
    assert done.stdout.splitlines() == [
        f"write failed: True {folder}",
        f"close failed: True {folder}",
        "close again ok",
    ]
    assert "Traceback" not in done.stderr and "Exception" not in done.stderr, done.stderr
    assert (tmp_path / "metrics.jsonl").read_text().count("\n") == 2  # (the line is written first)


class _Part:
    """An output of a run that notes when it is closed, and may fail then."""

    def __init__(self, name: str, calls: list[str], error: Exception | None = None):
        self.name, self.calls, self.error, self.pending = name, calls, error, None

    def close(self) -> None:
        self.calls.append(self.name)
        if self.error is not None:
            raise self.error


def _stopped_run(tmp_path, failed_write: Exception | None, logs_error: Exception):
    """A run's host side with a checkpoint still being written and logs that fail to close."""
    from td3_jax import run as run_module
    from td3_jax.config import TrainConfig

    calls: list[str] = []
    run = run_module._Run(TrainConfig(), tmp_path, [], 1, True, None, None)
    run.display = _Part("display", calls)
    run.checkpointer = _Part("checkpoint", calls)
    run.checkpointer.pending = 2
    run.logger = _Part("logs", calls, logs_error)
    run.failed_write = failed_write
    return run, calls


def test_a_run_stopped_by_a_full_disk_finishes_its_checkpoint_and_says_nothing_more(
    tmp_path, capsys
):
    """The checkpoint being written is finished (and said) before the logs close; the logs'
    last flush failing on the same full disk is no second message: the error line says it."""
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "tensorboard"))
    run, calls = _stopped_run(tmp_path, full, full)
    run.close()
    assert calls == ["display", "checkpoint", "logs"]
    assert capsys.readouterr().err == "td3-jax: finishing checkpoint 2...\n"
    # A run that was not stopped by the disk warns of logs that fail to close.
    run, calls = _stopped_run(tmp_path, None, full)
    run.close()
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "td3-jax: finishing checkpoint 2..."
    assert err[1].startswith("td3-jax: warning: closing the run's logs failed (OSError:")
