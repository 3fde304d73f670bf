"""Run outputs: ``metrics.jsonl`` and TensorBoard event files (``curve.png``:
:mod:`td3_jax.runner.curves`)."""

from __future__ import annotations

import contextlib
import errno
import itertools
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from td3_jax.common import upstream
from td3_jax.common.errors import ConfigError

__all__ = [
    "MetricsLogger",
    "append_line",
    "check_records",
    "evaluated_steps",
    "is_return",
    "read_metrics",
    "returns_by_setting",
    "setting_label",
    "write_atomically",
]

#: The TensorBoard writers this process has opened (a part of each event file's name).
_WRITERS_OPENED = itertools.count()


class MetricsLogger:
    """Appends one JSON object per evaluation to ``metrics.jsonl`` and mirrors it to TensorBoard
    (its evaluation returns at the env steps of the policy evaluated, :func:`evaluated_steps`,
    the other numbers at the record's env steps) and to ``mirror`` (e.g. a
    :class:`td3_jax.runner.tracking.Tracker`: an object whose ``log`` takes each record once the
    file holds it, and never raises).

    On resume, records beyond the restored checkpoint (written after it, then lost with the
    stop) are dropped first, so the file never holds an evaluation twice; TensorBoard drops
    their points too (:func:`_purge_step`), and the kept records' points from there on are
    written again.
    """

    def __init__(self, out_dir: Path, resume_env_steps: int | None = None, enabled: bool = True,
                 mirror: Any = None):  # fmt: skip
        self.enabled, self.mirror = enabled, mirror
        self.path = Path(out_dir) / "metrics.jsonl"
        if not enabled:  # another process writes the logs
            return
        records = read_metrics(self.path)
        kept = [r for r in records
                if resume_env_steps is not None and r["env_steps"] <= resume_env_steps]  # fmt: skip
        write_atomically(self.path, "".join(json.dumps(record) + "\n" for record in kept))
        _say_missing(self.path, kept, resume_env_steps)
        purge = _purge_step(records, resume_env_steps)
        self._tb = _tensorboard_writer(Path(out_dir) / "tensorboard", purge)
        self._to_tensorboard(kept, since=purge or 0)

    def write(self, record: dict[str, Any]) -> None:
        """Appends ``record`` to metrics.jsonl (whole, or not at all) and to TensorBoard; a
        failed write raises ``OSError`` naming the file (TensorBoard's: its folder)."""
        if not self.enabled:
            return
        append_line(self.path, json.dumps(_jsonable(record)) + "\n")
        self._to_tensorboard([record])
        if self.mirror is not None:
            self.mirror.log(record)

    def _to_tensorboard(self, records: list[dict[str, Any]], since: int = 0) -> None:
        """The records' finite numbers at their steps (:func:`evaluated_steps` for returns),
        those from step ``since`` on, then flushed; a failed write raises ``OSError`` naming
        TensorBoard's folder."""
        try:
            for record in records:
                step, evaluated = int(record["env_steps"]), evaluated_steps(record)
                for key, value in record.items():
                    at = evaluated if is_return(key) else step
                    if _plotted(key, value) and at >= since:
                        self._tb.add_scalar(key, value, at)
            self._tb.flush()
        except OSError as err:
            raise OSError(err.errno, err.strerror, err.filename or self._tb.logdir) from err

    def close(self) -> None:
        """Closes the TensorBoard event file; a last flush that the disk refuses raises
        ``OSError`` naming its folder, once: the writer is ended all the same, so nothing of
        it fails again (tensorboardX's exit hook and thread would each print a traceback)."""
        if not self.enabled:
            return
        try:
            self._tb.close()
        except OSError as err:
            upstream.abandon_tensorboard_writer(self._tb)
            raise OSError(err.errno, err.strerror, err.filename or self._tb.logdir) from err


def _say_missing(path: Path, kept: list[dict[str, Any]], resume_env_steps: int | None) -> None:
    """A warning where a resume from ``resume_env_steps`` finds ``path`` without the record of
    its checkpoint's chunk (every checkpoint's chunk wrote one): the file lost its last
    records (cut short or edited), and the resumed run cannot write them again."""
    last = max((int(record["env_steps"]) for record in kept), default=0)
    if resume_env_steps and last < resume_env_steps:
        held = f"has no record after env step {last:,}" if kept else "holds no records"
        lost = f"after env step {last:,} " if kept else ""
        print(f"td3-jax: warning: {path} {held} but the run resumes from its checkpoint at "
              f"{resume_env_steps:,}: the records {lost}up to it are lost (was the file cut "
              "short or edited?); the run goes on from the checkpoint",
              file=sys.stderr)  # fmt: skip


def _plotted(key: str, value: Any) -> bool:
    """Whether a record's ``key: value`` is a TensorBoard point (a finite number)."""
    return isinstance(value, int | float) and key != "env_steps" and math.isfinite(value)


def _purge_step(records: list[dict[str, Any]], resume_env_steps: int | None) -> int | None:
    """The step from which TensorBoard drops the points already logged, on a resume from
    ``resume_env_steps`` (``None``: a fresh run): past the restored checkpoint, or earlier
    where a record written after it plotted its returns at an earlier policy's steps (with the
    evaluation inside the chunk), so that the resumed run's record of them is not a second
    point there."""
    if not resume_env_steps:
        return None
    dropped = [evaluated_steps(r) for r in records if r["env_steps"] > resume_env_steps]
    return min([resume_env_steps + 1, *dropped])


def _tensorboard_writer(folder: Path, purge_step: int | None) -> Any:
    """A tensorboardX ``SummaryWriter`` of ``folder`` (dropping the points already there from
    ``purge_step`` on, where given), writing an event file of its own."""
    SummaryWriter = _summary_writer_class()
    return SummaryWriter(str(folder), purge_step=purge_step, filename_suffix=_event_file_suffix())


def _event_file_suffix() -> str:
    """The end of a new TensorBoard event file's name, which no other writer's has.

    tensorboardX names a file ``events.out.tfevents.<second>.<host>``, so a second writer
    opened in the same second (a resume right after a stop, another process) would open the
    same file again and overwrite the first's events. The suffix adds the time in nanoseconds
    (19 digits, so within a second the files sort, and TensorBoard reads them, in the order they
    were opened: a resume's purge comes after the points it drops), the process id and the
    number of writers this process opened before.
    """
    return f".{time.time_ns()}.{os.getpid()}.{next(_WRITERS_OPENED)}"


def write_atomically(path: Path, text: str) -> None:
    """Writes ``text`` to a temporary file renamed to ``path``, so a reader sees the old file
    or the new one; a failed write (a full disk) removes the temporary file and raises
    ``OSError`` naming ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise OSError(err.errno, err.strerror, str(path)) from err


def probe_write(path: Path) -> None:
    """Raises ``OSError`` where this process cannot write ``path`` (permissions, a read-only
    disk, /proc), before the work that would write it: an existing file is opened to append
    (neither truncated nor touched), else a file beside it is made and removed (a dangling link
    at ``path`` is left as it is)."""
    if path.exists():
        with open(path, "ab"):
            pass
    else:
        tempfile.NamedTemporaryFile(dir=path.parent, suffix=path.suffix).close()


def append_line(path: Path, line: str) -> None:
    """Appends ``line`` to ``path`` in one write; one that fails or stops short (a full disk)
    is cut back off, so the file never ends in part of a line, and raises ``OSError`` naming
    ``path``."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            _append(fd, line.encode())
        finally:
            os.close(fd)
    except OSError as err:
        raise OSError(err.errno, err.strerror, str(path)) from err


def _append(fd: int, data: bytes) -> None:
    """Writes ``data`` at the end of ``fd`` in one write, cut back off if it fails."""
    size = os.fstat(fd).st_size
    try:
        if os.write(fd, data) != len(data):  # the disk filled during the write
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    except OSError:
        with contextlib.suppress(OSError):  # (else read_metrics leaves the cut line out)
            os.ftruncate(fd, size)
        raise


def _summary_writer_class() -> type:
    """tensorboardX's ``SummaryWriter``, imported without PyTorch.

    tensorboardX's writer module imports ``torch`` when it is installed, only to name a type
    (several seconds at every run's start on a machine with PyTorch). Unless something has
    already imported it, ``torch`` is hidden while tensorboardX loads and then made importable
    again; td3-jax logs plain floats, which need no ``torch``.
    """
    if "tensorboardX.writer" in sys.modules or "torch" in sys.modules:
        from tensorboardX import SummaryWriter

        return SummaryWriter
    sys.modules["torch"] = None  # an ImportError for tensorboardX's `import torch`
    try:
        from tensorboardX import SummaryWriter
    finally:
        del sys.modules["torch"]
    return SummaryWriter


def read_metrics(path: Path, warn: bool = True) -> list[dict[str, Any]]:
    """The records of a ``metrics.jsonl`` (an empty list when there is none yet).

    A last line cut short (a run killed, or a disk that filled, while appending it: no line
    end after it, as a record's own comes last) is left out (with a warning where ``warn``);
    any other line that is not JSON raises :class:`~td3_jax.config.schema.ConfigError`.
    """
    path = Path(path)
    if not path.exists():
        return []
    text = path.read_text()
    lines = [line for line in text.splitlines() if line.strip()]
    records = []
    for number, line in enumerate(lines, start=1):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as err:
            if number < len(lines) or text.endswith("\n"):  # (a whole line: not cut short)
                raise ConfigError(f"line {number} of {path} is not a JSON record ({err}); "
                                  "was the file edited? Repair or delete that "
                                  "line") from err  # fmt: skip
            if warn:
                print(f"td3-jax: warning: the last line of {path} is incomplete (a run "
                      "stopped while writing it, or is writing it now); it is left out",
                      file=sys.stderr)  # fmt: skip
    return records


def check_records(path: Path) -> None:
    """A one-line ConfigError, before a resume writes anything, where ``path`` (a run's
    ``metrics.jsonl``) holds a line that is not JSON or a record without its whole-number
    ``env_steps`` (which the resume keeps or drops by): an edited file."""
    for number, record in enumerate(read_metrics(path, warn=False), start=1):
        steps = record.get("env_steps") if isinstance(record, dict) else None
        if not isinstance(steps, int) or isinstance(steps, bool):
            raise ConfigError(f"record {number} of {path} has no whole-number env_steps: was "
                              "the file edited? Repair or delete that line")  # fmt: skip


def evaluated_steps(record: dict) -> int:
    """The env steps of the policy a record evaluated: the record's own, or with the
    evaluation inside the chunk those of its round's policy (once a round has finished)."""
    policy = record.get("eval_policy_env_steps", -1)
    return int(policy) if policy is not None and policy >= 0 else int(record["env_steps"])


def returns_by_setting(per_member: list[dict]) -> dict[tuple, list[float | None]]:
    """A record's ``per_member`` grouped by swept setting: its sorted ``(name, value)`` pairs
    (``()`` for seeds alone), in the order the settings first appear, to its members' mean
    returns (None, or not finite, where a member diverged)."""
    groups: dict[tuple, list[float | None]] = {}
    for member in per_member:
        setting = tuple(sorted((member.get("settings") or {}).items()))
        groups.setdefault(setting, []).append(member.get("eval_return_mean"))
    return groups


def setting_label(setting: Iterable[tuple[str, Any]]) -> str:
    """Swept values, as :func:`returns_by_setting` groups them, as ``actor_lr=0.001 tau=0.01``
    (a value that is not a number, as a hand-edited record may hold, shown as it is)."""
    return " ".join(f"{k}={v:g}" if isinstance(v, int | float) else f"{k}={v}"
                    for k, v in setting)  # fmt: skip


def is_return(key: str) -> bool:
    """Whether a record's key (or a nested one, ``per_member/0/eval_return_mean``) is an
    evaluation return statistic, plotted at :func:`evaluated_steps`."""
    return key.rpartition("/")[2].startswith("eval_return_")


def _jsonable(record: dict[str, Any]) -> dict[str, Any]:
    """Floats stay floats; NaN and infinities become null (JSON has no such numbers)."""
    out = {}
    for key, value in record.items():
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        out[key] = value
    return out
