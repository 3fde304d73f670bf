"""tyro, as the subcommands call it: one parse of an argument list into a command dataclass,
whose errors are one :class:`~td3_jax.config.schema.ConfigError` line and whose ``--help``
text is the docstrings' paragraphs (the terminal wraps them)."""

from __future__ import annotations

import contextlib
import inspect
import io
import re
from typing import Any

import tyro

from td3_jax.cli.argv import whole_numbers_written_out
from td3_jax.cli.parse_errors import parse_error
from td3_jax.common import upstream
from td3_jax.config.schema import ConfigError

__all__ = ["help_paragraphs", "parse"]

#: A line that starts an item of a list in a docstring (``- x``, ``* x``, ``1. x``, ``2) x``).
_LIST_ITEM = re.compile(r"\s*([-*]|\d+[.)])\s")


def parse(command_type: type, args: list[str], prog: str, default: Any = None) -> Any:
    """``tyro.cli`` whose parse errors become one ``ConfigError`` line (tyro draws a box):
    ``args`` read as a ``command_type`` over ``default`` (its fields' defaults where None);
    ``--help`` prints the help and exits 0."""
    captured = io.StringIO()
    args = whole_numbers_written_out(command_type, args)
    try:
        with contextlib.redirect_stderr(captured), upstream.tyro_help_unwrapped_by(help_paragraphs):
            command = _tyro_cli(command_type, args, default, prog)
    except SystemExit as exit_:
        if exit_.code in (0, None):
            raise
        message = parse_error(captured.getvalue(), command_type, args, prog)
        raise ConfigError(message) from None
    return command


def _tyro_cli(command_type: type, args: list[str], default: Any, prog: str) -> Any:
    """``tyro.cli``, tried a second time after a ``SystemError`` (CPython 3.11's "AST
    constructor recursion depth mismatch", seen once in CI while tyro parsed this package's
    source for help text; it passed when run again)."""
    try:
        return tyro.cli(command_type, args=args, default=default, prog=prog)
    except SystemError:
        return tyro.cli(command_type, args=args, default=default, prog=prog)


def help_paragraphs(docstring: str) -> str:
    """A docstring as ``--help`` text: its lines joined into paragraphs (blank lines between
    paragraphs kept; list items each on a line of their own), so the terminal wraps them."""
    paragraphs = re.split(r"\n\s*\n", inspect.cleandoc(docstring))
    return "\n\n".join(_joined(paragraph.splitlines()) for paragraph in paragraphs).strip()


def _joined(lines: list[str]) -> str:
    """One paragraph's lines as one line, but a new line for each list item."""
    text = lines[0].strip() if lines else ""
    for line in lines[1:]:
        text += ("\n" if _LIST_ITEM.match(line) else " ") + line.strip()
    return text
