"""The argument list as typed, read and rewritten around the parser: a flag's values, the
settings the flags name, whole numbers written in scientific notation, whether the process
joins others of a run, and the checks made on the raw list before any subcommand parses it
(empty paths, ``~``, repeated list flags)."""

from __future__ import annotations

import dataclasses
import decimal
import itertools
import os
import re
import types
import typing

from td3_jax.common import runtime
from td3_jax.config.schema import ConfigError, TrainConfig

__all__ = [
    "check_no_empty_path",
    "expand_home",
    "flag_name",
    "flag_value",
    "flag_values",
    "given_fields",
    "joins_others",
    "number_kinds",
    "repeated_flags_warning",
    "whole_numbers_written_out",
]

#: A number in scientific notation (``1e6``, ``2.5E+4``), as users write step counts.
_SCIENTIFIC = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d{1,4}", re.ASCII)

#: The flags whose value is a run's folder or an output file: given empty, each would mean
#: the working directory. (An empty --compile-cache means off and an empty --menagerie not
#: given, as before.)
_PATH_FLAGS = ("--out", "--run", "--json")

#: The flags that take a list of values (besides ``--sweep-*``), whose repetition might be
#: read as adding to the list.
_LIST_FLAGS = ("--hidden-sizes", "--actor-hidden-sizes", "--critic-hidden-sizes", "--run")


def flag_value(args: list[str], flag: str) -> str | None:
    """The value of the first ``flag`` in ``args`` (``--flag v`` or ``--flag=v``); None where
    it is not given (or given last, without a value)."""
    for i, arg in enumerate(args):
        if arg == flag and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1]
    return None


def flag_values(args: list[str], flag: str) -> list[list[str]]:
    """The values given to ``flag`` each time it appears in ``args`` (``--flag=v`` or
    ``--flag v ...``), in order."""
    found = []
    for i, arg in enumerate(args):
        if arg.startswith(flag + "="):
            found.append([arg.split("=", 1)[1]])
        elif arg == flag:
            found.append(list(itertools.takewhile(lambda a: not a.startswith("--"), args[i + 1 :])))
    return found


def given_fields(args: list[str]) -> set[str]:
    """The TrainConfig fields that a flag in ``args`` names (``--num-envs``, ``--no-x``, ...)."""
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    given = set()
    for arg in args:
        if not arg.startswith("--"):
            continue
        name = arg[2:].split("=", 1)[0].replace("-", "_")
        if name not in names and name.startswith("no_"):
            name = name[3:]
        if name in names:
            given.add(name)
    return given


def number_kinds(command_type: type, name: str) -> tuple[type, bool] | None:
    """``(int or float, whether several)`` for a field of ``command_type`` holding numbers (a
    number, an optional one or a tuple of them); None for other fields."""
    hint = typing.get_type_hints(command_type, include_extras=False).get(name)
    several = False
    parts = [hint]
    while parts:
        part = parts.pop()
        if part in (int, float):
            return part, several
        origin = typing.get_origin(part)
        if origin is tuple:
            several = True
        if origin in (tuple, typing.Union, types.UnionType):
            parts.extend(
                a for a in typing.get_args(part) if a is not Ellipsis and a is not type(None)
            )
    return None


def whole_numbers_written_out(command_type: type, args: list[str]) -> list[str]:
    """``args`` with each value of a whole-number flag of ``command_type`` that is written in
    scientific notation and is a whole number (``--total-steps 1e6``, ``=2.5e4``) written out
    (``1000000``); other values unchanged (``1.5e0`` stays, for the parser to refuse). Only a
    tuple flag's values are all rewritten: a second value after a one-number flag is left as
    typed, for the parser's error to quote."""
    out, kind, several = [], None, False
    for arg in args:
        if arg.startswith("--"):
            name, equals, value = arg.partition("=")
            kind, several = number_kinds(command_type, name[2:].replace("-", "_")) or (None, False)
            arg = f"{name}={_written_out(value, kind)}" if equals else arg
            kind = None if equals else kind
        else:
            arg = _written_out(arg, kind)
            kind = kind if several else None  # (one value: a second is the parser's to refuse)
        out.append(arg)
    return out


def _written_out(value: str, kind: type | None) -> str:
    """``value`` as a plain integer where ``kind`` is int and it is a whole number written
    in scientific notation, else ``value``."""
    if kind is not int or not _SCIENTIFIC.fullmatch(value):
        return value
    number = decimal.Decimal(value)
    if number.adjusted() > 30:  # (far past any count; the flag's own check refuses it)
        return value
    return str(int(number)) if number == number.to_integral_value() else value


def check_no_empty_path(args: list[str]) -> None:
    """``ConfigError`` for ``--out`` or ``--run`` given an empty or blank value (``--out ''``,
    ``--out=``: often ``--out "$DIR"`` with DIR unset), which would otherwise mean the working
    directory (or a path named by spaces)."""
    for token, after in itertools.pairwise([*args, None]):
        flag, equals, value = token.partition("=")
        given = value if equals else after
        if flag in _PATH_FLAGS and given is not None and not given.strip():
            raise ConfigError(f"{flag} is {'blank' if given else 'empty'} (an unset shell "
                              "variable?); give the path, or ./ for the working "
                              "directory")  # fmt: skip


def expand_home(args: list[str]) -> list[str]:
    """``args`` with a leading ``~`` of an ``--out`` or ``--run`` value (each of ``--run``'s
    values) expanded to the home folder, as the shell does for ``--out ~/x`` but not for
    ``--out=~/x``, a quoted ``'~/x'`` or a Python caller's list (which made a folder named
    ``~`` in the working directory, and said ``~/x``)."""
    expanded, flag = [], None  # (the path flag whose values follow)
    for token in args:
        name, equals, value = token.partition("=")
        if token.startswith("-"):
            flag = name if name in _PATH_FLAGS and not equals else None
            if equals and name in _PATH_FLAGS and value.startswith("~"):
                token = f"{name}={os.path.expanduser(value)}"
        elif flag is not None and token.startswith("~"):
            token = os.path.expanduser(token)
        expanded.append(token)
    return expanded


def repeated_flags_warning(args: list[str]) -> str | None:
    """A warning naming the list flags (``--sweep-*``, :data:`_LIST_FLAGS`) given more than
    once in ``args``: only the last list counts, so ``--sweep-actor-lr 1e-4 --sweep-actor-lr
    1e-3 3e-4`` drops 1e-4. ``None``: none. (A repeated one-value flag is an override, as
    a script's defaults followed by ``--seed 3`` give, and is not warned about.)"""
    flags = [arg.split("=", 1)[0] for arg in args if arg.startswith("--")]
    lists = [f for f in flags if f.startswith("--sweep-") or f in _LIST_FLAGS]
    repeated = [flag for flag in dict.fromkeys(lists) if lists.count(flag) > 1]
    if not repeated:
        return None
    return (f"{', '.join(repeated)} given more than once: only the last list of each counts "
            "(the lists are not added together)")  # fmt: skip


def flag_name(arg: str) -> str:
    """The flag an argument names, as the help spells it (``--local_processes=2``:
    ``--local-processes``; the parser takes either spelling)."""
    name = arg.partition("=")[0]
    return name.replace("_", "-") if name.startswith("--") else name


def joins_others(args: list[str]) -> bool:
    """Whether a train or sweep process of ``args`` joins other processes: started by
    ``--local-processes``, or given ``jax.distributed``'s coordinator or process id, or a
    process count above 1 (flags, or JAX's variables)."""
    given = {flag_name(arg): i for i, arg in enumerate(args)}
    counts = [os.environ.get("JAX_NUM_PROCESSES", "")]
    if "--num-processes" in given:
        at = given["--num-processes"]
        _, equals, value = args[at].partition("=")
        counts.append(value if equals else (args[at + 1] if at + 1 < len(args) else ""))
    return (runtime.local_processes() is not None
            or bool({"--coordinator-address", "--process-id"} & set(given))
            or bool(os.environ.get("JAX_COORDINATOR_ADDRESS"))
            or any(count.isdigit() and int(count) > 1 for count in counts))  # fmt: skip
