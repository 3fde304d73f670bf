"""Environments named ``SOURCE/NAME`` behind one small interface (see :mod:`.base`).

Sources: ``brax/...`` (Brax, MJX backend by default), ``playground/...`` (MuJoCo Playground's DM
Control Suite and locomotion tasks, optional extras) and ``gymnax/...`` (continuous-action gymnax
tasks). Environments of your own: an object or a factory ``module.path:function``
(:mod:`.custom`).
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import sys
from typing import Any

from td3_jax.common.errors import CustomEnvironmentError, UnknownEnvironmentError
from td3_jax.envs import brax as _brax
from td3_jax.envs import custom as _custom
from td3_jax.envs import gymnax as _gymnax
from td3_jax.envs import locomotion as _locomotion
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
from td3_jax.envs.custom import (
    FunctionalEnv,
    check_environment,
    from_object,
    is_custom,
    load_factory,
    object_label,
)
from td3_jax.envs.menagerie import MissingAssetsError, candidates, first_holding, robot
from td3_jax.envs.per_device import over_devices
from td3_jax.envs.physics import without_warp_import_notes

#: Each source module has ``names() -> list[str]`` and
#: ``make(task, *, backend, episode_length) -> Environment`` (Playground's also takes
#: ``options``).
_SOURCES = {"brax": _brax, "playground": _playground, "gymnax": _gymnax}


def closest_names(name: str, names: list[str], limit: int = 3) -> list[str]:
    """Known names a mistyped ``name`` probably meant: the same task under its source
    (``Pendulum-v1`` -> ``gymnax/Pendulum-v1``) or in another case (``brax/Ant``), then the
    closest spellings."""
    task = name.rpartition("/")[2].lower()
    same_task = [n for n in names if n.rpartition("/")[2].lower() == task]
    by_task: dict[str, list[str]] = {}
    for n in names:  # spelled like the task part alone, not like the shared "brax/" prefix
        by_task.setdefault(n.rpartition("/")[2].lower(), []).append(n)
    close = difflib.get_close_matches(task, list(by_task), n=limit, cutoff=0.75)
    found = same_task + [n for c in close for n in by_task[c]]
    return list(dict.fromkeys(found))[:limit]


def _unknown_message(name: str, source: str) -> str:
    # gymnax's own names first: a gymnax typo imports neither Brax nor Playground (MJX, 3-7 s
    # on a CPU). Brax's and Playground's names import MJX anyway, and each has tasks that the
    # other has under a close name (brax/humanoid, playground/HumanoidRun): both are searched.
    own = [f"gymnax/{n}" for n in _gymnax.names()] if source == "gymnax" else []
    guesses = closest_names(name, own) or closest_names(name, known_names())
    every = "`td3-jax envs` lists all of them"
    if source == "playground" and not _playground.names():  # (the name cannot be told here)
        return (f"environment {name!r} needs MuJoCo Playground, which is not installed: "
                "pip install 'td3-jax[playground]', or 'td3-jax[locomotion]' for its robots "
                f"(T1, G1, Go1 and the other locomotion tasks) ({every})")  # fmt: skip
    if guesses:
        return f"unknown environment {name!r}; did you mean {' or '.join(guesses)}? ({every})"
    if "/" not in name and "." in name:  # a module path without its function
        module, _, function = name.rpartition(".")
        if module in _SOURCES:  # (brax.ant: a known one's slash typed as a dot)
            return f"unknown environment {name!r}; did you mean {module}/{function}? ({every})"
        if function.isidentifier() and not _module_exists(name) and _module_exists(module):
            return (f"unknown environment {name!r}; your own environment is given as "
                    f"module.path:function: did you mean --env {module}:{function}? "
                    f"({every})")  # fmt: skip
        return (f"unknown environment {name!r}; your own environment is given as "
                f"module.path:function, a function of {name} returning it "
                f"(--env {name}:FUNCTION), and a known one as SOURCE/NAME ({every})")  # fmt: skip
    if source in _SOURCES and _SOURCES[source].names():
        return (f"unknown environment {name!r}; {source} has "
                f"{', '.join(_SOURCES[source].names())} ({every})")  # fmt: skip
    if source in _SOURCES:
        return f"unknown environment {name!r}; {every}"
    return (f"unknown environment {name!r}; names are SOURCE/NAME, SOURCE one of "
            f"{', '.join(_SOURCES)} ({every}), or module.path:function for your own")  # fmt: skip


def _module_exists(module: str) -> bool:
    """Whether ``module`` can be imported from here, the current directory included as a
    factory's import has it (found, not imported; a dotted name's parent packages are, and
    anything they raise counts as not found)."""
    import importlib.util

    path = [*sys.path, os.getcwd()] if "" not in sys.path else sys.path
    saved, sys.path[:] = list(sys.path), path
    try:
        with without_warp_import_notes():
            return importlib.util.find_spec(module) is not None
    except Exception:  # (a parent package that fails on import)
        return False
    finally:
        sys.path[:] = saved


def known_names() -> list[str]:
    """Every ``SOURCE/NAME`` this installation can make."""
    return [f"{src}/{n}" for src, module in _SOURCES.items() for n in module.names()]


def check_name(name: str) -> None:
    """Raises :class:`UnknownEnvironmentError` (naming the closest known names) when
    ``SOURCE/NAME`` is not one this installation can make; a factory (``module:function``) or
    an object's name passes (:func:`make` checks those when it makes them)."""
    if ":" in name or name.startswith(_custom.OBJECT_PREFIX):
        return
    source, _, task = name.partition("/")
    module = _SOURCES.get(source)
    if module is None or task not in module.names():
        raise UnknownEnvironmentError(_unknown_message(name, source))


def what_is_missing(name: str, menagerie: str | None = None) -> str:
    """What a known environment ``name`` still needs before it can run here ("" when
    nothing): a Playground locomotion task's robot folder (:mod:`.menagerie`)."""
    source, _, task = name.partition("/")
    if source != "playground" or task not in _locomotion.names():
        return ""
    folder, package = robot(task)
    if first_holding(folder, candidates(menagerie)) is not None:
        return ""
    return f"robot '{folder}': pip install {package} (or 'td3-jax[locomotion]'), or --menagerie DIR"


def extra(name: str) -> str:
    """The ``td3-jax[...]`` extra the known environment ``name`` needs (``""``: none, its
    package is one of td3-jax's own dependencies)."""
    source, _, task = name.partition("/")
    if source != "playground":
        return ""
    return "locomotion" if task in _locomotion.names() else "playground"


def catalog(menagerie: str | None = None) -> list[tuple[str, str, str]]:
    """``[(name, extra, what it still needs here)]`` for every environment this installation
    knows (:func:`extra`; ``""``: it runs here as it is), plus one row ``("playground/*",
    "playground", install line)`` when MuJoCo Playground is not installed."""
    rows = [(name, extra(name), what_is_missing(name, menagerie)) for name in known_names()]
    if not _playground.names():
        rows.append(("playground/*", "playground",
                     "MuJoCo Playground: pip install 'td3-jax[playground]'"))  # fmt: skip
    return rows


def make(
    name: Any,
    *,
    backend: str = "mjx",
    episode_length: int | None = None,
    options: EnvOptions | None = None,
) -> Environment:
    """Makes the environment ``SOURCE/NAME``, the one a factory ``module.path:function`` makes,
    or adapts an environment object (:func:`from_object`).

    Args:
      name: e.g. ``brax/ant``, ``playground/CheetahRun``, ``playground/T1JoystickFlatTerrain``,
        ``gymnax/Pendulum-v1``; ``my_pkg.envs:make_arm``; or an object of
        :data:`td3_jax.envs.custom.KINDS` (checked: :func:`check_environment`).
      backend: Brax physics backend (``mjx``, ``generalized``, ``positional``, ``spring``);
        ``warp`` for a Playground task means ``options.impl="warp"``. Ignored by gymnax.
      episode_length: time limit; default: the source's (1000 for Brax and Playground).
      options: the locomotion tasks' options (:class:`EnvOptions`: Menagerie root, domain
        randomisation, pushes, observation keys); other sources refuse non-default
        randomisation or pushes with :class:`EnvironmentOptionError`.

    Raises :class:`MissingAssetsError` when a locomotion task's robot folder is nowhere,
    :class:`CustomEnvironmentError` for an object or factory td3-jax cannot use.
    """
    if not isinstance(name, str):
        return from_object(name, episode_length=episode_length, options=options)
    if name.startswith(_custom.OBJECT_PREFIX):
        raise _custom.object_run_error(name)
    if ":" in name:
        return _custom.from_factory(name, episode_length=episode_length, options=options)
    check_name(name)
    source, _, task = name.partition("/")
    module = _SOURCES[source]
    options = options or EnvOptions()
    if source == "playground":
        if backend == "warp":  # Playground's physics is options.impl
            options = dataclasses.replace(options, impl="warp")
        return module.make(task, backend=backend, episode_length=episode_length, options=options)
    refuse_locomotion_options(name, options)
    return module.make(task, backend=backend, episode_length=episode_length)


__all__ = [
    "CustomEnvironmentError",
    "EnvOptions",
    "EnvState",
    "Environment",
    "EnvironmentOptionError",
    "FunctionalEnv",
    "MissingAssetsError",
    "StepResult",
    "UnknownEnvironmentError",
    "actor_observation",
    "catalog",
    "check_environment",
    "check_name",
    "critic_observation",
    "extra",
    "from_object",
    "is_custom",
    "known_names",
    "load_factory",
    "make",
    "object_label",
    "over_devices",
    "reset",
    "reset_ended",
    "step",
    "what_is_missing",
]
