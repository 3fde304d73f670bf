"""Pytrees shared by the whole library: transitions, agent state and the agent itself."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import optax
from flax import struct

Params = Any
PRNGKey = jax.Array
Metrics = dict[str, jax.Array]


class Transition(NamedTuple):
    """One environment transition, or a batch of them along leading axes.

    Attributes:
      obs: ``[..., obs_size]`` observation the action was taken in.
      action: ``[..., action_size]`` action taken, in ``[-max_action, max_action]``.
      reward: ``[...]`` reward received.
      next_obs: ``[..., obs_size]`` observation after the step. At an episode end this is the true
        last observation of the episode, never the first observation of the next one.
      done: ``[...]`` 1.0 where the episode *terminated* (no bootstrapping), 0.0 otherwise. A
        time-limit truncation is not a termination: it has ``done = 0`` so the target bootstraps.
      critic_obs: ``[..., critic_obs_size]`` what the critics see in place of ``obs`` (an
        asymmetric actor-critic, e.g. a robot's privileged state), or ``None``: the critics see
        ``obs``.
      next_critic_obs: ``[..., critic_obs_size]`` the same after the step, or ``None``.
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    done: jax.Array
    critic_obs: jax.Array | None = None
    next_critic_obs: jax.Array | None = None


def critic_observations(batch: Transition) -> tuple[jax.Array, jax.Array]:
    """``(s, s')`` as the critics see them: the critic observations when the batch has them."""
    if batch.critic_obs is None:
        return batch.obs, batch.next_obs
    return batch.critic_obs, batch.next_critic_obs


@struct.dataclass
class AgentState:
    """Everything an actor-critic agent learns, as one pytree.

    ``critic_params`` hold all critic heads stacked along a leading axis (2 for TD3, 1 for DDPG).
    ``target_actor_params`` is ``None`` for an agent without a target actor
    (:attr:`td3_jax.core.actor_critic.AgentOptions.target_actor`).
    ``step`` counts the ``update`` calls done so far (an int32 scalar).
    """

    actor_params: Params
    critic_params: Params
    target_actor_params: Params
    target_critic_params: Params
    actor_opt_state: optax.OptState
    critic_opt_state: optax.OptState
    step: jax.Array


class Agent(NamedTuple):
    """An actor-critic algorithm as a bundle of pure functions (the optax shape).

    Attributes:
      init: ``init(key) -> AgentState``; ``key`` is one PRNG key (``jax.random.key(seed)`` or
        ``jax.random.PRNGKey(seed)``), anything else raises ``TypeError``.
      update: ``update(state, batch: Transition, key) -> (state, metrics)``; one gradient step
        on a batch ``[batch_size, ...]``. Pure: jit, vmap and scan it. A batch of other shapes
        raises ``ConfigError`` naming the field, a ``key`` that is no PRNG key ``TypeError``.
      act: ``act(actor_params, obs[..., obs_size]) -> action[..., action_size]``, deterministic;
        observations of another size raise ``ConfigError``.
      actor_apply: ``actor_apply(actor_params, obs) -> action`` (the same function as ``act``).
      critic_apply: ``critic_apply(critic_params, obs[..., o], action[..., a]) -> q[heads, ...]``
        (a distributional critic head's Q-value is its distribution's mean; ``o`` is the
        critic observation size); an ``obs`` or ``action`` of another width, or leading axes
        that differ, raise ``ConfigError`` naming the argument.
      config: the config the agent was built from.
      spec: the agent's static structure (:class:`td3_jax.core.actor_critic.AgentSpec`).
      hyperparams: the float settings bound into ``update``
        (:class:`td3_jax.core.actor_critic.AgentHyperparams`).
    """

    init: Callable[[PRNGKey], AgentState]
    update: Callable[[AgentState, Transition, PRNGKey], tuple[AgentState, Metrics]]
    act: Callable[[Params, jax.Array], jax.Array]
    actor_apply: Callable[[Params, jax.Array], jax.Array]
    critic_apply: Callable[[Params, jax.Array, jax.Array], jax.Array]
    config: Any
    spec: Any = None
    hyperparams: Any = None


__all__ = [
    "Agent",
    "AgentState",
    "Metrics",
    "PRNGKey",
    "Params",
    "Transition",
    "critic_observations",
]
