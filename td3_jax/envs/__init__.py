"""Environments named ``SOURCE/NAME`` behind one small interface (see :mod:`.base`).

Sources: ``brax/...`` (Brax, MJX backend by default), ``playground/...`` (MuJoCo Playground's DM
Control Suite, optional extra) and ``gymnax/...`` (continuous-action gymnax tasks).
"""

from __future__ import annotations

from td3_jax.envs import brax as _brax
from td3_jax.envs import gymnax as _gymnax
from td3_jax.envs import playground as _playground
from td3_jax.envs.base import Environment, EnvState, StepResult, reset, reset_ended, step

#: Each source module has ``names() -> list[str]`` and
#: ``make(task, *, backend, episode_length) -> Environment``.
_SOURCES = {"brax": _brax, "playground": _playground, "gymnax": _gymnax}


class UnknownEnvironmentError(ValueError):
    """An environment name that no source knows; the message lists the known names."""


def known_names() -> list[str]:
    """Every ``SOURCE/NAME`` this installation can make."""
    return [f"{src}/{n}" for src, module in _SOURCES.items() for n in module.names()]


def make(name: str, *, backend: str = "mjx", episode_length: int | None = None) -> Environment:
    """Makes the environment ``SOURCE/NAME``.

    Args:
      name: e.g. ``brax/ant``, ``playground/CheetahRun``, ``gymnax/Pendulum-v1``.
      backend: Brax physics backend (``mjx``, ``generalized``, ``positional``, ``spring``), or
        Playground's ``impl`` (``jax`` or ``warp``). Ignored by gymnax.
      episode_length: time limit; default: the source's (1000 for Brax and Playground).
    """
    source, _, task = name.partition("/")
    module = _SOURCES.get(source)
    if module is None or task not in module.names():
        listing = ", ".join(known_names())
        hint = ""
        if source == "playground" and not _playground.names():
            hint = " (playground tasks need: pip install 'td3-jax[playground]')"
        raise UnknownEnvironmentError(f"unknown environment {name!r}{hint}; known: {listing}")
    return module.make(task, backend=backend, episode_length=episode_length)


__all__ = [
    "EnvState",
    "Environment",
    "StepResult",
    "UnknownEnvironmentError",
    "known_names",
    "make",
    "reset",
    "reset_ended",
    "step",
]
