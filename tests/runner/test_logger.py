"""The run's outputs (``td3_jax.runner.logger``) when the disk refuses them: one error, nothing
more."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import textwrap
import types

import pytest
from support import tensorboard_events

from td3_jax.config.schema import ConfigError

# A process that logs one record, then finds the disk full: TensorBoard's flush fails.
_FULL_DISK = textwrap.dedent(
    """
    import errno, os, sys
    from tensorboardX import record_writer
    from td3_jax.runner.logger import MetricsLogger

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
    from td3_jax.config.schema import TrainConfig
    from td3_jax.runner import run as run_module

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


def _tensorboard_points(run_dir) -> dict[str, list[tuple[int, float]]]:
    """Each tag's points as TensorBoard shows them: a restart marker at step ``s`` (a writer's
    ``purge_step``) drops every point read before it at a step ``>= s``, in every tag
    (``EventAccumulator._CheckForRestartAndMaybePurge``)."""
    points: dict[str, list[tuple[int, float]]] = {}
    for event in tensorboard_events(run_dir):
        if any(getattr(value, "status", None) == 1 for _, value in event.ListFields()):
            # (TensorBoard's log record with status START, 1: a writer's restart marker)
            points = {tag: [p for p in kept if p[0] < event.step] for tag, kept in points.items()}
        for value in event.summary.value:
            points.setdefault(value.tag, []).append((event.step, value.simple_value))
    return points


def _one_second(monkeypatch) -> None:
    """tensorboardX's clock stopped within one second: each event file it opens is named for
    the same second."""
    from tensorboardX import event_file_writer

    clock = types.SimpleNamespace(time=lambda: 1_700_000_000.5)
    monkeypatch.setattr(event_file_writer, "time", clock)


def test_a_resume_shows_each_in_chunk_evaluation_once_in_tensorboard(tmp_path, monkeypatch):
    """With the evaluation inside the chunk, a record plots its returns at its round's policy
    steps, before its own. A run checkpointed at env step 64 that wrote the record of 96 (its
    returns at 64) before it stopped is resumed from 64, within the same second, and writes that
    record again: TensorBoard shows the resumed run's points once each, as a run that never
    stopped would (the first run's file kept, and read before the resume's)."""
    from td3_jax.runner.logger import MetricsLogger

    _one_second(monkeypatch)
    record = lambda steps, ret, loss: {"env_steps": steps, "eval_policy_env_steps": steps - 32,
                                       "eval_return_mean": ret, "critic_loss": loss}  # fmt: skip
    first = MetricsLogger(tmp_path)
    for r in (record(32, 1.0, 0.1), record(64, 2.0, 0.2), record(96, -9.0, -9.0)):
        first.write(r)
    first.close()
    resumed = MetricsLogger(tmp_path, resume_env_steps=64)
    for r in (record(96, 3.0, 0.3), record(128, 4.0, 0.4)):
        resumed.write(r)
    resumed.close()
    points = _tensorboard_points(tmp_path)
    assert points["eval_return_mean"] == [(0, 1.0), (32, 2.0), (64, 3.0), (96, 4.0)]
    steps, losses = zip(*points["critic_loss"], strict=True)
    assert steps == (32, 64, 96, 128) and losses == pytest.approx((0.1, 0.2, 0.3, 0.4))


def test_a_resume_past_the_last_record_says_the_records_between_are_lost(tmp_path, capsys):
    """metrics.jsonl cut back to the record of 32 while the checkpoint is at 96: the resume
    keeps what is there and warns that the records after 32 are lost; a file that holds its
    checkpoint's record resumes without a word."""
    from td3_jax.runner.logger import MetricsLogger, read_metrics

    lines = "".join(json.dumps({"env_steps": s, "critic_loss": 0.1}) + "\n" for s in (32, 64))
    (tmp_path / "metrics.jsonl").write_text(lines[: len(lines) // 2 + 3])  # (64's line cut)
    MetricsLogger(tmp_path, resume_env_steps=96).close()
    err = capsys.readouterr().err
    assert (f"warning: {tmp_path / 'metrics.jsonl'} has no record after env step 32 but the "
            "run resumes from its checkpoint at 96: the records after env step 32 up to it are "
            "lost") in err
    assert [r["env_steps"] for r in read_metrics(tmp_path / "metrics.jsonl")] == [32]
    (tmp_path / "metrics.jsonl").unlink()
    MetricsLogger(tmp_path, resume_env_steps=96).close()
    assert "holds no records but the run resumes from its checkpoint at 96: the records up to " \
        "it are lost" in capsys.readouterr().err
    (tmp_path / "metrics.jsonl").write_text(lines)
    MetricsLogger(tmp_path, resume_env_steps=64).close()
    MetricsLogger(tmp_path).close()  # (a fresh run: nothing to say)
    assert capsys.readouterr().err == ""


def test_two_writers_open_at_once_in_one_folder_each_keep_their_points(tmp_path, monkeypatch):
    """Two writers opened in the same second in one folder (two processes' logs, say), writing
    in turns: each writes a file of its own, and every point of both is there."""
    from td3_jax.runner.logger import _tensorboard_writer

    _one_second(monkeypatch)
    writers = [_tensorboard_writer(tmp_path / "tensorboard", None) for _ in range(2)]
    for steps in (8, 16):
        for value, writer in enumerate(writers):
            writer.add_scalar("critic_loss", value, steps)
            writer.flush()
    for writer in writers:
        writer.close()
    points = _tensorboard_points(tmp_path)["critic_loss"]
    assert sorted(points) == [(8, 0.0), (8, 1.0), (16, 0.0), (16, 1.0)]


@pytest.mark.parametrize(("tail", "cut_short"), [
    ('{"env_steps": 64, "eval_ret', True),  # (no line end: an append cut short)
    ("garbage\n", False),  # (a whole line that is not JSON: an edited file)
    ('{"env_steps": 64\n', False),
])  # fmt: skip
def test_only_a_last_line_without_its_line_end_counts_as_cut_short(tail, cut_short, tmp_path,
                                                                   capsys):  # fmt: skip
    from td3_jax.runner.logger import read_metrics

    path = tmp_path / "metrics.jsonl"
    path.write_text('{"env_steps": 32}\n' + tail)
    if cut_short:
        assert read_metrics(path) == [{"env_steps": 32}]
        assert f"the last line of {path} is incomplete" in capsys.readouterr().err
    else:
        with pytest.raises(ConfigError, match=f"line 2 of {path} is not a JSON record"):
            read_metrics(path)
