"""One actor-critic builder for TD3 and DDPG: a static :class:`AgentSpec` and traced
:class:`AgentHyperparams`, and the steps of an update as module-level pure functions.

:func:`update` is a critic step on the TD target (:func:`td3_jax.losses.td_target`), then,
every ``policy_freq`` updates, an actor step and Polyak averaging of both targets
(:func:`delayed_actor_step`). :func:`actor_critic` binds a spec and hyperparameters into the
:class:`~td3_jax.types.Agent` bundle; :func:`td3_jax.td3.td3` and :func:`td3_jax.td3.ddpg` are
its aliases (the optax ``alias.py`` shape).

Adam's learning rate is applied from the hyperparameters at every step (the optimiser state
holds only Adam's moments), so learning rates stay traced values: a sweep over them is a vmap.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from td3_jax import losses
from td3_jax.axes import any_member
from td3_jax.networks import Actor, CriticEnsemble
from td3_jax.types import Agent, AgentState, Metrics, Params, PRNGKey, Transition

#: The metrics of one :func:`update` (float32 scalars).
METRIC_NAMES = ("critic_loss", "actor_loss", "actor_updated", "q_mean", "target_mean")


#: Adam's direction (b1 0.9, b2 0.999, eps 1e-8), one shared instance so that specs compare equal.
ADAM = optax.scale_by_adam()


@dataclasses.dataclass(frozen=True)
class AgentSpec:
    """The static structure of an actor-critic agent.

    Attributes:
      actor: ``obs [..., obs_size] -> action [..., action_size]`` in ``[-max_action, max_action]``.
      critic: ``(obs, action) -> q [num_critics, ...]``.
      observation_size, action_size: input and output sizes.
      policy_freq: the actor and the targets are updated every ``policy_freq`` updates.
      target_smoothing: TD3's clipped noise on the target action (off for DDPG).
      optimizer: the optimiser's direction (Adam's moments); the learning rate is applied from
        :class:`AgentHyperparams` at every step.
      critic_observation_size: the critics' input size when they see another observation than
        the actor (``Transition.critic_obs``, an asymmetric actor-critic); ``None``: ``obs``.
    """

    actor: nn.Module
    critic: nn.Module
    observation_size: int
    action_size: int
    policy_freq: int = 2
    target_smoothing: bool = True
    optimizer: optax.GradientTransformation = ADAM
    critic_observation_size: int | None = None

    @property
    def num_critics(self) -> int:
        return self.critic.num_critics


@struct.dataclass
class AgentHyperparams:
    """The agent's float settings, scalars that may be traced (vmapped in sweeps)."""

    discount: jax.Array
    tau: jax.Array
    actor_lr: jax.Array
    critic_lr: jax.Array
    policy_noise: jax.Array
    noise_clip: jax.Array


def _check_sizes(observation_size: Any, action_size: Any, hidden_sizes: Any) -> None:
    for name, value in (("observation_size", observation_size), ("action_size", action_size)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    hidden = tuple(hidden_sizes or ())
    if not hidden or any(not isinstance(h, int | np.integer) or h <= 0 for h in hidden):
        raise ValueError(f"hidden_sizes must be positive integers, got {hidden_sizes}")


def _check_hyperparams(hp: AgentHyperparams) -> None:
    """Rejects impossible concrete values (traced values are the caller's responsibility)."""
    ranges = {
        "discount": (0.0, 1.0, True),
        "tau": (0.0, 1.0, False),
        "actor_lr": (0.0, np.inf, True),
        "critic_lr": (0.0, np.inf, True),
        "policy_noise": (0.0, np.inf, True),
        "noise_clip": (0.0, np.inf, True),
    }
    for name, (low, high, low_ok) in ranges.items():
        value = getattr(hp, name)
        if isinstance(value, jax.core.Tracer):
            continue
        v = np.asarray(value)
        below = v < low if low_ok else v <= low
        if not np.all(np.isfinite(v)) or np.any(v > high) or np.any(below):
            bound = "[" if low_ok else "("
            raise ValueError(f"{name} must be finite and in {bound}{low}, {high}], got {value}")


def make_spec(
    hidden_sizes: Sequence[int],
    observation_size: int,
    action_size: int,
    *,
    num_critics: int,
    target_smoothing: bool,
    policy_freq: int,
    max_action: Any = 1.0,
    critic_observation_size: int | None = None,
) -> AgentSpec:
    """The static structure of an actor-critic agent (sizes checked, ``ValueError`` if bad).

    ``critic_observation_size``: the critics learn from observations of this size
    (``Transition.critic_obs``) while the actor acts on ``observation_size`` ones; ``None``:
    the critics see the actor's observation.
    """
    _check_sizes(observation_size, action_size, hidden_sizes)
    if critic_observation_size is not None:
        _check_sizes(critic_observation_size, action_size, hidden_sizes)
    if int(policy_freq) < 1:
        raise ValueError(f"policy_freq must be >= 1, got {policy_freq}")
    hidden = tuple(int(h) for h in hidden_sizes)
    return AgentSpec(
        actor=Actor(hidden, int(action_size), max_action),
        critic=CriticEnsemble(hidden, num_critics),
        observation_size=int(observation_size),
        action_size=int(action_size),
        policy_freq=int(policy_freq),
        target_smoothing=target_smoothing,
        critic_observation_size=None if critic_observation_size is None
        else int(critic_observation_size),
    )


def critic_input_size(spec: AgentSpec) -> int:
    """The size of the critics' observation input."""
    return spec.critic_observation_size or spec.observation_size


def hyperparams(config: Any) -> AgentHyperparams:
    """The float settings of a config as :class:`AgentHyperparams` (DDPG: no smoothing noise)."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    hp = AgentHyperparams(
        discount=f32(config.discount),
        tau=f32(config.tau),
        actor_lr=f32(config.actor_lr),
        critic_lr=f32(config.critic_lr),
        policy_noise=f32(getattr(config, "policy_noise", 0.0)),
        noise_clip=f32(getattr(config, "noise_clip", 0.0)),
    )
    _check_hyperparams(hp)
    return hp


def init(spec: AgentSpec, key: PRNGKey) -> AgentState:
    """Fresh networks, targets equal to them, optimiser states, ``step = 0``."""
    actor_key, critic_key = jax.random.split(key)
    obs = jnp.zeros((1, spec.observation_size), jnp.float32)
    critic_obs = jnp.zeros((1, critic_input_size(spec)), jnp.float32)
    action = jnp.zeros((1, spec.action_size), jnp.float32)
    actor_params = spec.actor.init(actor_key, obs)
    critic_params = spec.critic.init(critic_key, critic_obs, action)
    return AgentState(
        actor_params=actor_params,
        critic_params=critic_params,
        target_actor_params=actor_params,
        target_critic_params=critic_params,
        actor_opt_state=spec.optimizer.init(actor_params),
        critic_opt_state=spec.optimizer.init(critic_params),
        step=jnp.zeros((), jnp.int32),
    )


def _descend(
    spec: AgentSpec, params: Params, grads: Params, opt_state: Any, lr: jax.Array
) -> tuple[Params, Any]:
    """One optimiser step: ``params - lr * direction(grads)``."""
    direction, opt_state = spec.optimizer.update(grads, opt_state, params)
    updates = jax.tree.map(lambda d: (-lr).astype(d.dtype) * d, direction)
    return optax.apply_updates(params, updates), opt_state


def critic_step(
    spec: AgentSpec, hp: AgentHyperparams, state: AgentState, batch: Transition, key: PRNGKey
) -> tuple[AgentState, Metrics]:
    """One critic step on the TD target; counts the update in ``state.step``."""
    target = losses.td_target(
        spec, hp, state.target_actor_params, state.target_critic_params, batch, key
    )
    (loss, q), grads = jax.value_and_grad(losses.critic_loss, has_aux=True)(
        state.critic_params, spec, batch, target
    )
    params, opt_state = _descend(spec, state.critic_params, grads, state.critic_opt_state,
                                 hp.critic_lr)  # fmt: skip
    state = state.replace(critic_params=params, critic_opt_state=opt_state, step=state.step + 1)
    return state, {"critic_loss": loss, "q_mean": jnp.mean(q), "target_mean": jnp.mean(target)}


def actor_step(
    spec: AgentSpec, hp: AgentHyperparams, state: AgentState, batch: Transition
) -> tuple[AgentState, jax.Array]:
    """One actor step on the current critic, then Polyak averaging of both targets."""
    loss, grads = jax.value_and_grad(losses.actor_loss)(
        state.actor_params, state.critic_params, spec, batch
    )
    params, opt_state = _descend(spec, state.actor_params, grads, state.actor_opt_state,
                                 hp.actor_lr)  # fmt: skip
    state = state.replace(
        actor_params=params,
        actor_opt_state=opt_state,
        target_actor_params=optax.incremental_update(params, state.target_actor_params, hp.tau),
        target_critic_params=optax.incremental_update(
            state.critic_params, state.target_critic_params, hp.tau
        ),
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
    """Raises ``ValueError`` naming the field when ``batch`` is not ``[batch, ...]``-shaped."""
    o, a = spec.observation_size, spec.action_size
    expected = {"obs": (o,), "action": (a,), "reward": (), "next_obs": (o,), "done": ()}
    if spec.critic_observation_size is not None or batch.critic_obs is not None:
        c = critic_input_size(spec)
        expected.update(critic_obs=(c,), next_critic_obs=(c,))
    rows = jnp.shape(batch.reward)[:1]
    for name, tail in expected.items():
        field = getattr(batch, name)
        shape = None if field is None else tuple(jnp.shape(field))
        if len(rows) != 1 or shape != rows + tail:
            want = f"[batch{''.join(f', {t}' for t in tail)}]"
            has = "is missing" if shape is None else f"has shape {list(shape)}"
            raise ValueError(
                f"Transition.{name} {has}; expected {want} for an agent with observation_size "
                f"{o}, critic observation size {critic_input_size(spec)} and action_size {a} "
                "(a batch, rows first)"
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
    """
    check_batch(spec, batch)
    state, metrics = critic_step(spec, hp, state, batch, key)
    state, loss, updated = delayed_actor_step(spec, hp, state, batch, axis_name)
    return state, {**metrics, "actor_loss": loss, "actor_updated": updated}


def zero_metrics() -> Metrics:
    """The metrics of an update that did not happen: every :data:`METRIC_NAMES` entry 0."""
    return {name: jnp.zeros((), jnp.float32) for name in METRIC_NAMES}


def actor_critic(
    spec: AgentSpec, hp: AgentHyperparams, config: Any = None, axis_name: str | None = None
) -> Agent:
    """The :class:`~td3_jax.types.Agent` bundle of ``spec`` with ``hp`` bound."""
    act = functools.partial(_apply, spec.actor)
    return Agent(
        init=functools.partial(init, spec),
        update=functools.partial(_bound_update, spec, hp, axis_name),
        act=act,
        actor_apply=act,
        critic_apply=functools.partial(_apply, spec.critic),
        config=config,
        spec=spec,
        hyperparams=hp,
    )


def _apply(module: nn.Module, params: Params, *inputs: jax.Array) -> jax.Array:
    return module.apply(params, *inputs)


def _bound_update(spec, hp, axis_name, state, batch, key):
    return update(spec, hp, state, batch, key, axis_name)
