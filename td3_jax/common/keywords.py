"""Config classes that name the field meant by a keyword they do not have: ``TrainConfig(
gamma=0.9)`` says ``did you mean discount?`` (:func:`~td3_jax.common.other_names.names_meant`)
where Python says only that the keyword is unexpected."""

from __future__ import annotations

import dataclasses
import functools
import inspect
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

from td3_jax.common.other_names import names_meant

__all__ = ["fields_meant", "keywords_named", "parameters_named", "unknown_keyword"]

Cls = TypeVar("Cls", bound=type)
Fn = TypeVar("Fn", bound=Callable[..., Any])


def keywords_named(cls: Cls) -> Cls:
    """``cls`` (a dataclass) whose ``__init__`` refuses a keyword that is none of its fields
    with a ``TypeError`` naming the field most likely meant (:func:`unknown_keyword`); the
    signature stays the fields'."""
    init = cls.__init__

    @functools.wraps(init)
    def checked(self: Any, *args: Any, **kwargs: Any) -> None:
        fields = {field.name for field in dataclasses.fields(self)}
        unknown = next((name for name in kwargs if name not in fields), None)
        if unknown is not None:
            raise TypeError(unknown_keyword(type(self).__name__, unknown, fields))
        init(self, *args, **kwargs)

    cls.__init__ = checked
    return cls


def parameters_named(function: Fn) -> Fn:
    """``function`` (of named parameters, no ``**kwargs``) refusing a keyword that names none
    of them with a ``TypeError`` naming the parameter most likely meant
    (:func:`unknown_keyword`: ``train(..., resum=True)``, did you mean resume?), before it
    runs; its signature and docstring stay its own."""
    names = set(inspect.signature(function).parameters)

    @functools.wraps(function)
    def checked(*args: Any, **kwargs: Any) -> Any:
        unknown = next((name for name in kwargs if name not in names), None)
        if unknown is not None:
            raise TypeError(unknown_keyword(function.__name__, unknown, names))
        return function(*args, **kwargs)

    return checked  # type: ignore[return-value]


def unknown_keyword(owner: str, name: str, fields: Iterable[str]) -> str:
    """``owner() got an unexpected keyword argument 'gamma'; did you mean discount?`` (the
    guess only where one of ``fields`` is close)."""
    meant = fields_meant(name, fields)
    guess = f"; did you mean {' or '.join(meant[:4])}?" if meant else ""
    return f"{owner}() got an unexpected keyword argument {name!r}{guess}"


def fields_meant(name: str, fields: Iterable[str]) -> list[str]:
    """The ``fields`` (Python names) that ``name`` most likely means, best first
    (:func:`~td3_jax.common.other_names.names_meant` on their dashed spellings)."""
    dashed = {field.replace("_", "-"): field for field in fields}
    return [dashed[n] for n in names_meant(name.replace("_", "-"), dashed)]
