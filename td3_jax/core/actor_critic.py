"""One actor-critic builder for TD3 and DDPG: a static :class:`AgentSpec` and traced
:class:`AgentHyperparams`, and the steps of an update as module-level pure functions.

:func:`update` is a critic step on the TD target (:func:`td3_jax.core.losses.td_target`), then,
every ``policy_freq`` updates, an actor step and Polyak averaging of both targets
(:func:`delayed_actor_step`; with ``target_update="every_update"`` the target critics are
averaged after every critic step instead, as FastTD3 does). :func:`actor_critic` binds a spec
and hyperparameters into the :class:`~td3_jax.core.types.Agent` bundle; :func:`td3_jax.core.td3.td3`
and :func:`td3_jax.core.td3.ddpg` are its aliases (the optax ``alias.py`` shape).

Adam's learning rate is applied from the hyperparameters at every step (the optimiser state
holds only Adam's moments), so learning rates stay traced values: a sweep over them is a vmap.
The same holds for the options of :class:`AgentOptions` that are floats (weight decay, the
gradient-norm bound, the C51 support): they live in :class:`AgentHyperparams`. One optimiser
step (:func:`descend`) is ``params - lr_t * (adam(clip(grads)) + weight_decay * params)``:
gradients clipped by their global norm (when ``clip_grads``), Adam's direction, decoupled
weight decay as in ``optax.adamw``, and ``lr_t`` the learning rate times the schedule's
multiplier after ``step`` updates (:func:`learning_rate`).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from td3_jax.common.axes import any_member
from td3_jax.common.errors import ConfigError
from td3_jax.core import distributional, losses
from td3_jax.core.agent_spec import (  # noqa: F401  (re-exported: ac.AgentSpec, ...)
    ACTOR_Q,
    ADAM,
    C51_TARGET_HEADS,
    LR_SCHEDULES,
    METRIC_NAMES,
    NETWORKS,
    PRECISIONS,
    TARGET_UPDATES,
    AgentHyperparams,
    AgentOptions,
    AgentSpec,
)
from td3_jax.core.networks import Actor, CriticEnsemble, residual_layout
from td3_jax.core.types import Agent, AgentState, Metrics, Params, PRNGKey, Transition


def _check_sizes(observation_size: Any, action_size: Any, hidden_sizes: Any) -> None:
    for name, value in (("observation_size", observation_size), ("action_size", action_size)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
            raise ConfigError(f"{name} must be a positive integer, got {value!r}")
    hidden = tuple(hidden_sizes or ())
    if not hidden or any(not isinstance(h, int | np.integer) or h <= 0 for h in hidden):
        raise ConfigError(f"hidden_sizes must be positive integers, got {hidden_sizes}")


def _check_hyperparams(hp: AgentHyperparams) -> None:
    """Rejects impossible concrete values (traced values are the caller's responsibility)."""
    ranges = {
        "discount": (0.0, 1.0, True),
        "tau": (0.0, 1.0, False),
        "actor_lr": (0.0, np.inf, True),
        "critic_lr": (0.0, np.inf, True),
        "policy_noise": (0.0, np.inf, True),
        "noise_clip": (0.0, np.inf, True),
        "weight_decay": (0.0, np.inf, True),
        "max_grad_norm": (0.0, np.inf, False),  # inf allowed: no bound
        "max_weight_norm": (0.0, np.inf, False),
        "v_min": (-np.inf, np.inf, False),
        "v_max": (-np.inf, np.inf, False),
        "lr_final_fraction": (0.0, 1.0, True),
    }
    for name, (low, high, low_ok) in ranges.items():
        value = getattr(hp, name)
        if isinstance(value, jax.core.Tracer):
            continue
        v = np.asarray(value)
        below = v < low if low_ok else v <= low
        unbounded = name in ("max_grad_norm", "max_weight_norm") and not np.any(np.isnan(v))
        finite = np.all(np.isfinite(v)) or unbounded
        if not finite or np.any(v > high) or np.any(below):
            bound = "[" if low_ok else "("
            raise ConfigError(f"{name} must be finite and in {bound}{low}, {high}], got {value}")
    if not any(isinstance(x, jax.core.Tracer) for x in (hp.v_min, hp.v_max)) and np.any(
        np.asarray(hp.v_min) >= np.asarray(hp.v_max)
    ):
        raise ConfigError(f"v_min must be below v_max, got {hp.v_min} and {hp.v_max}")


def _check_options(options: AgentOptions) -> None:
    """``ConfigError`` naming the first impossible option."""
    if options.num_atoms < 0 or options.num_atoms == 1:
        raise ConfigError(f"num_atoms must be 0 (a plain critic) or >= 2, got {options.num_atoms}")
    choices = {
        "precision": tuple(PRECISIONS),
        "actor_q": ACTOR_Q,
        "lr_schedule": LR_SCHEDULES,
        "target_update": TARGET_UPDATES,
        "c51_target_head": C51_TARGET_HEADS,
        "critic_network": NETWORKS,
        "actor_network": NETWORKS,
    }
    for name, allowed in choices.items():
        if getattr(options, name) not in allowed:
            raise ConfigError(f"unknown {name} {getattr(options, name)!r}; choose one of "
                             f"{', '.join(allowed)}")  # fmt: skip
    if options.lr_schedule == "cosine" and (options.schedule_updates or 0) < 1:
        raise ConfigError("lr_schedule cosine needs schedule_updates >= 1 (the schedule's "
                         f"length in updates), got {options.schedule_updates}")  # fmt: skip


def make_spec(
    hidden_sizes: Sequence[int],
    observation_size: int,
    action_size: int,
    *,
    num_critics: int,
    target_smoothing: bool,
    policy_freq: int,
    max_action: Any = 1.0,
    options: AgentOptions = AgentOptions(),
    critic_observation_size: int | None = None,
) -> AgentSpec:
    """The static structure of an actor-critic agent (sizes checked, ``ConfigError`` if bad).

    ``hidden_sizes``: the widths of actor and critics unless ``options`` gives their own.
    ``critic_observation_size``: the critics learn from observations of this size
    (``Transition.critic_obs``) while the actor acts on ``observation_size`` ones; ``None``:
    the critics see the actor's observation.
    """
    actor_hidden = tuple(options.actor_hidden_sizes or hidden_sizes or ())
    critic_hidden = tuple(options.critic_hidden_sizes or hidden_sizes or ())
    for hidden in (hidden_sizes, actor_hidden, critic_hidden):
        _check_sizes(observation_size, action_size, hidden)
    if critic_observation_size is not None:
        _check_sizes(critic_observation_size, action_size, critic_hidden)
    if int(policy_freq) < 1:
        raise ConfigError(f"policy_freq must be >= 1, got {policy_freq}")
    _check_options(options)
    actor, critic = _networks(options, actor_hidden, critic_hidden, action_size, max_action,
                              num_critics)  # fmt: skip
    return AgentSpec(
        actor=actor,
        critic=critic,
        observation_size=int(observation_size),
        action_size=int(action_size),
        policy_freq=int(policy_freq),
        target_smoothing=target_smoothing,
        options=options,
        critic_observation_size=None
        if critic_observation_size is None
        else int(critic_observation_size),
    )


def _networks(
    options: AgentOptions,
    actor_hidden: tuple[int, ...],
    critic_hidden: tuple[int, ...],
    action_size: int,
    max_action: Any,
    num_critics: int,
) -> tuple[Actor, CriticEnsemble]:
    """The actor and the critics' ensemble of ``options``; ``ConfigError`` where a residual
    network's hidden sizes are not one width (:func:`~td3_jax.core.networks.residual_layout`)."""
    for network, sizes in ((options.critic_network, critic_hidden),
                           (options.actor_network, actor_hidden)):  # fmt: skip
        if network == "residual":
            residual_layout(sizes)
    dtype = PRECISIONS[options.precision]
    actor = Actor(_ints(actor_hidden), int(action_size), max_action, options.layer_norm, dtype,
                  options.actor_network == "residual")  # fmt: skip
    critic = CriticEnsemble(_ints(critic_hidden), num_critics, options.layer_norm, dtype,
                            int(options.num_atoms), options.critic_feature_norm,
                            options.critic_network == "residual")  # fmt: skip
    return actor, critic


def critic_input_size(spec: AgentSpec) -> int:
    """The size of the critics' observation input."""
    return spec.critic_observation_size or spec.observation_size


def _ints(sizes: Sequence[int]) -> tuple[int, ...]:
    return tuple(int(h) for h in sizes)


def hyperparams(config: Any, **settings: Any) -> AgentHyperparams:
    """The float settings of a config as :class:`AgentHyperparams` (DDPG: no smoothing noise).

    ``settings`` give or override fields (``weight_decay``, ``max_grad_norm`` and
    ``max_weight_norm`` (``None``: no bound), ``v_min``, ``v_max``, ...); fields neither gives
    take their defaults.
    """
    values = {
        "discount": config.discount,
        "tau": config.tau,
        "actor_lr": config.actor_lr,
        "critic_lr": config.critic_lr,
        "policy_noise": getattr(config, "policy_noise", 0.0),
        "noise_clip": getattr(config, "noise_clip", 0.0),
        **settings,
    }
    for bound in ("max_grad_norm", "max_weight_norm"):
        if bound in values and values[bound] is None:
            values[bound] = float("inf")
    hp = AgentHyperparams(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})
    hp = hp.replace(**{f.name: jnp.asarray(getattr(hp, f.name), jnp.float32)
                       for f in dataclasses.fields(hp) if f.name not in values})  # fmt: skip
    _check_hyperparams(hp)
    return hp


def init(spec: AgentSpec, key: PRNGKey) -> AgentState:
    """Fresh networks, targets equal to them, optimiser states, ``step = 0``; ``key``: a PRNG
    key (a ``TypeError`` for anything else, :func:`check_key`)."""
    check_key(key, "init")
    actor_key, critic_key = jax.random.split(key)
    obs = jnp.zeros((1, spec.observation_size), jnp.float32)
    critic_obs = jnp.zeros((1, critic_input_size(spec)), jnp.float32)
    action = jnp.zeros((1, spec.action_size), jnp.float32)
    actor_params = spec.actor.init(actor_key, obs)
    critic_params = spec.critic.init(critic_key, critic_obs, action)
    return AgentState(
        actor_params=actor_params,
        critic_params=critic_params,
        target_actor_params=actor_params if spec.options.target_actor else None,
        target_critic_params=critic_params,
        actor_opt_state=spec.optimizer.init(actor_params),
        critic_opt_state=spec.optimizer.init(critic_params),
        step=jnp.zeros((), jnp.int32),
    )


def learning_rate(
    spec: AgentSpec, lr: jax.Array, step: jax.Array, final_fraction: jax.Array = 0.0
) -> jax.Array:
    """The learning rate of the update after ``step`` updates: ``lr`` (constant) or
    ``lr * (f + (1 - f) * 0.5 * (1 + cos(pi * min(step, T) / T)))``, ``T = schedule_updates``,
    ``f = final_fraction`` (cosine: from ``lr`` to ``f * lr``)."""
    if spec.options.lr_schedule == "constant":
        return lr
    schedule = optax.cosine_decay_schedule(1.0, spec.options.schedule_updates, final_fraction)
    return lr * schedule(step)


def descend(
    spec: AgentSpec,
    hp: AgentHyperparams,
    params: Params,
    grads: Params,
    opt_state: Any,
    lr: jax.Array,
) -> tuple[Params, Any]:
    """One optimiser step ``params - lr * (adam(clip(grads)) + weight_decay * params)``.

    Gradients are clipped to the global norm ``hp.max_grad_norm`` first when
    ``spec.options.clip_grads``; the weight decay is decoupled from Adam's moments, as in
    ``optax.adamw`` (0: plain Adam). With ``spec.options.bound_weights`` the new weights are
    then bounded (:func:`bound_weight_norms`).
    """
    if spec.options.clip_grads:
        grads, _ = optax.clip_by_global_norm(hp.max_grad_norm).update(grads, optax.EmptyState())
    direction, opt_state = spec.optimizer.update(grads, opt_state, params)
    decay = optax.add_decayed_weights(hp.weight_decay)
    direction, _ = decay.update(direction, optax.EmptyState(), params)
    updates = jax.tree.map(lambda d: (-lr).astype(d.dtype) * d, direction)
    params = optax.apply_updates(params, updates)
    if spec.options.bound_weights:
        params = bound_weight_norms(params, hp.max_weight_norm)
    return params, opt_state


def bound_weight_norms(params: Params, max_norm: jax.Array) -> Params:
    """``params`` with every Dense ``kernel [..., in, out]``'s columns (one unit's incoming
    weights) scaled to norm ``max_norm`` where they exceed it; biases and LayerNorm scales
    unchanged."""

    def bound(path: tuple, leaf: jax.Array) -> jax.Array:
        if getattr(path[-1], "key", None) != "kernel":
            return leaf
        norms = jnp.linalg.norm(leaf, axis=-2, keepdims=True)
        return leaf * jnp.minimum(1.0, max_norm / jnp.maximum(norms, 1e-12))

    return jax.tree_util.tree_map_with_path(bound, params)


def target_policy_params(spec: AgentSpec, state: AgentState) -> Params:
    """The actor that picks target actions: the target actor, or the online one without it."""
    return state.target_actor_params if spec.options.target_actor else state.actor_params


def _value_metrics(
    spec: AgentSpec, hp: AgentHyperparams, out: jax.Array, target: jax.Array
) -> Metrics:
    """``q_mean`` and ``target_mean`` of a critic step (C51: the distributions' means)."""
    if not spec.distributional:
        return {"q_mean": jnp.mean(out), "target_mean": jnp.mean(target)}
    z = distributional.support(spec.options.num_atoms, hp.v_min, hp.v_max)
    return {"q_mean": jnp.mean(distributional.mean_value(out, z)),
            "target_mean": jnp.mean(jnp.sum(target * z, axis=-1))}  # fmt: skip


def critic_step(
    spec: AgentSpec, hp: AgentHyperparams, state: AgentState, batch: Transition, key: PRNGKey
) -> tuple[AgentState, Metrics]:
    """One critic step on the TD target (C51: the target distribution); counts the update in
    ``state.step``."""
    target_fn, loss_fn = losses.td_target, losses.critic_loss
    if spec.distributional:
        target_fn, loss_fn = losses.categorical_target, losses.categorical_loss
    target = target_fn(
        spec, hp, target_policy_params(spec, state), state.target_critic_params, batch, key
    )
    (loss, out), grads = jax.value_and_grad(loss_fn, has_aux=True)(
        state.critic_params, spec, batch, target
    )
    lr = learning_rate(spec, hp.critic_lr, state.step, hp.lr_final_fraction)
    params, opt_state = descend(spec, hp, state.critic_params, grads, state.critic_opt_state, lr)
    state = state.replace(critic_params=params, critic_opt_state=opt_state, step=state.step + 1)
    if spec.options.target_update == "every_update":
        state = state.replace(target_critic_params=_averaged_critics(hp, state))
    return state, {"critic_loss": loss, **_value_metrics(spec, hp, out, target)}


def _averaged_critics(hp: AgentHyperparams, state: AgentState) -> Params:
    """The target critics moved ``tau`` of the way to the online ones (Polyak averaging)."""
    return optax.incremental_update(state.critic_params, state.target_critic_params, hp.tau)


def actor_step(
    spec: AgentSpec, hp: AgentHyperparams, state: AgentState, batch: Transition
) -> tuple[AgentState, jax.Array]:
    """One actor step on the current critic, then Polyak averaging of the target actor (when
    there is one) and, with ``target_update="with_actor"``, of the target critics. Its learning
    rate is that of the critic step just taken (the schedule at ``state.step - 1``)."""
    loss, grads = jax.value_and_grad(losses.actor_loss)(
        state.actor_params, state.critic_params, spec, hp, batch
    )
    lr = learning_rate(spec, hp.actor_lr, state.step - 1, hp.lr_final_fraction)
    params, opt_state = descend(spec, hp, state.actor_params, grads, state.actor_opt_state, lr)
    target_actor = state.target_actor_params
    if spec.options.target_actor:
        target_actor = optax.incremental_update(params, target_actor, hp.tau)
    target_critic = state.target_critic_params
    if spec.options.target_update == "with_actor":
        target_critic = _averaged_critics(hp, state)
    state = state.replace(
        actor_params=params,
        actor_opt_state=opt_state,
        target_actor_params=target_actor,
        target_critic_params=target_critic,
    )
    return state, loss


def _actor_step_where_due(
    spec: AgentSpec, hp: AgentHyperparams, due: jax.Array, state: AgentState, batch: Transition
) -> tuple[AgentState, jax.Array]:
    """:func:`actor_step` where ``due``; the unchanged state (and loss 0) elsewhere."""
    new_state, loss = actor_step(spec, hp, state, batch)
    keep = lambda new, old: jnp.where(due, new, old)
    return jax.tree.map(keep, new_state, state), jnp.where(due, loss, 0.0)


def _skip_actor_step(state: AgentState, batch: Transition) -> tuple[AgentState, jax.Array]:
    del batch
    return state, jnp.zeros((), jnp.float32)


def delayed_actor_step(
    spec: AgentSpec,
    hp: AgentHyperparams,
    state: AgentState,
    batch: Transition,
    axis_name: str | None = None,
) -> tuple[AgentState, jax.Array, jax.Array]:
    """:func:`actor_step` when ``state.step`` is a multiple of ``policy_freq``.

    Returns ``(state, actor_loss, actor_updated)`` (loss 0 when not updated). Under a
    ``jax.vmap`` with ``axis_name`` the branch is taken when any member is due, and each member
    still only updates on its own schedule.
    """
    if spec.policy_freq == 1:
        state, loss = actor_step(spec, hp, state, batch)
        return state, loss, jnp.ones((), jnp.float32)
    due = state.step % spec.policy_freq == 0
    # Alone, the branch runs exactly when due; under a member axis, when any member is due.
    take = (functools.partial(actor_step, spec, hp) if axis_name is None
            else functools.partial(_actor_step_where_due, spec, hp, due))  # fmt: skip
    state, loss = jax.lax.cond(any_member(due, axis_name), take, _skip_actor_step, state, batch)
    return state, loss, due.astype(jnp.float32)


def check_batch(spec: AgentSpec, batch: Transition) -> None:
    """Raises ``ConfigError`` naming the field when ``batch`` is not ``[batch, ...]``-shaped, or
    the field whose batch size differs from the other fields'."""
    o, a = spec.observation_size, spec.action_size
    expected = {"obs": (o,), "action": (a,), "reward": (), "next_obs": (o,), "done": ()}
    if spec.critic_observation_size is not None or batch.critic_obs is not None:
        c = critic_input_size(spec)
        expected.update(critic_obs=(c,), next_critic_obs=(c,))
    shapes = {}
    for name, tail in expected.items():
        field = getattr(batch, name)
        shape = shapes[name] = None if field is None else tuple(jnp.shape(field))
        if shape is None or len(shape) != len(tail) + 1 or shape[1:] != tail:
            want = f"[batch{''.join(f', {t}' for t in tail)}]"
            has = "is missing" if shape is None else f"has shape {list(shape)}"
            raise ConfigError(
                f"Transition.{name} {has}; expected {want} for an agent with observation_size "
                f"{o}, critic observation size {critic_input_size(spec)} and action_size {a} "
                "(a batch, rows first)"
            )
    rows = collections.Counter(shape[0] for shape in shapes.values()).most_common(1)[0][0]
    odd = next((name for name, shape in shapes.items() if shape[0] != rows), None)
    if odd is not None:
        others = [name for name, shape in shapes.items() if shape[0] == rows]
        raise ConfigError(
            f"Transition.{odd} has a batch of {shapes[odd][0]} rows (shape "
            f"{list(shapes[odd])}) while {', '.join(others)} have {rows}; every field needs the "
            "same batch size (rows first)"
        )


def update(
    spec: AgentSpec,
    hp: AgentHyperparams,
    state: AgentState,
    batch: Transition,
    key: PRNGKey,
    axis_name: str | None = None,
) -> tuple[AgentState, Metrics]:
    """One TD3/DDPG update on ``batch`` (leaves ``[batch, ...]``); see the module docstring.

    Metrics (float32 scalars, :data:`METRIC_NAMES`): ``critic_loss``, ``actor_loss`` (0 where
    the actor was not updated), ``actor_updated``, ``q_mean``, ``target_mean``.
    Raises ``ConfigError`` for a batch of other shapes (:func:`check_batch`) and ``TypeError``
    for a ``key`` that is no PRNG key (:func:`check_key`), where it is traced.
    """
    check_batch(spec, batch)
    check_key(key, "update")
    state, metrics = critic_step(spec, hp, state, batch, key)
    state, loss, updated = delayed_actor_step(spec, hp, state, batch, axis_name)
    return state, {**metrics, "actor_loss": loss, "actor_updated": updated}


def zero_metrics() -> Metrics:
    """The metrics of an update that did not happen: every :data:`METRIC_NAMES` entry 0."""
    return {name: jnp.zeros((), jnp.float32) for name in METRIC_NAMES}


def actor_critic(
    spec: AgentSpec, hp: AgentHyperparams, config: Any = None, axis_name: str | None = None
) -> Agent:
    """The :class:`~td3_jax.core.types.Agent` bundle of ``spec`` with ``hp`` bound."""
    act = functools.partial(_act, spec)
    return Agent(
        init=functools.partial(init, spec),
        update=functools.partial(_bound_update, spec, hp, axis_name),
        act=act,
        actor_apply=act,
        critic_apply=functools.partial(_critic_apply, spec, hp),
        config=config,
        spec=spec,
        hyperparams=hp,
    )


def _act(spec: AgentSpec, params: Params, obs: jax.Array) -> jax.Array:
    """The actor on ``obs [..., observation_size]``; a ``ConfigError`` with both sizes for
    observations of another width (flax would raise its internal ``ScopeParamShapeError``)."""
    shape = tuple(jnp.shape(obs))
    if not shape or shape[-1] != spec.observation_size:
        given = f"of size {shape[-1]}" if shape else "that are a scalar"
        raise ConfigError(
            f"act got observations {given} (shape {list(shape)}); this agent's actor takes "
            f"observation_size {spec.observation_size} ([..., {spec.observation_size}])"
        )
    return spec.actor.apply(params, obs)


def _critic_apply(spec: AgentSpec, hp: AgentHyperparams, params: Params, obs: jax.Array,
                  action: jax.Array) -> jax.Array:  # fmt: skip
    """Every critic head's Q-value ``[heads, ...]`` of ``obs [..., o]`` and ``action [..., a]``
    (:func:`td3_jax.core.losses.q_values`); a ``ConfigError`` naming the argument whose width
    or leading shape is not the critics' (flax would raise its ``ScopeParamShapeError``)."""
    obs_shape, action_shape = tuple(jnp.shape(obs)), tuple(jnp.shape(action))
    sizes = {"obs": critic_input_size(spec), "action": spec.action_size}
    for name, shape in (("obs", obs_shape), ("action", action_shape)):
        if not shape or shape[-1] != sizes[name]:
            given = f"of size {shape[-1]}" if shape else "that is a scalar"
            raise ConfigError(
                f"critic_apply got {name} {given} (shape {list(shape)}); this agent's critics "
                f"take observations of size {sizes['obs']} and actions of size "
                f"{sizes['action']} ([..., {sizes['obs']}] and [..., {sizes['action']}])"
            )
    if obs_shape[:-1] != action_shape[:-1]:
        raise ConfigError(
            f"critic_apply got obs of shape {list(obs_shape)} and action of shape "
            f"{list(action_shape)}; their leading axes must be the same (one action per "
            "observation)"
        )
    return losses.q_values(spec, hp, params, obs, action)


def check_key(key: Any, where: str) -> None:
    """Raises ``TypeError`` naming ``where`` unless ``key`` is one PRNG key: a typed key of
    shape ``[]`` (``jax.random.key``) or raw ``uint32`` key data of the default
    implementation's shape (``jax.random.PRNGKey``: ``[2]``); checked where traced, so under
    ``vmap`` a member's key."""
    dtype, shape = getattr(key, "dtype", None), getattr(key, "shape", None)
    if dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key):
        if tuple(shape) == ():
            return
        got = f"an array of {list(shape)} keys"
    elif dtype is not None and shape is not None:
        if np.dtype(dtype) == np.uint32 and tuple(shape) == _raw_key_shape():
            return
        got = f"an array of shape {list(shape)} and dtype {np.dtype(dtype).name}"
    else:
        got = f"{type(key).__name__} {key!r}"
    raise TypeError(
        f"{where}'s key must be one PRNG key, jax.random.key(seed) or jax.random.PRNGKey(seed) "
        f"(split it for several: jax.random.split), got {got}"
    )


@functools.cache
def _raw_key_shape() -> tuple[int, ...]:
    """The shape of ``jax.random.PRNGKey``'s key data (``(2,)`` for the default threefry)."""
    return tuple(jax.eval_shape(jax.random.PRNGKey, 0).shape)


def _bound_update(spec, hp, axis_name, state, batch, key):
    return update(spec, hp, state, batch, key, axis_name)


__all__ = [
    "C51_TARGET_HEADS",
    "LR_SCHEDULES",
    "METRIC_NAMES",
    "NETWORKS",
    "PRECISIONS",
    "TARGET_UPDATES",
    "AgentHyperparams",
    "AgentOptions",
    "AgentSpec",
    "actor_critic",
    "actor_step",
    "bound_weight_norms",
    "check_key",
    "critic_step",
    "hyperparams",
    "init",
    "make_spec",
    "update",
]
