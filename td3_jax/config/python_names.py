"""Errors in the words of a Python caller: the messages td3-jax writes with command-line flags
(``--total-steps 2000``), as :func:`td3_jax.train` and :func:`td3_jax.make_train` raise them
(``total_steps=2000``, ``resume=True``, ``out_dir``)."""

from __future__ import annotations

import functools
import re
import typing
from collections.abc import Callable
from typing import Any

from td3_jax.common.errors import Td3JaxError
from td3_jax.config.schema import field_types, union_arms

__all__ = ["field_names", "with_field_names"]


#: What a command-line word that is not a TrainConfig field is called in ``td3_jax.train``.
_ARGUMENT_NAMES = {"out": "out_dir", "resume": "resume", "devices": "devices",
                   "time-budget-s": "time_budget_s"}  # fmt: skip
#: A flag in a message, with the numbers after it (``--hidden-sizes 256 256``, ``--v-min -inf``).
_VALUE = r"(?:-?\d(?:[\w+-]|\.(?=\w))*|(?:-?inf|nan)(?![\w.]))"
_FLAG_IN_TEXT = re.compile(rf"(?<![\w-])--(no-)?([a-z][a-z0-9]*(?:-[a-z0-9]+)*)((?: {_VALUE})*)")
#: A command quoted in a message (``continue with: td3-jax train --out x --resume``), kept as
#: it is up to the end of its clause.
_COMMAND_IN_TEXT = re.compile(r"(td3-jax [a-z][^;)]*)")


def field_names(message: str) -> str:
    """``message`` (written with command-line flags) as a Python caller of
    :func:`td3_jax.train` or :func:`td3_jax.make_train` names things: ``--total-steps 2000`` as
    ``total_steps=2000``, ``--no-eval-in-chunk`` as ``eval_in_chunk=False``, ``--hidden-sizes
    256 256`` as ``hidden_sizes=(256, 256)``, ``--eval-in-chunk`` as ``eval_in_chunk``,
    ``--out`` as ``out_dir``, ``--resume`` as ``resume=True``, ``--sweep-tau 0.1 0.2`` as
    ``sweep={'tau': [0.1, 0.2]}``; a quoted ``td3-jax ...`` command and other words unchanged."""
    parts = _COMMAND_IN_TEXT.split(message)  # (odd parts: the commands)
    return "".join(part if i % 2 else _FLAG_IN_TEXT.sub(_field_word, part)
                   for i, part in enumerate(parts))  # fmt: skip


def _field_word(match: re.Match) -> str:
    negated, word, values = match.group(1), match.group(2), match.group(3).split()
    name = word.replace("-", "_")
    kinds = field_types()
    if name.startswith("sweep_") and name[6:] in kinds:
        listed = ", ".join(values)
        return f"sweep={{{name[6:]!r}: [{listed}]}}" if values else f"sweep[{name[6:]!r}]"
    if name not in kinds and word not in _ARGUMENT_NAMES:
        return match.group(0)
    name = _ARGUMENT_NAMES.get(word, name)
    if negated:
        return f"{name}=False"
    if not values:
        return "resume=True" if name == "resume" else name
    if any(typing.get_origin(t) is tuple for t in union_arms(kinds.get(name))):
        return f"{name}=({', '.join(values)}{',' if len(values) == 1 else ''})"
    return f"{name}={values[0]}" if len(values) == 1 else f"{name}={' '.join(values)}"


def with_field_names(function: Callable) -> Callable:
    """``function`` whose td3-jax errors name :class:`TrainConfig`'s fields and its own
    arguments instead of command-line flags (:func:`field_names`): what ``td3_jax.train`` and
    ``td3_jax.make_train`` are."""

    @functools.wraps(function)
    def named(*args: Any, **kwargs: Any) -> Any:
        try:
            return function(*args, **kwargs)
        except Td3JaxError as err:
            if err.args and isinstance(err.args[0], str):
                err.args = (field_names(err.args[0]), *err.args[1:])
            raise

    return named
