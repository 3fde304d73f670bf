"""tyro's parse errors (a box of several lines) reworded as one line: an unknown flag with
the one most likely meant, a value that is not a number or not a choice, a flag without its
value, the required flags missing."""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import re
import shlex

from td3_jax.cli.argv import flag_values, number_kinds
from td3_jax.common.other_names import names_meant
from td3_jax.config.schema import SWEEPABLE, flag

__all__ = ["parse_error"]

def parse_error(text: str, command_type: type, args: list[str], prog: str) -> str:
    """tyro's error box (``text``, its stderr) as one line: the options not known (with the
    closest known one), a value that is not a number or not a choice, a flag without its
    value, the required ones missing, else the box's first part (what went wrong, without
    help text)."""
    title, sections = _tyro_box(text)
    first = " ".join(line.strip() for line in sections[0])
    if title == "Unrecognized options":
        return _unrecognized(command_type, args, prog, sections[0])
    said = None
    if title == "Value error":
        said = _value_error(command_type, args, first)
    elif title == "Invalid choice":
        said = _invalid_choice(first)
    elif title == "Missing argument" and (named := re.search(r"argument '(--[\w-]+)'", first)):
        said = f"{named.group(1)} needs a value (see {prog} --help)"
    elif title == "Required options":  # "Missing from PROG:", each flag 4 deeper, its help 8
        flag = " " * (len(sections[0][0]) - len(sections[0][0].lstrip()) + 4) + "-"
        missing = [line.split()[0] for line in sections[0] if line.startswith(flag)]
        meant = _word_meant(args, missing, several=prog.endswith(" plot"))
        said = missing and f"{prog} needs {', '.join(missing)} ({meant}see {prog} --help)"
    return said or first or title or f"could not parse {' '.join(args)} (see {prog} --help)"


def _word_meant(args: list[str], missing: list[str], several: bool) -> str:
    """Where ``--run`` is missing and the command began with words of their own, as other
    tools take a run (``td3-jax eval runs/x``): ``"as a flag: --run runs/x; "`` (every such
    word where the command takes ``several`` runs, else the first), else nothing."""
    words = list(itertools.takewhile(lambda arg: not arg.startswith("-"), args))
    if "--run" not in missing or not words:
        return ""
    return f"as a flag: {shlex.join(['--run', *(words if several else words[:1])])}; "


def _tyro_box(text: str) -> tuple[str, list[list[str]]]:
    """``(title, sections)`` of tyro's error box (drawn with box characters, or in ASCII where
    the output cannot take them): the title line, then the parts between its rules, each part
    its lines with their indentation (an empty list where there is none)."""
    lines = [line.rstrip().removesuffix("│").rstrip() for line in text.splitlines()]
    lines = [line.replace("│ ", "", 1) if line.startswith("│") else line for line in lines]
    lines = [line for line in lines if line.strip() and not line.startswith("usage:")]
    if not lines:
        return "", [[]]
    sections: list[list[str]] = [[]]
    for line in lines[1:]:
        if len(line.strip()) > 2 and set(line.strip()) <= set("─-╰╯"):
            sections.append([])
        else:
            sections[-1].append(line)
    return lines[0].strip("╭─╮ "), [part for part in sections if part] or [[]]


def _value_error(command_type: type, args: list[str], text: str) -> str | None:
    """``--actor-lr takes a number, got 'abc'``: tyro's "Error parsing FLAG" for a flag of
    numbers, in one line (None for other flags or errors)."""
    match = re.match(r"Error parsing (--[\w-]+):", text)
    kinds = match and number_kinds(command_type, match.group(1)[2:].replace("-", "_"))
    if not kinds:
        return None
    flag, (kind, several) = match.group(1), kinds
    given = _first_unparsed(flag_values(args, flag), kind)
    what = "whole number" if kind is int else "number"
    said = f"{flag} takes {what}s" if several else f"{flag} takes a {what}"
    bad = [value for value in given if not _reads_as(kind, value)]
    if several and 0 < len(bad) < len(given):  # (name the values it could not read)
        return f"{said}, got {' '.join(map(repr, bad))} (of {' '.join(given)})"
    return f"{said}, got {' '.join(map(repr, given)) or 'nothing'}"


def _reads_as(kind: type, value: str) -> bool:
    """Whether ``kind`` (int or float) reads ``value`` (``None``: tyro's "leave it out")."""
    if value == "None":
        return True
    try:
        kind(value)
    except ValueError:
        return False
    return True


def _first_unparsed(occurrences: list[list[str]], kind: type) -> list[str]:
    """The values of the first occurrence that ``kind`` cannot read (the one the parser
    refused: ``--num-envs 4 --num-envs x`` refuses ``x``), else the last one."""
    for values in occurrences:
        if not all(_reads_as(kind, value) for value in values):
            return values
    return occurrences[-1] if occurrences else []


def _invalid_choice(text: str) -> str | None:
    """``--impl 'cuda' is not one of jax, warp``: tyro's "invalid choice" in one line, with the
    closest choice, and without the ``None`` that tyro lists for a flag whose default is to
    leave it out (None for other errors)."""
    pattern = r"invalid choice '(.*)' for argument '(--[\w-]+)'\. Expected one of \((.*)\)\."
    match = re.match(pattern, text)
    if not match:
        return None
    given, flag, listed = match.groups()
    choices = sorted({c.strip(" '") for c in listed.split(",")} - {"None"})  # (tyro's: a set)
    close = difflib.get_close_matches(given.lower(), choices, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"{flag} {given!r} is not one of {', '.join(choices)}{hint}"


def _unrecognized(command_type: type, args: list[str], prog: str, listed: list[str]) -> str:
    """``unrecognized option --totl-steps (did you mean --total-steps?)``, for each option in
    ``args`` that ``command_type`` does not have: the flags that end with it (``--lr``:
    ``--actor-lr or --critic-lr``), else the closest spelling; else tyro's list of leftover
    arguments."""
    known = _known_flags(command_type)
    unknown = [name for name in (arg.split("=", 1)[0] for arg in args)
               if name.startswith("-") and name not in known and not _is_number(name)]  # fmt: skip
    if not unknown:
        leftover = " ".join(listed).split(":", 1)[-1].strip() or " ".join(args)
        return f"unexpected argument {leftover} (see {prog} --help)"
    misplaced = _misplaced_sweep(unknown, known, args, prog)
    if misplaced:
        return misplaced
    names = {name.lstrip("-"): name for name in known}
    said = [_with_guess(name, names) for name in dict.fromkeys(unknown)]
    hint = "" if len(said) == sum("did you mean" in s for s in said) else f" (see {prog} --help)"
    return f"unrecognized option{'s' if len(said) > 1 else ''} {', '.join(said)}{hint}"


def _known_flags(command_type: type) -> set[str]:
    """The flags of ``command_type`` (``--no-x`` too for a switch), and ``--help``, ``-h``."""
    known = {"--help", "-h"}
    for field in dataclasses.fields(command_type):
        known.add(f"--{field.name.replace('_', '-')}")
        if field.type in (bool, "bool"):
            known.add(f"--no-{field.name.replace('_', '-')}")
    return known


def _misplaced_sweep(unknown: list[str], known: set[str], args: list[str],
                     prog: str) -> str | None:  # fmt: skip
    """The message for a ``--sweep-*`` list given to ``td3-jax train`` (a flag of sweep), or
    one given to ``td3-jax sweep`` for a setting that cannot be swept; None otherwise."""
    sweeps = [name for name in unknown if name.startswith("--sweep-")]
    if sweeps and prog == "td3-jax train":  # a sweep's lists are `td3-jax sweep`'s flags
        return (f"{sweeps[0]}: the --sweep-* lists are flags of td3-jax sweep, which trains "
                f"every combination of their values: td3-jax sweep {' '.join(args)}")  # fmt: skip
    settings = {name: "--" + name.removeprefix("--sweep-") for name in sweeps}
    not_swept = [name for name in sweeps if settings[name] in known]  # (a setting, not a typo)
    if not_swept and prog == "td3-jax sweep":
        return (f"{not_swept[0]}: {settings[not_swept[0]]} cannot be swept (it changes the "
                "program, not a value in it); run td3-jax train once per value. A sweep "
                f"varies {', '.join(flag(s)[2:] for s in SWEEPABLE)}")  # fmt: skip
    return None


def _with_guess(name: str, names: dict[str, str]) -> str:
    """``name`` with the flags it most likely means (``--totl-steps (did you mean
    --total-steps?)``), at most four named; ``name`` alone where none is close."""
    close = names_meant(name.lstrip("-"), names)
    guesses = " or ".join(names[c] for c in close[:4]) + (" or ..." if len(close) > 4 else "")
    return f"{name} (did you mean {guesses}?)" if close else name


def _is_number(text: str) -> bool:
    """Whether ``text`` reads as a float (``-1``: a value, not a flag)."""
    try:
        float(text)
    except ValueError:
        return False
    return True
