"""Where a train or sweep command without ``--out`` writes its run: a new folder under
``runs/``, named for its preset or environment and the moment it starts, made at once so that
two runs started together never share it (and removed again where the run wrote nothing)."""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import time
from pathlib import Path

from td3_jax.cli.argv import flag_name, flag_values, joins_others
from td3_jax.config.schema import ConfigError, TrainConfig

__all__ = ["RESUME_NEEDS_OUT", "RUNS_FOLDER", "new_run_directory", "out_chosen_note",
           "remove_if_empty", "with_run_directory"]  # fmt: skip

#: The folder that holds the runs started without ``--out``.
RUNS_FOLDER = Path("runs")
#: What a ``--resume`` without ``--out`` is told.
RESUME_NEEDS_OUT = "--resume continues the run in --out DIR: name it with --out"
#: Where a run started without ``--out`` went before each got a folder of its own.
_FORMER_DEFAULT = RUNS_FOLDER / "latest"
#: Each folder :func:`new_run_directory` made, as it was returned: its absolute path and the
#: folder of runs where that was made for it (else None), for :func:`remove_if_empty`.
_MADE: dict[Path, tuple[Path, Path | None]] = {}


def with_run_directory(args: list[str], now: float | None = None) -> tuple[list[str], Path | None]:
    """The train (or sweep) flags ``args`` with ``--out`` of a new folder where none is given,
    and that folder (:func:`new_run_directory`, made now); ``(args, None)`` where ``--out`` or
    ``--help`` is given. A ``--resume``, or a process that joins others
    (:func:`~td3_jax.cli.argv.joins_others`), without ``--out`` is a ConfigError: a
    resume continues a run it must name, and the processes of a run must name one folder."""
    names = [flag_name(arg) for arg in args]
    if {"-h", "--help", "--out"} & set(names):
        return args, None
    if "--resume" in names:
        former = (f"; {shlex.join(['--out', str(_FORMER_DEFAULT)])} for the run an earlier "
                  "td3-jax wrote without it" if (_FORMER_DEFAULT / "config.json").exists()
                  else "")  # fmt: skip
        raise ConfigError(RESUME_NEEDS_OUT + former)
    if joins_others(args):
        raise ConfigError("this process joins others of one run, which write one folder: give "
                          "each the same --out DIR")  # fmt: skip
    name = _last(args, "--preset") or _last(args, "--env") or TrainConfig.env
    try:
        out = new_run_directory(name, RUNS_FOLDER, now)
    except OSError as err:  # (a file named runs, a folder this process cannot write)
        raise ConfigError(f"cannot make a folder for the run in {RUNS_FOLDER}/ "
                          f"({err.strerror or err}): give one with --out DIR") from None
    return [*args, "--out", str(out)], out


def _last(args: list[str], flag: str) -> str | None:
    """The value of the last ``flag`` in ``args`` (the one the parser takes), or None."""
    given = [values for values in flag_values(args, flag) if values]
    return given[-1][0] if given else None


def out_chosen_note(out: Path) -> str:
    """The line saying where a run that no ``--out`` named goes (:func:`with_run_directory`)."""
    return f"no --out given: the run goes to {out}"


def new_run_directory(name: str, folder: Path, now: float | None = None) -> Path:
    """Makes and returns ``folder/NAME-YYYYmmdd-HHMMSS`` (local time ``now``, default the
    present), ``NAME`` being ``name`` (a preset, an environment) in letters, digits, ``.``,
    ``_`` and ``-``; ``-2``, ``-3``, ... after it where that folder exists (made by another
    run, even one started in the same second). ``folder`` is made where it is missing, again
    where a run refused beside this one removes it meanwhile."""
    label = re.sub(r"[^A-Za-z0-9._-]+", "-", name)[:60].strip("-.") or "run"
    stem = f"{label}-{time.strftime('%Y%m%d-%H%M%S', time.localtime(now))}"
    made = _make_folder(folder)
    path, count = folder / stem, 1
    while True:
        try:
            path.mkdir()
        except FileExistsError:
            count += 1
            path = folder / f"{stem}-{count}"
            continue
        except FileNotFoundError:  # (folder removed by a refused run started beside this one)
            remade = _make_folder(folder)
            if not remade and not folder.is_dir():
                raise  # (a link to a folder that is gone: nowhere to make it)
            made = made or remade
            continue
        _MADE[path] = (path.absolute(), folder.absolute() if made else None)
        return path


def _make_folder(folder: Path) -> bool:
    """Makes ``folder`` (and its parents); False where it was there already."""
    try:
        folder.mkdir(parents=True)
    except FileExistsError:
        return False
    return True


def remove_if_empty(path: Path | None) -> None:
    """Removes the folder ``path`` where it holds nothing (a run refused before writing), and
    the folder of runs where :func:`new_run_directory` made it for ``path`` and it is then
    empty too."""
    if path is None:
        return
    run, made = _MADE.pop(path, (path, None))
    with contextlib.suppress(OSError):
        os.rmdir(run)
        if made is not None:
            os.rmdir(made)
