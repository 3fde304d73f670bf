"""Environments of your own: an object td3-jax does not know by name, or a factory
``module.path:function`` that makes one.

What td3-jax needs from an environment (docs/guides/own-environment.md says it at length):

* a ``reset`` of a key and a ``step`` of a state and an action that JAX can trace (they are
  jitted and vmapped inside the training program): ``jax.numpy``/``jax.lax``, no Python
  branches on values, no NumPy on traced arrays; a state of arrays whose shapes and dtypes
  ``step`` keeps;
* an observation of a fixed size (a vector; or, from a Playground ``MjxEnv``, a dict with one
  key for the actor and one for the critics), a scalar reward and a scalar termination flag;
* actions of a fixed size with finite bounds (the actor acts in ``[-1, 1]``, rescaled to them);
* a termination flag for true terminations only, and no auto-reset: td3-jax applies the time
  limit (``episode_length``, a truncation: the target bootstraps) and resets ended episodes
  itself, keeping the true last observation.

Four forms are taken (:func:`from_object`): a Playground ``MjxEnv``, a Brax ``Env``, a gymnax
environment (or ``(env, params)``) and a :class:`FunctionalEnv` (a pair of pure functions with
sizes and bounds), each made into an :class:`~td3_jax.envs.base.Environment` by the adapter of
its source. From the command line a factory (:func:`load_factory`): ``--env
my_pkg.envs:make_arm``, imported from the current directory or the Python path and called with
no arguments; config.json records it, so ``--resume``, ``eval``, ``render`` and ``export`` make
it again. Every environment handed over is checked (:func:`check_environment`): reset and one
step are traced abstractly (nothing runs) and a missing or wrong part is one line
(:class:`~td3_jax.common.errors.CustomEnvironmentError`, exit code 2).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import pkgutil
import re
import sys
import sysconfig
import traceback
import types
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from td3_jax.common.errors import CustomEnvironmentError, Td3JaxError, did_you_mean
from td3_jax.envs import brax as _brax
from td3_jax.envs import gymnax as _gymnax
from td3_jax.envs import playground as _playground
from td3_jax.envs.base import Environment, EnvOptions, action_bound, refuse_locomotion_options
from td3_jax.envs.physics import without_warp_import_notes

#: The name an environment handed over as an object gets (``object/<its name>``); a run made
#: from one records it in config.json, where it stands for an object no file can hold.
OBJECT_PREFIX = "object/"
#: What :func:`from_object` takes, as its messages say it.
KINDS = ("a Playground MjxEnv, a Brax Env, a gymnax environment (or (env, params)) or a "
         "td3_jax.envs.FunctionalEnv")  # fmt: skip
#: Brax's and Playground's wrappers that bring their own time limit, auto-reset or batch
#: axis (td3-jax adds its own time limit and resets; it vmaps the environment itself).
REFUSED_WRAPPERS = ("EpisodeWrapper", "AutoResetWrapper", "BraxAutoResetWrapper", "VmapWrapper",
                    "DomainRandomizationVmapWrapper", "BraxDomainRandomizationVmapWrapper",
                    "EvalWrapper")  # fmt: skip
#: ``(module, class)`` of each source's environment base class, looked up in ``sys.modules``
#: only (an instance of one means its module is imported).
_BASES = {
    "playground": ("mujoco_playground", "MjxEnv"),
    "brax": ("brax.envs.base", "Env"),
    "gymnax": ("gymnax.environments.environment", "Environment"),
}
_NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")
_NOT_JITTABLE = (
    jax.errors.ConcretizationTypeError,
    jax.errors.TracerArrayConversionError,
    jax.errors.TracerBoolConversionError,
    jax.errors.TracerIntegerConversionError,
)


@dataclasses.dataclass(frozen=True, eq=False)
class FunctionalEnv:
    """One environment as a pair of pure functions, with its sizes and action bounds.

    Attributes:
      reset: ``reset(key) -> (state, obs[observation_size])``; ``state`` any pytree of arrays.
      step: ``step(state, action[action_size]) -> (state, obs[observation_size], reward [],
        terminated [])``; ``action`` in ``[action_low, action_high]``; ``terminated`` is a
        true termination (a fall), never the time limit; no auto-reset.
      observation_size, action_size: the vectors' lengths.
      action_low, action_high: the action bounds, one number or ``action_size`` numbers,
        finite (the actor's ``[-1, 1]`` is mapped onto them).
      episode_length: the time limit in steps (a truncation; ``--episode-length`` overrides).
      name: shown in messages and records (``object/<name>``).
      mj_model: a ``mujoco.MjModel`` to draw (``td3-jax render``), or ``None``.
      qpos: ``qpos(state) -> [nq]``, the positions a frame of ``mj_model`` is drawn from.
    """

    reset: Callable[[jax.Array], tuple[Any, jax.Array]]
    step: Callable[[Any, jax.Array], tuple[Any, jax.Array, jax.Array, jax.Array]]
    observation_size: int
    action_size: int
    action_low: float | Sequence[float] = -1.0
    action_high: float | Sequence[float] = 1.0
    episode_length: int = 1000
    name: str = "FunctionalEnv"
    mj_model: Any = dataclasses.field(default=None, repr=False)
    qpos: Callable[[Any], jax.Array] | None = dataclasses.field(default=None, repr=False)


def is_custom(name: str) -> bool:
    """Whether the environment name ``name`` is a factory (``module:function``) or stands for
    an object (:data:`OBJECT_PREFIX`)."""
    return ":" in name or name.startswith(OBJECT_PREFIX)


def object_label(env: Environment) -> str:
    """What config.json records for a run handed the environment object ``env``."""
    return env.name if env.name.startswith(OBJECT_PREFIX) else OBJECT_PREFIX + env.name


def object_run_error(name: str) -> CustomEnvironmentError:
    """The error for making ``object/...`` again: a run handed an object records only that."""
    return CustomEnvironmentError(
        f"{name} was handed to td3-jax as a Python object, which config.json cannot record: pass "
        "the object again (env=obj to td3_jax.train with resume=True, "
        "td3_jax.runner.finished.evaluate_run, td3_jax.tools.export.export_run or "
        "td3_jax.tools.render.render_run), "
        "or train with a factory (module.path:function as the environment's name), so that "
        "td3-jax train --resume, eval, render and export find it"
    )


def signature(env: Environment) -> dict[str, Any]:
    """What a run's policy and checkpoints depend on in ``env``, as JSON values: observation
    and action sizes, action bounds, time limit (config.json records it for a factory run)."""
    critic = env.critic_observation_size
    return {
        "observation_size": int(env.observation_size),
        "critic_observation_size": None if critic is None else int(critic),
        "action_size": int(env.action_size),
        "action_low": np.asarray(env.action_low, np.float64).tolist(),
        "action_high": np.asarray(env.action_high, np.float64).tolist(),
        "episode_length": int(env.episode_length),
    }


def check_unchanged(name: str, recorded: dict[str, Any] | None, env: Environment) -> None:
    """A :class:`CustomEnvironmentError` naming what differs when the environment ``name``
    makes now is not the one a run recorded (:func:`signature`; nothing recorded: no check)."""
    if not recorded:
        return
    now = signature(env)
    differ = [f"{key} {recorded.get(key)} then, {now[key]} now" for key in now
              if key in recorded and recorded[key] != now[key]]  # fmt: skip
    if not differ:
        return
    if name.startswith(OBJECT_PREFIX):
        raise CustomEnvironmentError(
            f"the {name} handed over now is another environment than the one this run trained "
            f"on ({'; '.join(differ)}): hand over that one, or start a new run"
        )
    raise CustomEnvironmentError(
        f"{name} makes another environment than the one this run trained on "
        f"({'; '.join(differ)}): did the factory change? Restore it, or start a new run"
    )


# ---------------------------------------------------------------------------------------------
# module.path:function
# ---------------------------------------------------------------------------------------------


def load_factory(spec: str) -> Any:
    """What the factory ``spec`` (``module.path:function``) returns, called with no arguments;
    the module is imported from the current directory or the Python path. Every failure is
    one line (:class:`CustomEnvironmentError`): the spelling, a module not found (which), an
    attribute missing, a factory that is not callable or raises."""
    module_name, _, attribute = spec.partition(":")
    if not (_NAME.fullmatch(module_name) and _NAME.fullmatch(attribute)):
        raise CustomEnvironmentError(
            f"--env {spec!r} is neither a factory, written module.path:function (e.g. "
            "my_pkg.envs:make_arm), nor a known SOURCE/NAME (td3-jax envs lists them)"
        )
    factory = _attribute(_import(module_name, spec), attribute, spec)
    if not callable(factory):
        raise CustomEnvironmentError(f"{spec} is not callable ({type(factory).__name__}): "
                                     "td3-jax calls it with no arguments")  # fmt: skip
    try:
        with without_warp_import_notes():  # (a factory importing Brax or MJX in its body)
            return factory()
    except Exception as err:
        raise CustomEnvironmentError(f"{spec}: calling it raised {_one_line(err)}") from err


def _import(module_name: str, spec: str) -> Any:
    """The module ``module_name``, the current directory on the path as ``python -m`` has it."""
    if "" not in sys.path and os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        with without_warp_import_notes():  # (a module importing MJX first: its notes dropped)
            return importlib.import_module(module_name)
    except Exception as err:  # not found; a SyntaxError or an error of the module's own code
        name = getattr(err, "name", None) if isinstance(err, ModuleNotFoundError) else None
        if module_name.endswith(".py"):  # (a file name: myenvs.py:make)
            module = module_name.removesuffix(".py").replace(os.sep, ".").strip(".")
            function = spec.rpartition(":")[2]
            raise CustomEnvironmentError(f"{spec}: give the module's name, not its file: --env "
                                         f"{module}:{function}") from err  # fmt: skip
        if name and (module_name + ".").startswith(name + "."):
            raise CustomEnvironmentError(
                f"{spec}: no module {name!r} in {os.getcwd()} or on the Python path (run from "
                "the folder holding it, set PYTHONPATH or install its package; a run made from "
                "it needs it importable again for --resume, eval, render and export)"
                f"{did_you_mean(name, _sibling_modules(name))}"
            ) from err
        raise CustomEnvironmentError(f"{spec}: importing {module_name} raised "
                                     f"{_one_line(err)}") from err  # fmt: skip


def _attribute(module: Any, path: str, spec: str) -> Any:
    """``module.<path>`` (a dotted path), or one line naming what is missing: the closest of
    its public callables, else those callables."""
    value = module
    parts = path.split(".")
    for depth, part in enumerate(parts):
        if not hasattr(value, part):
            where = module.__name__ + (f":{'.'.join(parts[:depth])}" if depth else "")
            callables = _public_callables(value)
            hint = did_you_mean(part, callables)
            if not hint:
                callables = _defined_here(value, callables)
                listed = ", ".join(callables[:10]) + (", ..." if len(callables) > 10 else "")
                hint = f"; its public callables: {listed}" if callables else ""
            raise CustomEnvironmentError(f"{spec}: {where} has no {part!r}{hint}")
        value = getattr(value, part)
    return value


def _public_callables(value: Any) -> list[str]:
    """The callables a factory could be among ``value``'s public names (its ``__all__`` where
    it has one, else its names not starting with ``_``), sorted."""
    names = getattr(value, "__all__", None)
    if not isinstance(names, list | tuple):
        names = [name for name in dir(value) if not name.startswith("_")]
    return sorted(name for name in names if _names_a_callable(value, name))


def _defined_here(value: Any, callables: list[str]) -> list[str]:
    """Of ``callables`` (names in ``value``), those a module without ``__all__`` defines itself
    or in its own submodules (not what it imported from elsewhere), where there are any; else
    all of them."""
    if not isinstance(value, types.ModuleType) or hasattr(value, "__all__"):
        return callables
    def own(callable_name: str) -> bool:
        home = getattr(getattr(value, callable_name), "__module__", None) or ""
        return home == value.__name__ or home.startswith(value.__name__ + ".")

    return [c for c in callables if own(c)] or callables


def _names_a_callable(value: Any, name: str) -> bool:
    """Whether ``value.name`` is callable; ``False`` where looking it up fails or warns (a
    module's ``__getattr__`` may import, warn of a deprecated name or raise anything)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return callable(getattr(value, name))
        except Exception:  # a suggestion must never turn into a traceback
            return False


def _sibling_modules(name: str) -> list[str]:
    """The modules beside the missing module ``name``, by their full names: in its parent
    package, imported (for ``pkg.modul``), else in :func:`_own_folders` (for ``modul``)."""
    parent, _, _ = name.rpartition(".")
    if not parent:
        return [found.name for found in pkgutil.iter_modules(_own_folders())]
    where = getattr(sys.modules.get(parent), "__path__", None) or []
    return [f"{parent}.{found.name}" for found in pkgutil.iter_modules(list(where))]


def _installation() -> list[Path]:
    """Python's installation and environment (its prefixes), where other libraries live."""
    return [Path(root) for root in {sys.prefix, sys.base_prefix, sys.exec_prefix}]


def _own_folders() -> list[str]:
    """Where a user's own modules are imported from: the current directory, ``PYTHONPATH``'s
    folders (wherever they are: a container's ``/usr/src/app`` lies under a system Python's
    prefix) and the Python path's other folders outside Python's installation and environment."""
    installed = _installation()
    given = os.environ.get("PYTHONPATH", "").split(os.pathsep)
    added = [entry for entry in sys.path if entry and Path(entry).is_dir()
             and not any(Path(entry).is_relative_to(root) for root in installed)]  # fmt: skip
    folders = [os.getcwd(), *(entry for entry in given if entry and Path(entry).is_dir()), *added]
    return list(dict.fromkeys(folders))


def from_factory(
    spec: str, *, episode_length: int | None = None, options: EnvOptions | None = None
) -> Environment:
    """The environment the factory ``spec`` makes (:func:`load_factory`, then
    :func:`from_object`), named ``spec``."""
    made = load_factory(spec)
    return from_object(made, name=spec, episode_length=episode_length, options=options)


# ---------------------------------------------------------------------------------------------
# objects
# ---------------------------------------------------------------------------------------------


def from_object(
    obj: Any,
    *,
    name: str | None = None,
    episode_length: int | None = None,
    options: EnvOptions | None = None,
) -> Environment:
    """``obj`` (one of :data:`KINDS`, or an :class:`Environment`) as a checked
    :class:`Environment` named ``name`` (default ``object/<its name>``).

    ``episode_length``: the time limit (default the object's own: a FunctionalEnv's, gymnax's
    ``max_steps_in_episode``, a Playground config's ``episode_length``, else 1000).
    ``options``: a Playground dict observation's keys (``actor_obs_key``,
    ``critic_obs_key``); the locomotion tasks' randomisation and pushes are refused.
    """
    kind = _kind(obj)
    label = name or _label(obj)
    if kind is None:
        wrapped = " (a wrapper? hand over what it wraps)" if hasattr(obj, "_env") else ""
        if isinstance(obj, type):
            wrapped = f" ({obj.__qualname__} is a class: return an instance of it)"
        raise CustomEnvironmentError(f"{label}: a {type(obj).__module__}.{type(obj).__qualname__}"
                                     f"{wrapped} is not an environment td3-jax can use; give "
                                     f"{KINDS}")  # fmt: skip
    options = options or EnvOptions()
    refuse_locomotion_options(label, options)
    _refuse_wrappers(label, obj)
    try:
        env = _ADAPTERS[kind](obj, label, episode_length, options)
    except Td3JaxError:
        raise
    except Exception as err:  # a missing attribute, a reset that cannot be traced, ...
        raise CustomEnvironmentError(f"{label}: cannot be used as {_ARTICLES[kind]}: "
                                     f"{_one_line(err)}") from err  # fmt: skip
    return check_environment(env)


def _kind(obj: Any) -> str | None:
    """Which of the forms ``obj`` is (``None``: none)."""
    if isinstance(obj, Environment):
        return "environment"
    if isinstance(obj, FunctionalEnv):
        return "functional"
    if isinstance(obj, tuple) and len(obj) == 2 and _instance(obj[0], "gymnax"):
        return "gymnax pair"
    return next((kind for kind in _BASES if _instance(obj, kind)), None)


def _instance(obj: Any, kind: str) -> bool:
    """Whether ``obj`` is an instance of ``kind``'s base class (its module already imported)."""
    module_name, class_name = _BASES[kind]
    module = sys.modules.get(module_name)
    base = getattr(module, class_name, None)
    return isinstance(base, type) and isinstance(obj, base)


def _label(obj: Any) -> str:
    """``object/<name>``: a FunctionalEnv's or gymnax environment's name, else its class's."""
    inner = obj[0] if isinstance(obj, tuple) else obj
    named = isinstance(inner, FunctionalEnv) or _instance(inner, "gymnax")
    return OBJECT_PREFIX + (str(inner.name) if named else type(inner).__name__)


def _refuse_wrappers(label: str, obj: Any) -> None:
    """One line for a Brax or Playground environment inside an episode, auto-reset or vmap
    wrapper (td3-jax brings its own: terminations kept apart from time limits, the true last
    observation, its own batch)."""
    layer = obj
    while layer is not None:
        if type(layer).__name__ in REFUSED_WRAPPERS:
            raise CustomEnvironmentError(
                f"{label}: the environment is wrapped in {type(layer).__name__}; hand it over "
                "without episode, auto-reset or vmap wrappers (e.g. brax.envs.get_environment, "
                "not brax.envs.create): td3-jax applies the time limit, resets and batches itself"
            )
        wraps = _instance(layer, "brax") or _instance(layer, "playground")
        layer = getattr(layer, "env", None) if wraps else None


def _from_functional(fenv: FunctionalEnv, name: str, episode_length: int | None,
                     options: EnvOptions) -> Environment:  # fmt: skip
    """A :class:`FunctionalEnv` as an :class:`Environment` (its reset and step jitted, so the
    programs share one trace of each)."""
    del options
    size = int(fenv.action_size)
    for which in ("action_low", "action_high"):
        bound = getattr(fenv, which)
        if np.asarray(bound).dtype.kind not in "biuf":  # (None, text: it read as NaN)
            raise CustomEnvironmentError(f"{name}: {which} is {bound!r}; give one number or "
                                         f"action_size ({size}) numbers")  # fmt: skip
        if np.ndim(bound) > 1 or np.size(bound) not in (1, size):
            raise CustomEnvironmentError(f"{name}: {which} has shape {np.shape(bound)}; give "
                                         f"one number or action_size ({size}) numbers")  # fmt: skip

    def step_fn(state: Any, action: jax.Array, key: jax.Array) -> tuple:
        del key  # a FunctionalEnv keeps any randomness it needs in its state
        return fenv.step(state, action)

    return Environment(
        name=name,
        observation_size=int(fenv.observation_size),
        action_size=size,
        episode_length=int(episode_length or fenv.episode_length),
        action_low=action_bound(fenv.action_low, size),
        action_high=action_bound(fenv.action_high, size),
        reset_fn=jax.jit(fenv.reset),
        step_fn=jax.jit(step_fn),
        mj_model=fenv.mj_model,
        qpos_fn=fenv.qpos,
    )


def _as_is(env: Environment, name: str, episode_length: int | None, options: EnvOptions):
    """An :class:`Environment` already (its time limit replaced when one is given)."""
    del name, options
    return dataclasses.replace(env, episode_length=int(episode_length)) if episode_length else env


_ADAPTERS: dict[str, Callable[..., Environment]] = {
    "environment": _as_is,
    "functional": _from_functional,
    "playground": lambda env, name, length, options: _playground.from_env(env, name, length,
                                                                          options),
    "brax": lambda env, name, length, options: _brax.from_env(env, name, length),
    "gymnax": lambda env, name, length, _: _gymnax.from_env(env, env.default_params, name,
                                                            length),
    "gymnax pair": lambda pair, name, length, _: _gymnax.from_env(*pair, name, length),
}  # fmt: skip
_ARTICLES = {
    "environment": "an Environment",
    "functional": "a FunctionalEnv",
    "playground": "a Playground MjxEnv",
    "brax": "a Brax Env",
    "gymnax": "a gymnax environment",
    "gymnax pair": "a gymnax (env, params) pair",
}


# ---------------------------------------------------------------------------------------------
# the check
# ---------------------------------------------------------------------------------------------


def check_environment(env: Environment) -> Environment:
    """``env`` once its reset and one step, traced abstractly (``jax.eval_shape``: nothing
    runs), give what td3-jax needs; else one line (:class:`CustomEnvironmentError`) saying what
    is wrong: sizes, bounds, a function JAX cannot trace, an observation, reward or
    termination of the wrong shape, a step that changes the state's shapes or dtypes."""
    _check_sizes(env)
    key = jax.random.PRNGKey(0)
    reset = _traced(env.name, "reset(key)", env.reset_fn, key)
    if not (isinstance(reset, tuple) and len(reset) == 2):
        raise CustomEnvironmentError(f"{env.name}: reset(key) must return (state, observation), "
                                     f"got {_described(reset)}")  # fmt: skip
    state, row = reset
    _check_observation(env, "reset(key)", row)
    action = jax.ShapeDtypeStruct((env.action_size,), jnp.float32)
    given = f"step(state, action) with an action of float32[{env.action_size}] (action_size)"
    stepped = _traced(env.name, given, env.step_fn, state, action, key)
    if not (isinstance(stepped, tuple) and len(stepped) == 4):
        raise CustomEnvironmentError(f"{env.name}: step(state, action) must return (state, "
                                     "observation, reward, terminated), got "
                                     f"{_described(stepped)}")  # fmt: skip
    _check_observation(env, "step(state, action)", stepped[1])
    for what, value in (("reward", stepped[2]), ("terminated", stepped[3])):
        if not _is_array(value) or value.shape != ():
            raise CustomEnvironmentError(f"{env.name}: step(state, action) gives a {what} of "
                                         f"{_described(value)}; it must be a scalar")  # fmt: skip
    _check_state(env.name, state, stepped[0])
    if env.qpos_fn is not None:
        positions = _traced(env.name, "qpos(state)", env.qpos_fn, state)
        if not _is_array(positions) or positions.ndim != 1:
            raise CustomEnvironmentError(f"{env.name}: qpos(state) gives {_described(positions)}; "
                                         "it must be a vector [nq]")  # fmt: skip
    return env


def _check_sizes(env: Environment) -> None:
    """Positive sizes and time limit; ``[action_size]`` finite bounds with ``low < high``."""
    for what in ("observation_size", "action_size", "episode_length"):
        value = getattr(env, what)
        if not isinstance(value, int | np.integer) or value <= 0:
            raise CustomEnvironmentError(f"{env.name}: {what} must be a positive integer, got "
                                         f"{value!r}")  # fmt: skip
    low, high = np.asarray(env.action_low), np.asarray(env.action_high)
    for what, bound in (("action_low", low), ("action_high", high)):
        if bound.shape != (env.action_size,) or not np.all(np.isfinite(bound)):
            count = "a finite number"
            if env.action_size > 1:
                count = f"{env.action_size} finite numbers"
            raise CustomEnvironmentError(f"{env.name}: {what} must be {count} (one per action), "
                                         f"got {bound.tolist()}")  # fmt: skip
    if not np.all(low < high):
        raise CustomEnvironmentError(f"{env.name}: action_low {low.tolist()} must be below "
                                     f"action_high {high.tolist()} in every dimension")  # fmt: skip


def _check_observation(env: Environment, what: str, row: Any) -> None:
    """``row`` is a ``[row_size]`` array of numbers."""
    if not _is_array(row) or row.shape != (env.row_size,) or not _numeric(row.dtype):
        raise CustomEnvironmentError(f"{env.name}: {what} gives an observation of "
                                     f"{_described(row)}; expected a vector of {env.row_size} "
                                     "numbers (observation_size)")  # fmt: skip


def _check_state(name: str, before: Any, after: Any) -> None:
    """``step`` returns a state of ``reset``'s structure, shapes and dtypes (the training loop
    carries it)."""
    if jax.tree.structure(before) != jax.tree.structure(after):
        raise CustomEnvironmentError(f"{name}: step(state, action) returns a state of another "
                                     "structure than reset(key)'s; it must keep the same "
                                     "fields")  # fmt: skip
    paths = jax.tree_util.tree_leaves_with_path(before)
    for (path, old), new in zip(paths, jax.tree.leaves(after), strict=True):
        if old.shape != new.shape or old.dtype != new.dtype:
            where = "state" + jax.tree_util.keystr(path)
            raise CustomEnvironmentError(f"{name}: step(state, action) turns {where} "
                                         f"from {_described(old)} into {_described(new)}; the "
                                         "state must keep its shapes and dtypes")  # fmt: skip


def _traced(name: str, what: str, fn: Callable, *args: Any) -> Any:
    """``jax.eval_shape(fn, *args)``; a failure is one line saying what could not be traced."""
    try:
        return jax.eval_shape(fn, *args)
    except Td3JaxError:
        raise
    except _NOT_JITTABLE as err:
        raise CustomEnvironmentError(
            f"{name}: {what} is not jittable ({_one_line(err)}); td3-jax compiles it: use "
            "jax.numpy and jax.lax (jnp.where, lax.cond), not Python branches or NumPy on values"
        ) from err
    except Exception as err:
        raise CustomEnvironmentError(f"{name}: {what} failed when traced: "
                                     f"{_one_line(err)}") from err  # fmt: skip


def _is_array(value: Any) -> bool:
    return isinstance(value, jax.ShapeDtypeStruct)


def _numeric(dtype: Any) -> bool:
    return bool(jnp.issubdtype(dtype, jnp.number) or jnp.issubdtype(dtype, jnp.bool_))


def _described(value: Any) -> str:
    """``float32[3]``-like text for an abstract array, the type's name otherwise."""
    if _is_array(value):
        return f"{value.dtype}{list(value.shape)}"
    if isinstance(value, tuple):
        return f"a tuple of {len(value)}"
    return f"a {type(value).__name__}"


def _one_line(err: BaseException) -> str:
    """``Type: first line of the message`` (at most 300 characters), then where in the caller's
    own code it was raised (:func:`_where_in_own_code`)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    text = f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__
    text = text if len(text) <= 300 else text[:297] + "..."
    return text + _where_in_own_code(err)


#: Folders whose frames are never the caller's own code: JAX's, NumPy's, td3-jax's and
#: Python's library (wherever they are installed).
_LIBRARY_FOLDERS = tuple(
    Path(folder).resolve()
    for folder in (Path(jax.__file__).parent, Path(np.__file__).parent,
                   Path(__file__).parent.parent, sysconfig.get_paths()["stdlib"])
)  # fmt: skip


def _where_in_own_code(err: BaseException) -> str:
    """`` (at FILE:LINE)``: the deepest frame of ``err``'s traceback in the caller's own code,
    or ``""`` where none is (:func:`_is_own_file`)."""
    own = [Path(folder).resolve() for folder in _own_folders()]
    given = [Path(entry).resolve() for entry in os.environ.get("PYTHONPATH", "").split(os.pathsep)
             if entry]  # fmt: skip
    installed = [root.resolve() for root in _installation()]
    frames = [frame for frame in traceback.extract_tb(err.__traceback__)
              if _is_own_file(frame.filename, own, given, installed)]  # fmt: skip
    return f" (at {frames[-1].filename}:{frames[-1].lineno})" if frames else ""


def _is_own_file(filename: str, own: list[Path], given: list[Path],
                 installed: list[Path]) -> bool:  # fmt: skip
    """Whether ``filename`` is a user's own code: under ``PYTHONPATH``'s folders (``given``),
    or under :func:`_own_folders` (``own``) and outside Python's installation and environment
    (``installed``: where other libraries are); never in :data:`_LIBRARY_FOLDERS`."""
    if filename.startswith("<"):
        return False
    path = Path(filename).resolve()
    inside = lambda folders: any(path.is_relative_to(folder) for folder in folders)
    return not inside(_LIBRARY_FOLDERS) and (
        inside(given) or (inside(own) and not inside(installed)))


__all__ = [
    "KINDS",
    "OBJECT_PREFIX",
    "FunctionalEnv",
    "check_environment",
    "check_unchanged",
    "from_factory",
    "from_object",
    "is_custom",
    "load_factory",
    "object_label",
    "signature",
]
