"""Errors in the words of a Python caller: the messages td3-jax writes with command-line flags
(``--total-steps 2000``), as :func:`td3_jax.train` and :func:`td3_jax.make_train` raise them
(``total_steps=2000``, ``resume=True``, ``out_dir``)."""

from __future__ import annotations

import functools
import re
import typing
from collections.abc import Callable
from typing import Any, Literal

from td3_jax.common.errors import Td3JaxError
from td3_jax.config.schema import field_types, union_arms

__all__ = ["field_names", "with_field_names"]


#: What a command-line word that is not a TrainConfig field is called in ``td3_jax.train``.
_ARGUMENT_NAMES = {"out": "out_dir", "resume": "resume", "devices": "devices",
                   "time-budget-s": "time_budget_s"}  # fmt: skip
#: A flag in a message, with the numbers after it (``--hidden-sizes 256 256``, ``--v-min -inf``).
_VALUE = r"(?:-?\d(?:[\w+-]|\.(?=\w))*|(?:-?inf|nan)(?![\w.]))"
_FLAG_IN_TEXT = re.compile(rf"(?<![\w-])--(no-)?([a-z][a-z0-9]*(?:-[a-z0-9]+)*)((?: {_VALUE})*)"
                           r"((?: [^\s,;:()'\"]+)?)")  # (and the word after it)
#: The command line's advice that a Python caller follows differently.
_PYTHON_ADVICE = {
    "leave it out to resume": "give the run's own value to resume "
    "(td3_jax.runner.rundir.load_config(out_dir) is the run's config)",
    "on --resume": "on a resume",
}
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
    for cli, python in _PYTHON_ADVICE.items():
        message = message.replace(cli, python)
    parts = _COMMAND_IN_TEXT.split(message)  # (odd parts: the commands)
    return "".join(part if i % 2 else _FLAG_IN_TEXT.sub(_field_word, part)
                   for i, part in enumerate(parts))  # fmt: skip


def _field_word(match: re.Match) -> str:
    negated, word, values, after = match.group(1, 2, 3, 4)
    name, values, kinds = word.replace("-", "_"), values.split(), field_types()
    if name.startswith("sweep_") and name[6:] in kinds:
        listed = ", ".join(values)
        swept = f"sweep={{{name[6:]!r}: [{listed}]}}" if values else f"sweep[{name[6:]!r}]"
        return swept + after
    if name not in kinds and word not in _ARGUMENT_NAMES:
        return match.group(0)
    name = _ARGUMENT_NAMES.get(word, name)
    arms = union_arms(kinds.get(name))
    if negated:
        return f"{name}=False{after}"
    text = after.strip().removesuffix(".")
    if not values and text and _takes_text(arms, text):
        return f"{name}={text!r}{after.strip()[len(text):]}"
    if not values:
        return ("resume=True" if name == "resume" else
                f"{name}=True" if bool in arms else name) + after  # fmt: skip
    if any(typing.get_origin(t) is tuple for t in arms):
        return f"{name}=({', '.join(values)}{',' if len(values) == 1 else ''}){after}"
    joined = values[0] if len(values) == 1 else " ".join(values)
    return f"{name}={joined}{after}"


def _takes_text(arms: tuple[Any, ...], text: str) -> bool:
    """Whether the word ``text`` after a flag is the value of a field of these annotated
    types: any word for a string, one of its choices for a Literal."""
    return any(a is str or (typing.get_origin(a) is Literal and text in typing.get_args(a))
               for a in arms)  # fmt: skip


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
