"""Environments named ``SOURCE/NAME`` behind one small interface (see :mod:`.base`).

Sources: ``brax/...`` (Brax, MJX backend by default), ``playground/...`` (MuJoCo Playground's DM
Control Suite and locomotion tasks, optional extras) and ``gymnax/...`` (continuous-action gymnax
tasks).
"""

from __future__ import annotations

from td3_jax.envs import brax as _brax
from td3_jax.envs import gymnax as _gymnax
from td3_jax.envs import playground as _playground
from td3_jax.envs.base import (
    Environment,
    EnvironmentOptionError,
    EnvOptions,
    EnvState,
    StepResult,
    actor_observation,
    critic_observation,
    refuse_locomotion_options,
    reset,
    reset_ended,
    step,
)
from td3_jax.envs.menagerie import MissingAssetsError

#: Each source module has ``names() -> list[str]`` and
#: ``make(task, *, backend, episode_length) -> Environment`` (Playground's also takes
#: ``options``).
_SOURCES = {"brax": _brax, "playground": _playground, "gymnax": _gymnax}


class UnknownEnvironmentError(ValueError):
    """An environment name that no source knows; the message lists the known names."""


def known_names() -> list[str]:
    """Every ``SOURCE/NAME`` this installation can make."""
    return [f"{src}/{n}" for src, module in _SOURCES.items() for n in module.names()]


def make(
    name: str,
    *,
    backend: str = "mjx",
    episode_length: int | None = None,
    options: EnvOptions | None = None,
) -> Environment:
    """Makes the environment ``SOURCE/NAME``.

    Args:
      name: e.g. ``brax/ant``, ``playground/CheetahRun``, ``playground/T1JoystickFlatTerrain``,
        ``gymnax/Pendulum-v1``.
      backend: Brax physics backend (``mjx``, ``generalized``, ``positional``, ``spring``), or
        Playground's ``impl`` (``jax`` or ``warp``). Ignored by gymnax.
      episode_length: time limit; default: the source's (1000 for Brax and Playground).
      options: the locomotion tasks' options (:class:`EnvOptions`: Menagerie root, domain
        randomisation, pushes, observation keys); other sources refuse non-default
        randomisation or pushes with :class:`EnvironmentOptionError`.

    Raises :class:`MissingAssetsError` when a locomotion task's robot folder is nowhere.
    """
    source, _, task = name.partition("/")
    module = _SOURCES.get(source)
    if module is None or task not in module.names():
        listing = ", ".join(known_names())
        hint = ""
        if source == "playground" and not _playground.names():
            hint = " (playground tasks need: pip install 'td3-jax[playground]')"
        raise UnknownEnvironmentError(f"unknown environment {name!r}{hint}; known: {listing}")
    options = options or EnvOptions()
    if source == "playground":
        return module.make(task, backend=backend, episode_length=episode_length, options=options)
    refuse_locomotion_options(name, options)
    return module.make(task, backend=backend, episode_length=episode_length)


__all__ = [
    "EnvOptions",
    "EnvState",
    "Environment",
    "EnvironmentOptionError",
    "MissingAssetsError",
    "StepResult",
    "UnknownEnvironmentError",
    "actor_observation",
    "critic_observation",
    "known_names",
    "make",
    "reset",
    "reset_ended",
    "step",
]
