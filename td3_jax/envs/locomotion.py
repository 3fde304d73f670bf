"""MuJoCo Playground's locomotion tasks (``playground/T1JoystickFlatTerrain``, ``.../Go1Getup``,
...): humanoids and quadrupeds with dict observations, for an asymmetric actor-critic.

* Stepped by MuJoCo Warp where it can run, else by MJX's JAX physics (``options.impl``,
  :mod:`td3_jax.envs.physics`); loaded from the robot folder
  :func:`td3_jax.envs.menagerie.find_root` finds; Playground's ``git clone`` of the Menagerie
  is never reached (its check is replaced by ours while the task is built).
* Observations ``{'state', 'privileged_state'}``: the actor sees ``options.actor_obs_key``, the
  critics ``options.critic_obs_key``, stored as one row (:mod:`td3_jax.envs.base`); whether the
  actor's observation is a prefix of the critics' is read from the task's own program
  (:func:`is_prefix`), per task, never assumed.
* Episode ends: the task's ``done`` is its termination (a fall, NaN physics); the time limit is
  the task's ``episode_length`` (1000 for the joysticks) and a truncation; the auto-reset of
  :func:`td3_jax.envs.base.step` keeps the true last observation and draws a fresh random state.
  Commands are sampled by the task itself (at reset and every few seconds), untouched.
* Options (:class:`~td3_jax.envs.base.EnvOptions`): the task's domain randomiser, drawn anew for
  every environment at every reset; push perturbations on or off.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
from collections.abc import Callable
from typing import Any

import jax
import jax.extend.core as jex_core
import jax.numpy as jnp
import numpy as np

from td3_jax.common import upstream
from td3_jax.envs import menagerie, physics, warp_kernels
from td3_jax.envs.base import Environment, EnvironmentOptionError, EnvOptions

__all__ = [
    "PUSH_SECTIONS",
    "Layout",
    "Randomization",
    "check_warp_randomization",
    "draw",
    "from_task",
    "is_prefix",
    "layout",
    "load",
    "make",
    "names",
    "precompile_sizes",
    "prepare_warp",
    "push_overrides",
    "randomization",
    "randomized_field_names",
    "randomized_model",
    "row",
    "warp_overflow",
    "warp_overrides",
]


def names() -> list[str]:
    """Playground's locomotion task names, or an empty list without Playground."""
    physics.import_mjx_quietly()  # (Playground imports MJX, which prints notes without Warp)
    try:
        return sorted(upstream.playground_locomotion().ALL_ENVS)
    except ImportError:
        return []


@dataclasses.dataclass(frozen=True)
class Layout:
    """How a task's observation becomes the stored row (see :mod:`td3_jax.envs.base`).

    ``actor_key``/``critic_key``: the dict keys (``None`` for a flat observation, and
    ``critic_key`` ``None`` when the critics see the actor's observation); ``prefix``: the
    actor's observation is the first ``actor_size`` entries of the critics'.
    """

    actor_key: str | None
    critic_key: str | None
    actor_size: int
    critic_size: int | None
    prefix: bool


def row(layout: Layout, obs: Any) -> jax.Array:
    """The stored row ``[row_size]`` of one observation (a dict or a flat vector)."""
    if layout.actor_key is None:
        return obs
    if layout.critic_key is None:
        return obs[layout.actor_key]
    if layout.prefix:
        return obs[layout.critic_key]
    return jnp.concatenate([obs[layout.actor_key], obs[layout.critic_key]])


# ---------------------------------------------------------------------------------------------
# Is the actor's observation a prefix of the critics'? Read from the traced program (the
# primitives' names: td3_jax.common.upstream).
# ---------------------------------------------------------------------------------------------


def _outer(var: Any, eqn: Any, inner: Any) -> Any:
    """The argument of ``eqn`` that its inner jaxpr's input ``var`` is (``None`` if none)."""
    for outer_in, inner_in in zip(eqn.invars, inner.invars, strict=True):
        if var is inner_in:
            return outer_in
    return None


def _passes_through(eqn: Any) -> Any:
    """The input an equation returns unchanged (an identity ``jit``, a same-shape reshape or
    dtype-preserving convert), or ``None``."""
    inner = upstream.called_jaxpr(eqn)
    if inner is not None:
        return _outer(inner.outvars[0], eqn, inner) if len(eqn.outvars) == 1 else None
    same = eqn.invars and eqn.invars[0].aval.shape == eqn.outvars[0].aval.shape
    if upstream.may_copy(eqn) and same:
        return eqn.invars[0] if eqn.invars[0].aval.dtype == eqn.outvars[0].aval.dtype else None
    return None


def _producers(jaxpr: Any) -> dict:
    return {v: e for e in jaxpr.eqns for v in e.outvars}


def _origin(var: Any, producers: dict) -> Any:
    """``var`` followed back through equations that pass their input through."""
    while isinstance(var, jex_core.Var) and var in producers:
        source = _passes_through(producers[var])
        if source is None:
            break
        var = source
    return var


def _first_piece(var: Any, producers: dict) -> Any:
    """The first piece of the concatenation (along axis 0) that makes ``var``, looking inside
    ``jit`` calls (a jitted ``hstack``), or ``None``."""
    eqn = producers.get(var) if isinstance(var, jex_core.Var) else None
    if eqn is None:
        return None
    axis = upstream.concatenation_axis(eqn)
    if axis is not None:
        return eqn.invars[0] if axis == 0 else None
    inner = upstream.called_jaxpr(eqn)
    if inner is None:
        return None
    inside = _producers(inner)
    out = _origin(inner.outvars[eqn.outvars.index(var)], inside)
    piece = _origin(_first_piece(out, inside), inside)
    return None if piece is None else _outer(piece, eqn, inner)


def _prefix_in(jaxpr: Any, outputs: list) -> bool:
    """Whether ``outputs[1]`` of ``jaxpr`` is a concatenation whose first piece is exactly
    ``outputs[0]`` (the same traced value, not an equal-looking one)."""
    producers = _producers(jaxpr)
    actor, critic = (_origin(v, producers) for v in outputs)
    piece = _first_piece(critic, producers)
    return isinstance(actor, jex_core.Var) and _origin(piece, producers) is actor


def _traced_reset(env: Any) -> tuple[Any, Any]:
    """``(jaxpr, state shapes)`` of ``env.reset`` (one trace; nothing runs)."""
    return jax.make_jaxpr(env.reset, return_shape=True)(jax.random.PRNGKey(0))


def _outputs(jaxpr: Any, shapes: Any, keys: tuple[str, str]) -> list:
    """The output variables of ``jaxpr`` holding ``obs[keys[0]]`` and ``obs[keys[1]]``."""
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(shapes)]
    return [jaxpr.outvars[paths.index(f".obs['{key}']")] for key in keys]


def is_prefix(env: Any, actor_key: str, critic_key: str, traced_reset: Any = None) -> bool:
    """Whether ``obs[critic_key]`` starts with ``obs[actor_key]`` after ``reset`` and after
    ``step`` of the Playground task ``env``, read from their traced programs (no physics
    runs). ``False`` when it cannot be shown (the row then stores both)."""
    closed, state = traced_reset or _traced_reset(env)
    keys = (actor_key, critic_key)
    action = jax.ShapeDtypeStruct((env.action_size,), jnp.float32)
    stepped, _ = jax.make_jaxpr(env.step, return_shape=True)(state, action)
    return all(_prefix_in(j.jaxpr, _outputs(j.jaxpr, state, keys))
               for j in (closed, stepped))  # fmt: skip


def layout(env: Any, options: EnvOptions) -> Layout:
    """The row layout of ``env``'s observation under ``options``' keys."""
    traced = _traced_reset(env)
    shapes = traced[1].obs
    if not isinstance(shapes, dict):
        return Layout(None, None, int(shapes.shape[-1]), None, False)
    for key in (options.actor_obs_key, options.critic_obs_key):
        if key not in shapes:
            raise EnvironmentOptionError(
                f"observation key {key!r} is not one of this task's: {', '.join(sorted(shapes))}"
            )
    actor_size = int(shapes[options.actor_obs_key].shape[-1])
    if options.actor_obs_key == options.critic_obs_key:
        return Layout(options.actor_obs_key, None, actor_size, None, False)
    prefix = is_prefix(env, options.actor_obs_key, options.critic_obs_key, traced)
    critic_size = int(shapes[options.critic_obs_key].shape[-1])
    return Layout(options.actor_obs_key, options.critic_obs_key, actor_size, critic_size, prefix)


# ---------------------------------------------------------------------------------------------
# Building a task offline, with its options
# ---------------------------------------------------------------------------------------------


#: The perturbation settings of the tasks that have them: config section -> its switch.
PUSH_SECTIONS = ("push_config", "pert_config")


def push_overrides(task: str, config: Any, pushes: bool | None) -> dict[str, Any]:
    """Playground config overrides switching the task's pushes on or off (``None``: none)."""
    if pushes is None:
        return {}
    for section in PUSH_SECTIONS:
        if section in config:
            overrides = {f"{section}.enable": bool(pushes)}
            if not pushes and "magnitude_range" in config[section]:
                overrides[f"{section}.magnitude_range"] = [0.0, 0.0]
            return overrides
    raise EnvironmentOptionError(f"playground/{task} has no push perturbations to turn "
                                 f"{'on' if pushes else 'off'}")  # fmt: skip


def warp_overrides(config: Any, impl: str, options: EnvOptions) -> dict[str, Any]:
    """Playground config overrides sizing MuJoCo Warp's buffers: the contact buffer (shared by
    every environment stepped together) for ``options.worlds`` environments, the constraints
    per environment (``options.njmax``, else the task's); none for the JAX physics."""
    if impl != "warp" or "naconmax" not in config:
        return {}
    overrides = {"naconmax": physics.contact_capacity(int(config.naconmax), options.worlds,
                                                      options.nconmax)}  # fmt: skip
    if options.njmax is not None:
        overrides["njmax"] = int(options.njmax)
    return overrides


def warp_overflow(state: Any) -> jax.Array:
    """Whether MuJoCo Warp ran out of a fixed buffer (contacts, constraints, collision pairs)
    in the step that produced the Playground ``state``: what it dropped makes the physics
    wrong. Read from Warp's per-environment overflow flags (:data:`physics.WRONG_PHYSICS`)."""
    return (upstream.warp_overflow_flags(state.data) & physics.WRONG_PHYSICS) != 0


def load(task: str, *, impl: str = "jax", options: EnvOptions = EnvOptions()) -> tuple[Any, Any]:
    """``(task object, its config)``: the Playground task built offline from the robot folder
    found for it (:class:`~td3_jax.envs.menagerie.MissingAssetsError` when there is none)."""
    root = menagerie.find_root(task, options.menagerie)
    physics.import_mjx_quietly()
    registry = upstream.playground_locomotion()
    config = registry.get_default_config(task)
    overrides = {"impl": impl, **push_overrides(task, config, options.pushes),
                 **warp_overrides(config, impl, options)}  # fmt: skip
    with upstream.playground_menagerie_at(root):
        env = registry.load(task, config=config, config_overrides=overrides)
    if impl == "warp":
        prepare_warp(env.unwrapped, config, options)
    return env, config


def prepare_warp(task: Any, config: Any, options: EnvOptions) -> None:
    """Readies a Playground ``task`` made on Warp (``config``: its default config): quiets its
    solver's iteration-limit warnings, then compiles Warp's kernels for its model ahead, on
    several threads (:func:`td3_jax.envs.warp_kernels.precompile_task`), sized as the run's
    buffers are (:func:`precompile_sizes`)."""
    physics.quiet_solver_limits(task)
    warp_kernels.precompile_task(task, **precompile_sizes(config, options))


def precompile_sizes(config: Any, options: EnvOptions) -> dict[str, int | None]:
    """``njmax`` (constraints per environment, as :func:`warp_overrides` sets them) and
    ``naconmax`` (one environment's contacts) of the task's ``config`` for the precompile's one
    world; ``None`` where the config has no such size."""
    njmax = options.njmax if options.njmax is not None else config.get("njmax")
    naconmax = config.get("naconmax")  # (for all of Playground's worlds: one world's share)
    one_world = options.nconmax or max(1, int(naconmax or 0) // physics.PLAYGROUND_WORLDS)
    return {"njmax": None if njmax is None else int(njmax),
            "naconmax": None if naconmax is None else int(one_world)}  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Domain randomisation: the task's randomiser, drawn per environment at every reset
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Randomization:
    """A task's domain randomiser reduced to the model leaves it draws (``leaves``: their
    indices in ``jax.tree.leaves(model)``), so each environment carries only those."""

    randomizer: Callable[[Any, jax.Array], tuple[Any, Any]]
    model: Any
    leaves: tuple[int, ...]


def randomization(task: str, env: Any) -> Randomization:
    """The task's own randomiser (``EnvironmentOptionError`` for a task without one)."""
    with contextlib.redirect_stdout(io.StringIO()):  # (it prints when there is none)
        randomizer = upstream.playground_locomotion().get_domain_randomizer(task)
    if randomizer is None:
        raise EnvironmentOptionError(f"playground/{task} has no domain randomiser")
    model = env.mjx_model
    drawn = jax.eval_shape(lambda k: randomizer(model, k[None])[0], jax.random.PRNGKey(0))
    pairs = zip(jax.tree.leaves(model), jax.tree.leaves(drawn), strict=True)
    leaves = tuple(i for i, (m, d) in enumerate(pairs) if tuple(d.shape) != np.shape(m))
    return Randomization(randomizer, model, leaves)


def randomized_field_names(rand: Randomization) -> tuple[str, ...]:
    """The model fields ``rand`` draws, as ``jax.tree_util.keystr`` spells their paths without
    the leading dot (``body_mass``; a nested field ``opt.gravity``)."""
    paths = [path for path, _ in jax.tree_util.tree_flatten_with_path(rand.model)[0]]
    return tuple(jax.tree_util.keystr(paths[i]).lstrip(".") for i in rand.leaves)


def check_warp_randomization(task: str, rand: Randomization, per_world: frozenset[str]) -> None:
    """``EnvironmentOptionError`` when ``rand`` draws a field that MuJoCo Warp would simulate as
    one value for every world (not in ``per_world``): domain randomisation would silently not
    happen there."""
    shared = [name for name in randomized_field_names(rand) if name not in per_world]
    if shared:
        raise EnvironmentOptionError(
            f"playground/{task}'s domain randomiser draws {', '.join(shared)}, which MuJoCo Warp "
            "simulates as one value for every environment: use --impl jax with "
            "--domain-randomization"
        )


def draw(rand: Randomization, key: jax.Array) -> tuple[jax.Array, ...]:
    """One environment's randomised model leaves (unbatched)."""
    leaves = jax.tree.leaves(rand.randomizer(rand.model, key[None])[0])
    return tuple(leaves[i][0] for i in rand.leaves)


def randomized_model(rand: Randomization, fields: tuple[jax.Array, ...]) -> Any:
    """The task's model with the drawn ``fields`` in place."""
    leaves, treedef = jax.tree.flatten(rand.model)
    for i, field in zip(rand.leaves, fields, strict=True):
        leaves[i] = field
    return jax.tree.unflatten(treedef, leaves)


# ---------------------------------------------------------------------------------------------
# The td3-jax environment
# ---------------------------------------------------------------------------------------------


def _reset(env: Any, lay: Layout, rand: Randomization | None, key: jax.Array):
    if rand is None:
        state = env.reset(key)
        return state, row(lay, state.obs)
    model_key, key = jax.random.split(key)
    fields = draw(rand, model_key)
    with upstream.simulating(env.unwrapped, randomized_model(rand, fields)):
        state = env.reset(key)
    return (state, fields), row(lay, state.obs)


def _step(env: Any, lay: Layout, rand: Randomization | None, inner: Any, action, key):
    del key  # the task draws its own noise, pushes and commands from its state's key
    if rand is None:
        state = inner = env.step(inner, action)
    else:
        state, fields = inner
        with upstream.simulating(env.unwrapped, randomized_model(rand, fields)):
            state = env.step(state, action)
        inner = (state, fields)
    return inner, row(lay, state.obs), state.reward, state.done > 0.5


def _qpos(rand: Randomization | None, inner: Any) -> jax.Array:
    """``[nq]`` joint positions of the task's state (held beside the drawn model fields when
    randomised)."""
    state = inner if rand is None else inner[0]
    return state.data.qpos


def _overflow(rand: Randomization | None, inner: Any) -> jax.Array:
    """:func:`warp_overflow` of the task's state (held beside the drawn model fields when
    randomised)."""
    return warp_overflow(inner if rand is None else inner[0])


def make(
    task: str,
    *,
    episode_length: int | None = None,
    options: EnvOptions = EnvOptions(),
) -> Environment:
    """A Playground locomotion task (see the module docstring) on the physics
    ``options.impl`` (:func:`td3_jax.envs.physics.resolve`); ``episode_length``: the time
    limit, default the task's own."""
    impl = physics.resolve(options.impl)
    env, config = load(task, impl=impl, options=options)
    rand = randomization(task, env) if options.domain_randomization else None
    if rand is not None and impl == "warp":
        check_warp_randomization(task, rand, upstream.warp_per_world_model_fields())
    return from_task(env, f"playground/{task}", int(episode_length or config.episode_length),
                     options, rand=rand, warp=impl == "warp")  # fmt: skip


def from_task(
    env: Any,
    name: str,
    episode_length: int,
    options: EnvOptions = EnvOptions(),
    *,
    rand: Randomization | None = None,
    warp: bool = False,
) -> Environment:
    """An already-made Playground task ``env`` (a ``MjxEnv``) as the environment ``name``: its
    observation (flat, or a dict whose ``options`` keys the actor and the critics see) stored
    as rows (:func:`layout`), its model drawn by ``rand`` at every reset (``None``: fixed),
    MuJoCo Warp's buffer overflows reported and its batches stepped on each device apart
    (:attr:`~td3_jax.envs.base.Environment.per_device`) when ``warp``."""
    lay = layout(env, options)
    return Environment(
        name=name,
        observation_size=lay.actor_size,
        action_size=int(env.action_size),
        episode_length=int(episode_length),
        action_low=-np.ones(env.action_size, np.float32),
        action_high=np.ones(env.action_size, np.float32),
        # Jitted (as base.from_mjx_style does): the physics is traced once per input shape and
        # shared by init, chunk and evaluation, instead of traced again by each (seconds each).
        reset_fn=jax.jit(functools.partial(_reset, env, lay, rand)),
        step_fn=jax.jit(functools.partial(_step, env, lay, rand)),
        critic_observation_size=lay.critic_size,
        critic_offset=lay.actor_size if lay.critic_size and not lay.prefix else 0,
        mj_model=env.mj_model,
        qpos_fn=functools.partial(_qpos, rand),
        overflow_fn=functools.partial(_overflow, rand) if warp else None,
        per_device=warp,
    )
