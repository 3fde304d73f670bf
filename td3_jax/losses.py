"""The TD3/DDPG targets and losses as module-level pure functions (brax's ``losses.py`` shape).

Each takes the agent's static :class:`~td3_jax.actor_critic.AgentSpec` (networks, number of critics,
whether targets are smoothed) and its traced :class:`~td3_jax.actor_critic.AgentHyperparams`, so the
same functions serve one agent, a ``vmap`` over seeds and a ``vmap`` over swept settings.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from td3_jax.types import Params, PRNGKey, Transition, critic_observations

if TYPE_CHECKING:  # pragma: no cover
    from td3_jax.actor_critic import AgentHyperparams, AgentSpec


def target_action(
    spec: AgentSpec, hp: AgentHyperparams, actor_params: Params, next_obs: jax.Array, key: PRNGKey
) -> jax.Array:
    """``a' [batch, action_size]``: the target actor's action, smoothed for TD3.

    With smoothing: ``clip(pi'(s') + clip(N(0, policy_noise), -noise_clip, noise_clip),
    -max_action, max_action)``; without (DDPG): ``pi'(s')``.
    """
    action = spec.actor.apply(actor_params, next_obs)
    if not spec.target_smoothing:
        return action
    noise = hp.policy_noise * jax.random.normal(key, action.shape, action.dtype)
    noise = jnp.clip(noise, -hp.noise_clip, hp.noise_clip)
    max_action = jnp.asarray(spec.actor.max_action, action.dtype)
    return jnp.clip(action + noise, -max_action, max_action)


def td_target(
    spec: AgentSpec,
    hp: AgentHyperparams,
    target_actor_params: Params,
    target_critic_params: Params,
    batch: Transition,
    key: PRNGKey,
) -> jax.Array:
    """``y [batch] = r + discount * (1 - done) * min_h Q'_h(s', a')``, without gradient.

    The minimum over the critic heads is TD3's clipped double-Q (one head for DDPG).
    """
    next_action = target_action(spec, hp, target_actor_params, batch.next_obs, key)
    _, next_critic_obs = critic_observations(batch)
    next_q = spec.critic.apply(target_critic_params, next_critic_obs, next_action)
    bootstrap = hp.discount * (1.0 - batch.done) * jnp.min(next_q, axis=0)
    return jax.lax.stop_gradient(batch.reward + bootstrap)


def critic_loss(
    critic_params: Params, spec: AgentSpec, batch: Transition, target: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """``(sum_h mean_b (Q_h(s, a) - y)^2, q [heads, batch])``: each head regresses on ``y``."""
    critic_obs, _ = critic_observations(batch)
    q = spec.critic.apply(critic_params, critic_obs, batch.action)
    loss = jnp.sum(jnp.mean(jnp.square(q - target[None]), axis=-1))
    return loss, q


def actor_loss(
    actor_params: Params, critic_params: Params, spec: AgentSpec, batch: Transition
) -> jax.Array:
    """``-mean_b Q_1(s_c, pi(s))`` (the first critic head) on ``batch`` rows ``[batch, ...]``.

    The actor acts on ``batch.obs``; the critic scores its action on the critic observation
    (:func:`~td3_jax.types.critic_observations`).
    """
    critic_obs, _ = critic_observations(batch)
    action = spec.actor.apply(actor_params, batch.obs)
    q = spec.critic.apply(critic_params, critic_obs, action)
    return -jnp.mean(q[0])
