"""The run directory (``--out DIR``): its lock, fresh and resumed starts, config.json (with a
factory's environment recorded) and members.json. Reading a finished run back (its checkpoint,
its evaluations) is :mod:`td3_jax.runner.finished`'s.

* **One run at a time.** A run holds an exclusive ``fcntl.flock`` on ``DIR/.lock`` (the file
  names the holder's pid and host) from before it writes anything until it has written its last
  output; the kernel drops the lock when the process dies. A second run on ``DIR`` stops with a
  one-line error and writes nothing.
* **No silent overwrite.** A fresh run refuses a directory that holds a checkpoint (``--resume``
  continues it) or a previous run's records without a checkpoint (move them away first). What a
  run leaves that ended before its first record (killed, even by ``kill -9`` or the kernel's
  out-of-memory killer: config.json, an empty metrics.jsonl) is no run to keep: the same
  command starts over there, once no live process holds the lock. So does a run stopped after
  its first records but before its first checkpoint (a Ctrl-C while it trains its first
  chunk): a fresh run of the same settings and members writes all of them again
  (:func:`stopped_before_checkpoint`), so it replaces them, and says so.
* **config.json says what each member trained with.** In a sweep each swept setting is the
  list of its values, and the ``sweep`` section names the swept settings, each member's values
  and the configuration's own ones (``base``, which the members' values override).
* **Resume keeps the run's identity.** On ``--resume`` only :data:`SAFE_ON_RESUME` may differ
  from the saved config.json (``total_steps`` extends or shortens the run); each change is
  recorded in config.json under ``resume_changes``. Any other difference is a one-line error.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import json
import os
import shlex
import shutil
import socket
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from td3_jax.common import runtime
from td3_jax.common.errors import CheckpointError, LockUnavailableError
from td3_jax.config.build import agent_config, members, ou_params
from td3_jax.config.schema import (
    SWEEPABLE,
    WANDB_SETTINGS,
    ConfigError,
    TrainConfig,
    as_flag,
    field_types,
    flag,
    type_words,
    value_fits,
    whole_iterations,
)
from td3_jax.core.population import Member
from td3_jax.envs import Environment, custom
from td3_jax.runner.logger import check_records, write_atomically
from td3_jax.runner.tracking import WANDB_DIR

__all__ = [
    "CHECKPOINTS",
    "CONFIG_FILE",
    "MEMBERS_FILE",
    "OUTPUTS",
    "SAFE_ON_RESUME",
    "SWEEP",
    "RunLock",
    "check_config_unedited",
    "check_environment_unchanged",
    "check_fresh",
    "check_resume",
    "check_total_steps_reach",
    "checkpoint_steps",
    "clear_outputs",
    "config_changes",
    "ended_before_recording",
    "environment_record",
    "interrupted_message",
    "load_config",
    "load_members",
    "load_run_info",
    "nothing_to_do",
    "open_run_dir",
    "previous_outputs",
    "run_info",
    "save_config",
    "stopped_before_checkpoint",
    "sweep_entries",
    "swept_values",
]

CONFIG_FILE = "config.json"
#: config.json's section of a sweep (:func:`sweep_entries`).
SWEEP = "sweep"
MEMBERS_FILE = "members.json"
LOCK_FILE = ".lock"
CHECKPOINTS = "checkpoints"
# What a run writes into its directory (a fresh run refuses a directory holding any of them).
OUTPUTS = (CONFIG_FILE, MEMBERS_FILE, "metrics.jsonl", "tensorboard", "curve.png", CHECKPOINTS)
# Settings a resumed run may change; every other one fixes the state layout, the key schedule
# or what the checkpoint means.
# (``menagerie``: where the robot meshes lie may differ from one machine to the next; the W&B
# settings say only where the records are mirrored; ``matmuls`` says only which GPU library
# multiplies, the same computation rounded differently, as on another GPU.)
SAFE_ON_RESUME = (
    "total_steps",
    "matmuls",
    "keep_checkpoints",
    "checkpoint_every",
    "eval_envs",
    "early_evaluation",
    "menagerie",
    *WANDB_SETTINGS,
)
# Float hyperparameters: traced values, but changing them mid-run is not reproducible (yet).
FLOAT_SETTINGS = (*SWEEPABLE, "ou_min_sigma")


# --------------------------------------------------------------------------------------------
# the lock
# --------------------------------------------------------------------------------------------


class RunLock:
    """An exclusive ``flock`` on ``DIR/.lock`` held by this process until :meth:`unlock`."""

    def __init__(self, fd: int | None, path: Path):
        self._fd, self.path = fd, path

    def unlock(self) -> None:
        """Unlocks and closes the lock file (the file itself stays)."""
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


def acquire_lock(out_dir: Path) -> RunLock:
    """Locks ``out_dir`` (which must exist) for this process and records its pid and host."""
    path = Path(out_dir) / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        raise ConfigError(f"--out {out_dir}: cannot open {path} ({err.strerror})") from err
    try:
        locked = _try_flock(fd)
    except OSError as err:  # e.g. ENOLCK: a network file system without locks
        os.close(fd)
        raise _cannot_lock(path, err) from None
    if not locked:
        os.close(fd)
        raise in_use_error(out_dir)
    holder = json.dumps({"pid": os.getpid(), "host": socket.gethostname()}) + "\n"
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, holder.encode(), 0)
    except OSError as err:  # e.g. a full disk
        RunLock(fd, path).unlock()
        raise ConfigError(f"--out {out_dir}: cannot write {path} ({err.strerror})") from err
    return RunLock(fd, path)


def _try_flock(fd: int, attempts: int = 5, pause_s: float = 0.05) -> bool:
    """Takes the exclusive lock, retrying briefly: another process's :func:`check_not_in_use`
    probe holds it for an instant, which must not refuse a run that is entitled to it."""
    for attempt in range(attempts):
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if attempt + 1 < attempts:
                time.sleep(pause_s)
    return False


def check_not_in_use(out_dir: Path) -> None:
    """Raises :func:`in_use_error` if another process holds ``out_dir``'s lock; creates nothing."""
    try:
        fd = os.open(Path(out_dir) / LOCK_FILE, os.O_RDONLY)
    except OSError:  # no lock file: nobody ever locked it
        return
    try:  # shared: it conflicts with the holder's exclusive lock, and needs no write access
        # (NFS turns flock into a POSIX lock, whose exclusive form needs a writable file)
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise in_use_error(out_dir) from None
    except OSError as err:
        raise _cannot_lock(Path(out_dir) / LOCK_FILE, err) from None
    finally:
        os.close(fd)  # (also drops this probe's own lock)


def _cannot_lock(path: Path, err: OSError) -> LockUnavailableError:
    """The one line for a lock the file system refuses (``ENOLCK`` on a network file system
    without locking, ...): no run may go on unlocked, since two could then write one directory."""
    return LockUnavailableError(
        f"cannot lock {path} ({err.strerror or err}); a run directory is locked so that two "
        "runs never write one: use a run directory on a local disk"
    )


def in_use_error(out_dir: Path) -> ConfigError:
    return ConfigError(
        f"{out_dir} is in use by another td3-jax run ({lock_holder(out_dir)}); "
        "wait for it to end or choose another --out"
    )


def lock_holder(out_dir: Path) -> str:
    """``pid N on HOST`` as recorded by the lock's holder."""
    try:
        holder = json.loads((Path(out_dir) / LOCK_FILE).read_text())
        return f"pid {holder['pid']} on {holder['host']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "pid unknown"  # (the holder is between locking and writing its name)


# --------------------------------------------------------------------------------------------
# what a directory holds
# --------------------------------------------------------------------------------------------


def checkpoint_steps(out_dir: Path) -> list[int]:
    """The chunk indices of the complete checkpoints in ``out_dir/checkpoints``, ascending."""
    folder = Path(out_dir) / CHECKPOINTS
    if not folder.is_dir():
        return []
    return sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit() and p.is_dir())


def previous_outputs(out_dir: Path) -> list[str]:
    """The names in :data:`OUTPUTS` that ``out_dir`` holds (empty folders do not count)."""
    found = []
    for name in OUTPUTS:
        path = Path(out_dir) / name
        if path.is_dir() and not any(path.iterdir()):
            continue
        if path.exists():
            found.append(name)
    return found


# --------------------------------------------------------------------------------------------
# starting a run
# --------------------------------------------------------------------------------------------


def check_fresh(out_dir: Path, *, writer: bool = True, locked: bool = False,
                run: tuple[TrainConfig, list[Member]] | None = None) -> bool:  # fmt: skip
    """Raises one-line errors when a fresh run cannot start in ``out_dir``; creates nothing.
    Returns whether the run starts over there: ``run``, its ``(cfg, population)``, finds the
    outputs of the same run stopped before its first checkpoint
    (:func:`stopped_before_checkpoint`), which it may replace.

    ``writer``: this process writes the logs (the lock and the outputs are its business; other
    processes of a multi-process run only check what cannot change under them). ``locked``:
    this process holds the lock already (a second flock of the file would fail).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"--out {out_dir} is a file, not a directory")
    if not out_dir.is_dir():
        if writer:  # (open_run_dir makes it later)
            _check_can_create(out_dir)
        return False
    if writer and not locked:
        check_not_in_use(out_dir)
    if checkpoint_steps(out_dir):
        raise ConfigError(f"{out_dir} already holds a run; pass --resume or choose a new --out")
    over = writer and run is not None and stopped_before_checkpoint(out_dir, *run)
    outputs = previous_outputs(out_dir) if writer and not over else []
    if outputs and not ended_before_recording(out_dir):
        raise ConfigError(
            f"{out_dir} holds a previous run's outputs ({', '.join(outputs)}) but no checkpoint "
            "to resume; move them away or choose another --out"
        )
    others = foreign_entries(out_dir) if writer else []
    if others:
        raise ConfigError(
            f"--out {out_dir} is a directory of other files ({', '.join(others[:3])}"
            f"{', ...' if len(others) > 3 else ''}); a run needs a new or empty directory of "
            "its own"
        )
    return over


def stopped_before_checkpoint(out_dir: Path, cfg: TrainConfig, population: list[Member]) -> bool:
    """Whether ``out_dir`` holds the outputs of a fresh run of ``cfg`` and ``population`` (its
    config.json's settings and members.json as this run writes them, no resume) that
    recorded, then stopped before its first checkpoint (every record at that checkpoint's env
    step or before: not a run whose checkpoints were deleted), and nothing of others (in its
    folders too): a fresh run of the same settings starts over there (:func:`clear_outputs`),
    since it writes again everything that run wrote. Never for an environment of the user's
    own, whose code may have changed since."""
    out_dir = Path(out_dir)
    if (custom.is_custom(cfg.env) or not out_dir.is_dir() or checkpoint_steps(out_dir)
            or foreign_entries(out_dir) or not _only_run_files(out_dir)):  # fmt: skip
        return False
    try:
        saved = json.loads((out_dir / CONFIG_FILE).read_text())
        listing = json.loads((out_dir / MEMBERS_FILE).read_text())
        steps = _recorded_steps(out_dir / "metrics.jsonl")
    except (OSError, ValueError, TypeError, KeyError):
        return False
    values = _as_used(cfg)
    expected = json.loads(json.dumps({**values, **sweep_entries(values, population)}))
    if not isinstance(saved, dict) or "resume_changes" in saved:
        return False
    same = all(saved.get(k) == v for k, v in expected.items())
    first = min(cfg.checkpoint_every * cfg.steps_per_chunk, cfg.run_steps)
    return (same and listing == json.loads(json.dumps(_members_listing(population)))
            and bool(steps) and all(step <= first for step in steps))  # fmt: skip


def _only_run_files(out_dir: Path) -> bool:
    """Whether ``out_dir``'s checkpoints folder holds nothing but Orbax's unfinished writes
    and its TensorBoard folder nothing but event files (what a run puts there)."""
    checkpoints, events = Path(out_dir) / CHECKPOINTS, Path(out_dir) / "tensorboard"
    kept = [p for p in checkpoints.iterdir() if "orbax-checkpoint-tmp" not in p.name] if (
        checkpoints.is_dir()) else []  # fmt: skip
    others = [p for p in events.iterdir() if not (p.is_file() and p.name.startswith(
        "events.out.tfevents."))] if events.is_dir() else []  # fmt: skip
    return not kept and not others


def _recorded_steps(path: Path) -> list[int]:
    """The env steps of the records in a metrics.jsonl (none where it is missing)."""
    if not path.exists():
        return []
    return [int(json.loads(line)["env_steps"]) for line in path.read_text().splitlines()
            if line.strip()]  # fmt: skip


def clear_outputs(out_dir: Path) -> None:
    """Removes a run's outputs from ``out_dir`` (:data:`OUTPUTS`; its lock and W&B's folder
    stay), for a run that starts over there (:func:`stopped_before_checkpoint`,
    :func:`ended_before_recording`)."""
    for name in OUTPUTS:
        path = Path(out_dir) / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def ended_before_recording(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds only what a run leaves that ended before its first evaluation
    record (a kill, an out-of-memory kill, a crash): no checkpoint, no record (metrics.jsonl
    missing or empty), no curve and no file of others. Nothing there is worth keeping, so a
    fresh run may start in it (its lock is checked apart)."""
    out_dir = Path(out_dir)
    metrics = out_dir / "metrics.jsonl"
    records = metrics.exists() and not (metrics.is_file() and metrics.stat().st_size == 0)
    drawn = (out_dir / "curve.png").exists()
    return not (checkpoint_steps(out_dir) or records or drawn or foreign_entries(out_dir))


def foreign_entries(out_dir: Path) -> list[str]:
    """Names in ``out_dir`` that no run writes (sorted), e.g. for ``--out ~`` or ``--out /``.

    W&B's folder is a run's too, though not an output that makes a directory used: a run
    stopped before it wrote anything else (while compiling) can start again in its directory."""
    ours = {*OUTPUTS, LOCK_FILE, WANDB_DIR}
    return sorted(p.name for p in Path(out_dir).iterdir() if p.name not in ours)


def check_resume(
    out_dir: Path, cfg: TrainConfig, sweep: dict | None = None, *, writer: bool = True
) -> tuple[list[Member], dict[str, list]]:
    """``(members, changes)`` of a resume of ``out_dir`` with ``cfg``; creates nothing.

    ``changes`` maps each changed setting of :data:`SAFE_ON_RESUME` to ``[saved, new]``. Raises
    one-line errors for a directory without a checkpoint, one in use, a changed structural
    setting, sweep values other than the saved members' or a run already past ``total_steps``.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        what = "is not a directory" if out_dir.exists() else "does not exist"
        raise ConfigError(f"--resume given but {out_dir} {what}: there is no checkpoint to resume")
    if writer:
        check_not_in_use(out_dir)
    steps = checkpoint_steps(out_dir)
    if not steps and not previous_outputs(out_dir) and not (out_dir / LOCK_FILE).exists():
        raise ConfigError(f"--resume given but {out_dir} is not a td3-jax run directory "
                          "(it holds none of a run's files); --out names the run to "
                          "resume")  # fmt: skip
    if not steps:
        raise ConfigError(
            f"--resume given but {out_dir / CHECKPOINTS} has no checkpoint{_start_instead(out_dir)}"
        )
    population = load_members(out_dir, cfg)
    saved = load_config(out_dir)
    check_config_unedited(out_dir, saved)  # (an edited config.json first: cfg may come from it)
    changes = config_changes(saved, cfg, population)
    if writer:  # (before config.json is rewritten: a resume that stops writes nothing)
        check_records(out_dir / "metrics.jsonl")
    if "total_steps" in changes and cfg.lr_schedule == "cosine":
        raise ConfigError(
            "--total-steps cannot change on --resume with --lr-schedule cosine: the schedule's "
            "length is the run's number of updates (start a new run to train longer)"
        )
    if sweep and members(cfg, sweep) != population:
        raise ConfigError(
            f"the --sweep-* values ({sweep_flags(sweep)}) differ from the members of the run in "
            f"{out_dir} ({sweep_flags(swept_values(population)) or 'no swept setting'}, "
            f"{MEMBERS_FILE}); leave them out to resume"
        )
    check_total_steps_reach(out_dir, cfg)
    return population, changes


def check_total_steps_reach(out_dir: Path, cfg: TrainConfig) -> None:
    """A one-line ConfigError where the resume of ``out_dir`` with ``cfg`` asks for fewer env
    steps (``--total-steps``) than the run has already taken (its newest checkpoint); nothing
    where it has no checkpoint yet. Checked before ``cfg`` itself, whose advice for a short run
    (a smaller ``--warmup-steps``) a resume could not follow."""
    if cfg.env_steps_per_iter <= 0 or cfg.eval_every <= 0:  # (validate says what is wrong)
        return
    steps = checkpoint_steps(out_dir)
    if not steps or cfg.num_chunks >= steps[-1]:
        return
    # (whole chunks, or the run's end where its last chunk was shortened)
    done = min(steps[-1] * cfg.iters_per_chunk * cfg.env_steps_per_iter,
               load_config(out_dir).run_steps)  # fmt: skip
    raise ConfigError(
        f"--total-steps {cfg.total_steps} is less than the {done} env steps the run in "
        f"{out_dir} has already taken (give more to extend it)"
    )


def _check_can_create(out_dir: Path) -> None:
    """A ConfigError, before the environment is made or anything traced, where a fresh run's
    missing ``out_dir`` could not be made: its nearest existing parent is a file, or a folder
    this user may not write in (as :func:`open_run_dir` would say it)."""
    parent = Path(out_dir).absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        code = errno.ENOTDIR
    elif _read_only(parent):
        code = errno.EROFS
    elif not os.access(parent, os.W_OK | os.X_OK):
        code = errno.EACCES
    else:
        return
    raise ConfigError(f"--out {out_dir}: cannot create it ({os.strerror(code)})")


def _read_only(folder: Path) -> bool:
    """Whether ``folder``'s file system is mounted read-only (False where it cannot tell)."""
    try:
        return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def open_run_dir(out_dir: Path, *, resume: bool, writer: bool = True,
                 run: tuple[TrainConfig, list[Member]] | None = None) -> RunLock:  # fmt: skip
    """Creates (fresh run) and locks ``out_dir``, re-checking a fresh one under the lock.

    ``run``: the fresh run's ``(cfg, population)``; where ``out_dir`` holds the outputs of the
    same run stopped before its first checkpoint (:func:`stopped_before_checkpoint`), or of
    any run that ended before its first record (:func:`_start_over`), they are removed under
    the lock, with a line that says so, and the run starts over there.
    Processes other than the writer neither lock nor check; they get a lock that holds nothing.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"--out {out_dir}: cannot create it ({err.strerror or err})") from err
    if not writer:
        return RunLock(None, out_dir / LOCK_FILE)
    lock = acquire_lock(out_dir)
    if not resume:
        try:
            _start_over(out_dir, check_fresh(out_dir, locked=True, run=run))
        except BaseException:
            lock.unlock()
            raise
    return lock


def _start_over(out_dir: Path, same_run: bool) -> None:
    """Removes, with a line that says so, the outputs a fresh run may replace in ``out_dir``:
    those of the same run stopped before its first checkpoint (``same_run``), or of any run
    that ended before its first record (:func:`ended_before_recording`) where its checkpoints
    and TensorBoard folders hold only what a run writes there (else nothing is removed)."""
    if same_run:
        why = "the run of these settings there stopped before its first checkpoint"
    elif (previous_outputs(out_dir) and ended_before_recording(out_dir)
          and _only_run_files(out_dir)):  # fmt: skip
        why = "the run there ended before its first record"
    else:
        return
    clear_outputs(out_dir)
    print(f"td3-jax: starting over in {out_dir}: {why}", flush=True)


#: What to do with a directory that holds a run's outputs but no checkpoint: a fresh run is
#: refused there while they stay (:func:`check_fresh`), and there is nothing to resume.
_MOVE_AWAY = "move it away or choose another --out to train again"


def _start_instead(out_dir: Path) -> str:
    """What a ``--resume`` of ``out_dir`` without a checkpoint says to do: start without it
    where its run ended before its first record (:func:`ended_before_recording`: a fresh start
    is accepted there), else move it away, unless the command that started it starts it over
    (a run stopped in its first chunk: :func:`stopped_before_checkpoint`; not one whose
    checkpoints were deleted)."""
    if not ended_before_recording(out_dir):
        return (f" (it holds a run's outputs but no checkpoint: {_MOVE_AWAY}, unless its run "
                "stopped in its first chunk: then the command that started it, without "
                "--resume, starts it over)")
    return " (its run stopped before the first: run without --resume to start it)"


def _stopped_before_training(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds what a run leaves that stopped before it wrote anything: its
    lock file (and empty folders), no output and nothing else, so a fresh run may start there."""
    out_dir = Path(out_dir)
    return (out_dir / LOCK_FILE).exists() and not (
        checkpoint_steps(out_dir) or previous_outputs(out_dir) or foreign_entries(out_dir)
    )


def training_holder(out_dir: Path) -> str | None:
    """``pid N on HOST`` of a td3-jax run that holds ``out_dir``'s lock now, else None; a
    file system that refuses locks is :class:`LockUnavailableError`."""
    try:
        check_not_in_use(out_dir)
    except LockUnavailableError:
        raise
    except ConfigError:
        return lock_holder(out_dir)
    return None


def holder_for_reader(out_dir: Path) -> str | None:
    """:func:`training_holder` for a command that only reads ``out_dir`` (``eval``, ``plot``):
    None also where the file system refuses locks, since a reader takes none."""
    try:
        return training_holder(out_dir)
    except LockUnavailableError:
        return None


def no_checkpoint_error(out_dir: Path) -> ConfigError:
    """Why a run directory with a config.json has no checkpoint to read (``eval``, ``render``,
    ``export``): a run training it has not written its first, or there is none to wait for."""
    holder = holder_for_reader(out_dir)
    if holder is not None:
        return ConfigError(f"{out_dir} has no checkpoint yet: a td3-jax run ({holder}) is "
                           "training it and has not written its first; try again "
                           "later")  # fmt: skip
    if ended_before_recording(out_dir):
        return ConfigError(f"{out_dir} holds no checkpoint (its run stopped before its first "
                           "evaluation), so there is no policy to read: run its td3-jax train "
                           "command again to start it over")  # fmt: skip
    return ConfigError(f"{out_dir} holds no checkpoint (its run stopped before writing one, or "
                       "they were removed), so there is no policy to read: train it again with "
                       "td3-jax train (move it away or give another --out)")  # fmt: skip


def is_sweep_dir(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds a sweep's run: its config.json has a :data:`SWEEP` section,
    or (a sweep written before that section) its members.json lists swept values; False where
    config.json is missing or unreadable."""
    try:
        if SWEEP in json.loads((Path(out_dir) / CONFIG_FILE).read_text()):
            return True
        listing = json.loads((Path(out_dir) / MEMBERS_FILE).read_text())
    except (OSError, ValueError, TypeError):
        return False
    return isinstance(listing, list) and any(
        isinstance(m, dict) and bool(m.get("overrides")) for m in listing
    )


def resume_command(out_dir: Path, extra: str = "") -> str:
    """``td3-jax sweep --out OUT --resume`` for a sweep's directory (:func:`is_sweep_dir`; it
    then ends with the sweep's ranking), else ``td3-jax train``'s; OUT quoted for a shell,
    ``extra`` flags (e.g. `` --total-steps N``) after it. The run directory does not record
    how many processes ran it: in a process that ``--local-processes N`` started, the command
    ends with that flag, and in one started by hand with the others, with a note that each
    process resumes with its own join flags."""
    command = "sweep" if is_sweep_dir(out_dir) else "train"
    count = runtime.local_processes()
    processes = f" --local-processes {count}" if count else ""
    resume = f"td3-jax {command} --out {shlex.quote(str(out_dir))} --resume{extra}{processes}"
    if not count and runtime.joined_others():  # (started by hand)
        resume += (" in each process, with its own --coordinator-address, --num-processes and "
                   "--process-id")  # fmt: skip
    return resume


def nothing_to_do(out_dir: Path, cfg: TrainConfig, python: bool = False) -> str:
    """The line of a resume that finds nothing to train: how far the run went and how to
    train it further (a larger ``--total-steps``; a new run where a cosine schedule fixed its
    length; for a run stopped short and resumed with a smaller ``--total-steps``, the steps it
    was set for). ``python``: in the words of :func:`td3_jax.train`'s caller
    (``total_steps=N``, ``resume=True``), else the command line's."""
    steps = "total_steps" if python else "--total-steps"

    def go_on(total: int, saved: bool) -> str:  # (saved: the steps config.json holds)
        if python:
            return f"resume=True with total_steps={total}"
        return resume_command(out_dir, "" if saved else f" --total-steps {total}")

    done, planned = f"{cfg.run_steps:,}", load_config(out_dir).run_steps
    if planned > cfg.run_steps:  # a stopped run resumed with a shorter --total-steps
        asked = f"total_steps={cfg.total_steps}" if python else f"--total-steps {cfg.total_steps}"
        return (f"nothing to do: the run in {out_dir} has taken {done} env steps, what {asked} "
                f"asks; it was set for {planned:,}: {go_on(planned, saved=True)} goes on to "
                "them")  # fmt: skip
    if cfg.lr_schedule == "cosine":
        further = ("its cosine learning-rate schedule fixed its length: start a new run with a "
                   f"larger {steps} to train longer")  # fmt: skip
    else:
        more = 2 * cfg.run_steps
        further = f"{go_on(more, saved=False)} goes on to {more:,}"
    return f"nothing to do: the run in {out_dir} is complete ({done} env steps); {further}"


def interrupted_message(out_dir: Path, cause: str = "interrupted") -> str:
    """What a run stopped by ``cause`` (a Ctrl-C, a SIGTERM) leaves behind, in one line."""
    steps = checkpoint_steps(out_dir)
    if steps:
        newest = Path(out_dir) / CHECKPOINTS / str(steps[-1])
        if _complete(out_dir, steps[-1]):
            return f"{cause} after the run's last chunk: the run is complete ({newest})"
        return f"{cause}; the newest checkpoint is {newest} (continue with: " \
               f"{resume_command(out_dir)})"  # fmt: skip
    if not Path(out_dir).exists():
        return f"{cause} before the run wrote anything to {out_dir} (run the same command again)"
    again = "run the same command again to start over"
    with contextlib.suppress(OSError, ValueError, AttributeError):  # (no config.json: as said)
        if custom.is_custom(json.loads((Path(out_dir) / CONFIG_FILE).read_text()).get("env", "")):
            again = "remove it or choose another --out to start again"  # (its code may differ)
    return f"{cause} before the first checkpoint: {out_dir} holds none to resume ({again})"


def _complete(out_dir: Path, chunks_done: int) -> bool:
    """Whether ``chunks_done`` chunks finish the run recorded in ``out_dir``'s config.json."""
    try:
        return chunks_done >= load_config(out_dir).num_chunks
    except (ConfigError, OSError, ValueError, TypeError):
        return False


# --------------------------------------------------------------------------------------------
# the resume policy
# --------------------------------------------------------------------------------------------


def config_changes(
    saved: TrainConfig, cfg: TrainConfig, population: Sequence[Member] = ()
) -> dict[str, list]:
    """``{name: [saved, new]}`` of the changed safe settings; a one-line error for any other,
    naming what the run used: a setting ``population``'s members override as their values
    (``--sweep-tau 0.01 0.02``), not ``saved``'s, which they override; a run of an object
    resumed without one says to pass the object again."""
    if saved.env.startswith(custom.OBJECT_PREFIX) and not cfg.env.startswith(custom.OBJECT_PREFIX):
        raise custom.object_run_error(saved.env)  # (a resume without the object: env= left out)
    changes, safe = {}, _safe_on_resume(saved)
    swept = swept_values(population)
    for field in dataclasses.fields(TrainConfig):
        old, new = getattr(saved, field.name), getattr(cfg, field.name)
        if old == new or _effective(saved, field.name) == _effective(cfg, field.name):
            continue
        if field.name not in safe:
            used = (as_flag(f"sweep_{field.name}", swept[field.name]) if field.name in swept
                    else _shown(saved, field.name))  # fmt: skip
            raise ConfigError(_mismatch(field.name, used, _shown(cfg, field.name), safe))
        changes[field.name] = [old, new]
    return changes


def eval_every_as_saved(cfg: TrainConfig, saved: TrainConfig) -> TrainConfig:
    """``cfg`` for a resume of the run whose config.json holds ``saved``: its ``eval_every``
    replaced by the saved one where the fresh run took it as those whole iterations (``3000``
    with 16 environments: the run's chunks of 3008 steps); unchanged otherwise (another value
    is a change, which :func:`config_changes` refuses; so is one that the fresh run lowered to
    a run shorter than it, unless it rounds to the saved chunk)."""
    if cfg.env_steps_per_iter <= 0:
        return cfg
    if saved.steps_per_chunk in whole_iterations(cfg.eval_every, cfg.env_steps_per_iter):
        return dataclasses.replace(cfg, eval_every=saved.eval_every)
    return cfg


def fixed_settings(cfg: TrainConfig) -> dict[str, Any]:
    """The settings of ``cfg`` that a resume may not change (all but :data:`SAFE_ON_RESUME`), as
    config.json records them: what each checkpoint keeps, so that a resume notices a config.json
    edited since (:func:`check_unedited`)."""
    safe = _safe_on_resume(cfg)
    return json.loads(json.dumps({k: v for k, v in _as_used(cfg).items() if k not in safe}))


def check_config_unedited(out_dir: Path, saved: TrainConfig) -> None:
    """:func:`check_unedited` of ``saved`` (``out_dir``'s config.json) against the settings
    recorded in its newest checkpoint whose record is intact (damaged ones are skipped, as a
    restore skips them; no checkpoint: nothing to check), before anything is restored: a
    hand-edited ``num_envs`` or ``env`` is then named as the setting it is, not as the arrays
    it changes."""
    from td3_jax.runner.checkpoint import Checkpointer  # (lazy: orbax)

    checkpointer = Checkpointer(Path(out_dir) / CHECKPOINTS, create=False)
    try:
        for step in reversed(checkpointer.steps()):
            try:
                recorded = checkpointer.read_meta(step).get("settings")
            except CheckpointError:
                continue
            check_unedited(recorded, saved, Path(out_dir) / CONFIG_FILE)
            return
    finally:
        checkpointer.close()


def check_unedited(recorded: Any, cfg: TrainConfig, path: Path) -> None:
    """A one-line ConfigError where a setting of ``cfg`` (read from ``path``, config.json)
    differs from the one the checkpoint was written with (``recorded``: its
    :func:`fixed_settings`; not a dict: a checkpoint written before they were kept)."""
    if not isinstance(recorded, dict):
        return
    now = fixed_settings(cfg)
    for name, value in recorded.items():
        if name not in now or now[name] == value or _same_effect(cfg, name, value):
            continue
        raise ConfigError(f"{path}: {name} is {json.dumps(now[name])} but the run's checkpoints "
                          f"were written with {json.dumps(value)}; was the file edited? Restore "
                          "its value")  # fmt: skip


def _same_effect(cfg: TrainConfig, name: str, value: Any) -> bool:
    """Whether ``cfg`` with its setting ``name`` as the JSON ``value`` takes effect as ``cfg``."""
    try:
        other = dataclasses.replace(cfg, **{name: tuple(value) if isinstance(value, list)
                                            else value})  # fmt: skip
        return _effective(other, name) == _effective(cfg, name)
    except (TypeError, ValueError, ConfigError):
        return False


def _safe_on_resume(saved: TrainConfig) -> tuple[str, ...]:
    """:data:`SAFE_ON_RESUME`, less ``eval_envs`` for a run whose evaluation worlds are in the
    environment batch (``--eval-in-chunk``: their number is part of the checkpoint)."""
    if saved.eval_in_chunk:
        return tuple(name for name in SAFE_ON_RESUME if name != "eval_envs")
    return SAFE_ON_RESUME


def _effective(cfg: TrainConfig, name: str) -> Any:
    """The value a setting takes effect with (``None`` stands for the algorithm's default)."""
    if name in ("hidden_sizes", "actor_lr", "critic_lr", "tau"):
        value = getattr(agent_config(cfg), name)
        return tuple(value) if name == "hidden_sizes" else value
    if name == "ou_min_sigma":
        return ou_params(cfg).min_sigma
    return getattr(cfg, name)


def _shown(cfg: TrainConfig, name: str) -> str:
    """A setting as the flag it took effect with: ``--actor-lr 0.001`` for a TD3 run whose
    --actor-lr was left to the algorithm (``None``); ``no --max-grad-norm`` for one left off."""
    value = _effective(cfg, name)
    if value is None and name in ("actor_hidden_sizes", "critic_hidden_sizes"):
        value = _effective(cfg, "hidden_sizes")
    return f"no {flag(name)}" if value is None else as_flag(name, value)


# Why a setting cannot change on --resume, where a general reason would not say enough.
_REASONS = {
    "eval_every": "the checkpoints count chunks of --eval-every env steps",
    "seed": "the run's random keys derive from it",
    "seeds": "the members and their states are fixed (members.json)",
    "num_envs": "it fixes the environment and replay state in the checkpoint",
    "buffer_size": "it fixes the replay buffer in the checkpoint",
    "eval_envs": "with --eval-in-chunk the evaluation worlds are in the checkpoint's environments",
    "return_bound": "its return statistics are part of the checkpoint's state",
}


def _mismatch(name: str, saved: str, given: str, safe_names: tuple[str, ...]) -> str:
    if name in FLOAT_SETTINGS and name not in _REASONS:
        why = (
            "learning rates, tau, noise scales and the discount cannot change on --resume yet "
            "(the continued run would not be reproducible)"
        )
    else:
        why = _REASONS.get(name, "it fixes the run's state layout, key schedule or meaning")
    safe = ", ".join(flag(n) for n in safe_names)
    return (
        f"{given} given but the run was started with {saved}: "
        f"{why}; leave it out to resume (only {safe} may change) or start a new --out"
    )


# --------------------------------------------------------------------------------------------
# config.json and members.json
# --------------------------------------------------------------------------------------------


def save_config(
    cfg: TrainConfig, population: list[Member], out_dir: Path, info: dict | None = None
) -> None:
    """Writes config.json (the resolved config, then ``info``: preset, resume_changes, ...;
    for a sweep, :func:`sweep_entries`) and members.json, each atomically (a temporary file
    renamed)."""
    out_dir = Path(out_dir)
    values = _as_used(cfg)
    extra = {k: v for k, v in (info or {}).items() if k != SWEEP}  # (made anew: the members')
    _write_json(out_dir / CONFIG_FILE, {**values, **extra, **sweep_entries(values, population)})
    _write_json(out_dir / MEMBERS_FILE, _members_listing(population))


def _members_listing(population: list[Member]) -> list[dict[str, Any]]:
    """members.json's content for ``population``."""
    return [{"seed": m.seed, "overrides": dict(m.overrides)} for m in population]


def sweep_entries(values: dict[str, Any], population: Sequence[Member]) -> dict[str, Any]:
    """config.json's entries for ``population``'s swept settings (``{}`` where no member
    overrides one): each swept setting as the list of its values (in the members' order), in
    place of ``values``' one value, which the members' override, and :data:`SWEEP`:
    ``settings`` (their names), ``base`` (their values in ``values``, the run's configuration,
    which :func:`load_config` reads back) and ``members`` (each member's seed and values, in
    members.json's order)."""
    swept = swept_values(population)
    if not swept:
        return {}
    section = {
        "settings": list(swept),
        "base": {n: values[n] for n in swept},
        "members": [{"seed": m.seed, **dict(m.overrides)} for m in population],
    }
    return {**swept, SWEEP: section}


def sweep_flags(values: dict[str, Sequence[float]]) -> str:
    """``{"actor_lr": [0.001, 0.0003]}`` as the flags that give it:
    ``--sweep-actor-lr 0.001 0.0003`` (settings in the dict's order)."""
    return " ".join(f"--sweep-{name.replace('_', '-')} " + " ".join(f"{v:g}" for v in vals)
                    for name, vals in values.items())  # fmt: skip


def swept_values(population: Sequence[Member]) -> dict[str, list[float]]:
    """``{setting: values}`` of the settings ``population``'s members override, sorted by
    name, each setting's distinct values in the members' order (``{}``: no member overrides
    one)."""
    each = [dict(m.overrides) for m in population]
    names = sorted({name for overrides in each for name in overrides})
    return {n: list(dict.fromkeys(o[n] for o in each if n in o)) for n in names}


def _sweep_base(raw: dict, path: Path) -> dict[str, Any]:
    """The swept settings' values in the run's configuration, from config.json's
    :data:`SWEEP` section (``{}`` without one: not a sweep, or written before sweeps had it)."""
    if SWEEP not in raw:
        return {}
    section = raw[SWEEP]
    base = section.get("base") if isinstance(section, dict) else None
    if not isinstance(base, dict):
        raise ConfigError(f"{path}: its {SWEEP!r} section has no 'base' values of the swept "
                          "settings (td3-jax writes them there; was the file edited?)")  # fmt: skip
    return base


#: Settings whose ``None`` means "the algorithm's default"
#: (:func:`td3_jax.config.build.agent_config`).
_ALGORITHM_DEFAULTS = ("hidden_sizes", "actor_lr", "critic_lr", "tau")


def _as_used(cfg: TrainConfig) -> dict[str, Any]:
    """``cfg`` as config.json records it: the settings left to the algorithm (``None``) as the
    values the run uses (a TD3 run's ``actor_lr`` 0.001, not null). An older config.json with
    nulls still loads (:func:`load_config`) and resumes: both mean the same values."""
    values = dataclasses.asdict(cfg)
    agent = agent_config(cfg)
    for name in _ALGORITHM_DEFAULTS:
        if values[name] is None:
            values[name] = getattr(agent, name)
    return values


def _write_json(path: Path, value: Any) -> None:
    write_atomically(path, json.dumps(value, indent=2) + "\n")


def require_run_dir(out_dir: Path) -> None:
    """Raises ConfigError where ``out_dir`` is not a directory (missing, or a file)."""
    if not Path(out_dir).is_dir():
        what = "is a file, not a run directory" if Path(out_dir).exists() else "does not exist"
        raise ConfigError(f"{out_dir} {what} (give the directory td3-jax train wrote to)")


def _read_config(out_dir: Path) -> dict:
    path = Path(out_dir) / CONFIG_FILE
    require_run_dir(out_dir)
    if not path.exists():
        holder = training_holder(out_dir)
        if holder is not None:
            raise ConfigError(
                f"{out_dir} is being started by a td3-jax run ({holder}) and holds "
                "no config.json or checkpoint yet; try again after its first evaluation"
            )
        if _stopped_before_training(out_dir):
            raise ConfigError(
                f"{out_dir} holds no {CONFIG_FILE} or checkpoint: its run stopped before it "
                "trained (run its td3-jax train command again to start it)"
            )
        if checkpoint_steps(out_dir):
            raise ConfigError(
                f"{out_dir} holds checkpoints but no {CONFIG_FILE} (deleted?), which td3-jax "
                f"reads to rebuild the run: restore it from a copy (each checkpoint's "
                f"{CHECKPOINTS}/N/meta/metadata lists, under 'settings', those a resume may "
                "not change)"
            )
        raise ConfigError(f"{out_dir} holds no {CONFIG_FILE}: not a td3-jax run directory"
                          f"{_run_above(Path(out_dir))}")  # fmt: skip
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ConfigError(f"{path} is not valid JSON ({err}); restore it from a copy (each "
                          f"checkpoint's {CHECKPOINTS}/N/meta/metadata lists, under 'settings', "
                          "those a resume may not change)") from err  # fmt: skip
    if not isinstance(raw, dict):
        raise ConfigError(f"{path} does not hold a configuration (a JSON object)")
    return raw


def _run_above(folder: Path) -> str:
    """A hint naming the run directory that holds ``folder`` (its checkpoints/ or one
    checkpoint of it: ``runs/x/checkpoints/3``), else ``""``."""
    for parent in list(folder.absolute().parents)[:2]:
        if (parent / CONFIG_FILE).is_file() and CHECKPOINTS in folder.absolute().parts:
            shown = parent if folder.is_absolute() else os.path.relpath(parent)
            return f" (its run is {shown}: give that folder)"
    return ""


def load_config(out_dir: Path) -> TrainConfig:
    """The resolved config a run directory was started with (other keys of config.json, such
    as ``preset`` and ``resume_changes``, are ignored; see :func:`load_run_info`). A sweep's
    swept settings, listed in config.json with every member's values, come back as the run's
    configuration had them (its ``sweep`` section's ``base``; the members: :func:`load_members`)."""
    raw = _read_config(out_dir)
    raw.update(_sweep_base(raw, Path(out_dir) / CONFIG_FILE))  # (the lists are the members')
    for name in ("hidden_sizes", "actor_hidden_sizes", "critic_hidden_sizes"):
        if raw.get(name) is not None:
            raw[name] = tuple(raw[name])
    if "impl" not in raw and str(raw.get("env", "")).startswith("playground/"):
        # written before --impl: Playground ran on Warp with --env-backend warp, else on JAX
        raw["impl"] = "warp" if raw.get("env_backend") == "warp" else "jax"
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    settings = {k: v for k, v in raw.items() if k in known}
    _check_setting_types(settings, Path(out_dir) / CONFIG_FILE)
    return TrainConfig(**settings)


def _check_setting_types(settings: dict[str, Any], path: Path) -> None:
    """A one-line ConfigError for a setting of config.json whose JSON value is not of its
    field's type (a hand-edited ``"num_envs": "4"``), rather than a traceback later."""
    hints = field_types()
    for name, value in settings.items():
        if not value_fits(value, hints[name]):
            expected = type_words(hints[name], json_words=True)
            raise ConfigError(f"{path}: {name} is {json.dumps(value)} (expected {expected}); was "
                              "the file edited? Restore its value")  # fmt: skip


def load_run_info(out_dir: Path) -> dict:
    """The keys of config.json that are not settings: ``preset``, ``resume_changes``, ..."""
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    return {k: v for k, v in _read_config(out_dir).items() if k not in known}


def run_info(
    out_dir: Path, *, resume: bool, preset: str | None, changes: dict, at_env_steps: int
) -> dict:
    """config.json's extra keys: a fresh run's preset (if it came from one); on resume, the
    saved ones plus this resume's ``changes`` appended to ``resume_changes``."""
    if not resume:
        return {"preset": preset} if preset else {}
    info = load_run_info(out_dir)
    if changes:
        entry = {"at_env_steps": at_env_steps, **changes}
        info["resume_changes"] = [*info.get("resume_changes", []), entry]
    return info


def load_members(out_dir: Path, cfg: TrainConfig) -> list[Member]:
    """The members of a run directory (its seeds and swept settings). A members.json that is
    not as td3-jax writes it, or that disagrees with config.json (its seeds, or its sweep
    section's members), raises a one-line ConfigError: an edited file would label (or
    restore) the members wrongly."""
    path = Path(out_dir) / MEMBERS_FILE
    if not path.exists():
        return members(cfg)
    try:
        listing = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path} is not valid JSON ({err}); {_RESTORE_MEMBERS}") from err
    population = _parse_members(listing, path)
    expected = _members_in_config(out_dir, population)
    if expected is not None and population != expected:
        listed, said = (", ".join(str(m.seed) for m in g) for g in (population, expected))
        raise ConfigError(f"{path} lists the members of seeds {listed} but config.json says the "
                          f"run trained seeds {said} (or other swept values); was it edited? "
                          f"{_RESTORE_MEMBERS.capitalize()}")  # fmt: skip
    return population


#: How to go on from a damaged members.json.
_RESTORE_MEMBERS = ("restore it from a copy, or delete it: config.json's seed and seeds (and "
                    "its sweep section) say which members the run has")  # fmt: skip


def _parse_members(listing: Any, path: Path) -> list[Member]:
    """members.json's entries as members; a one-line ConfigError where it is not a non-empty
    list of ``{"seed": int, "overrides": {setting: number}}``."""
    if not isinstance(listing, list) or not listing or not all(map(_is_member, listing)):
        raise ConfigError(f"{path} is not a list of members as td3-jax writes it (each with "
                          "an integer seed and its overrides); was it edited? "
                          f"{_RESTORE_MEMBERS.capitalize()}")  # fmt: skip
    return [Member(seed=m["seed"], overrides=tuple(sorted((k, float(v))
                   for k, v in m["overrides"].items()))) for m in listing]  # fmt: skip


def _is_member(entry: Any) -> bool:
    """Whether a members.json entry is ``{"seed": int, "overrides": {setting: number}}``."""
    if not isinstance(entry, dict) or not isinstance(entry.get("overrides"), dict):
        return False
    numbers = all(isinstance(v, int | float) for v in entry["overrides"].values())
    return isinstance(entry.get("seed"), int) and not isinstance(entry["seed"], bool) and numbers


def _members_in_config(out_dir: Path, listed: list[Member]) -> list[Member] | None:
    """The members config.json describes: its sweep section's, else its ``seeds`` seeds from
    its ``seed``; None where it cannot say (no config.json, or a sweep written before config.json
    had its sweep section: ``listed`` overrides settings but no section says which)."""
    path = Path(out_dir) / CONFIG_FILE
    if not path.exists():
        return None
    raw = _read_config(out_dir)
    section = raw.get(SWEEP)
    if isinstance(section, dict) and isinstance(section.get("members"), list):
        swept = section.get("settings") or []
        return [Member(seed=m.get("seed"), overrides=tuple(sorted(
                    (k, float(m[k])) for k in swept if k in m)))
                for m in section["members"] if isinstance(m, dict)]  # fmt: skip
    if any(m.overrides for m in listed):
        return None
    saved = load_config(out_dir)
    return [Member(seed=saved.seed + k, overrides=()) for k in range(saved.seeds)]


def environment_record(env_name: str, env: Environment | None) -> dict:
    """config.json's ``environment`` entry for a run of a factory (``env_name`` is
    ``module.path:function``) or of an object (``object/<name>``): ``env``'s sizes, bounds and
    time limit (:func:`td3_jax.envs.custom.signature`), so that a later ``--resume``, ``eval``,
    ``render`` or ``export`` notices a changed factory or another object; ``{}`` for
    environments known by name."""
    return {"environment": custom.signature(env)} if custom.is_custom(env_name) else {}


def check_environment_unchanged(out_dir: Path, env_name: str, env: Environment | None) -> None:
    """Raises :class:`~td3_jax.common.errors.CustomEnvironmentError` when a factory's or object's
    run environment ``env``, made or handed now, differs from what its config.json recorded
    (nothing to check for environments known by name)."""
    if custom.is_custom(env_name) and env is not None:
        custom.check_unchanged(env_name, load_run_info(out_dir).get("environment"), env)
