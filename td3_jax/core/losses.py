"""The TD3/DDPG targets and losses as module-level pure functions (brax's ``losses.py`` shape).

Plain critics regress on the scalar TD target (:func:`td_target`, :func:`critic_loss`);
distributional (C51) critics on a projected target distribution (:func:`categorical_target`,
:func:`categorical_loss`, built from :mod:`td3_jax.core.distributional`). The actor loss
(:func:`actor_loss`) works with both through :func:`q_values`.

Each takes the agent's static :class:`~td3_jax.core.agent_spec.AgentSpec` (networks, number of
critics, whether targets are smoothed) and its traced
:class:`~td3_jax.core.agent_spec.AgentHyperparams`, so the same functions serve one agent, a
``vmap`` over seeds and a ``vmap`` over swept settings.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from td3_jax.common.errors import ConfigError
from td3_jax.core import distributional
from td3_jax.core.types import Params, PRNGKey, Transition, critic_observations

if TYPE_CHECKING:  # pragma: no cover
    from td3_jax.core.agent_spec import AgentHyperparams, AgentSpec


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


def next_critic_output(
    spec: AgentSpec,
    hp: AgentHyperparams,
    target_actor_params: Params,
    target_critic_params: Params,
    batch: Transition,
    key: PRNGKey,
) -> jax.Array:
    """The target critics on ``(s', a')``, ``a'`` from :func:`target_action`: ``q [heads,
    batch]`` (C51: ``logits [heads, batch, atoms]``)."""
    next_action = target_action(spec, hp, target_actor_params, batch.next_obs, key)
    _, next_critic_obs = critic_observations(batch)
    return spec.critic.apply(target_critic_params, next_critic_obs, next_action)


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
    ``target_actor_params``: the actor that picks ``a'`` (the online actor's parameters when
    the agent has no target actor).
    """
    next_q = next_critic_output(spec, hp, target_actor_params, target_critic_params, batch, key)
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


def categorical_target(
    spec: AgentSpec,
    hp: AgentHyperparams,
    target_actor_params: Params,
    target_critic_params: Params,
    batch: Transition,
    key: PRNGKey,
) -> jax.Array:
    """``[batch, num_atoms]`` C51 target probabilities, without gradient.

    The next-state distribution of the target head with the lower mean (per sample), its atoms
    moved to ``r + discount * (1 - done) * z``, clamped to ``[v_min, v_max]`` and projected
    onto the support (:func:`td3_jax.core.distributional.project`). Which head: the lower mean of
    the unprojected distributions (``c51_target_head="unprojected"``), or every head projected
    first and the lower mean of the projected ones (``"projected"``, FastTD3). With an n-step
    batch ``reward`` is the discounted sum and ``discount * (1 - done) = discount ** k`` (or
    0), as in :func:`td_target`.
    """
    logits = next_critic_output(spec, hp, target_actor_params, target_critic_params, batch, key)
    z = distributional.support(logits.shape[-1], hp.v_min, hp.v_max)
    probs = jax.nn.softmax(logits, axis=-1)  # [heads, batch, atoms]
    bootstrap = hp.discount * (1.0 - batch.done)
    target_z = batch.reward[:, None] + bootstrap[:, None] * z
    if spec.options.c51_target_head == "projected":
        projected = distributional.project(probs, target_z, hp.v_min, hp.v_max)
        return jax.lax.stop_gradient(distributional.lower_mean_head(projected, z))
    chosen = distributional.lower_mean_head(probs, z)
    return jax.lax.stop_gradient(distributional.project(chosen, target_z, hp.v_min, hp.v_max))


def categorical_loss(
    critic_params: Params, spec: AgentSpec, batch: Transition, target: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """``(sum_h mean_b CE_h, logits [heads, batch, atoms])``: every head's cross-entropy to the
    one target distribution ``[batch, atoms]`` (:func:`categorical_target`)."""
    critic_obs, _ = critic_observations(batch)
    logits = spec.critic.apply(critic_params, critic_obs, batch.action)
    return jnp.sum(jnp.mean(distributional.cross_entropy(target[None], logits), axis=-1)), logits


def q_values(
    spec: AgentSpec, hp: AgentHyperparams, critic_params: Params, obs: jax.Array,
    action: jax.Array,
) -> jax.Array:  # fmt: skip
    """``q [heads, ...]``: every critic head's Q-value (a distributional head's mean)."""
    out = spec.critic.apply(critic_params, obs, action)
    if not spec.distributional:
        return out
    return distributional.mean_value(out, distributional.support(out.shape[-1], hp.v_min,
                                                                 hp.v_max))  # fmt: skip


def reduce_heads(q: jax.Array, how: str) -> jax.Array:
    """``[...]`` from ``q [heads, ...]``: ``first`` (head 0, the TD3 paper's actor), ``min``
    (the lower head per sample, FastTD3's) or ``mean`` (the heads' mean)."""
    if how == "first":
        return q[0]
    if how == "min":
        return jnp.min(q, axis=0)
    if how == "mean":
        return jnp.mean(q, axis=0)
    raise ConfigError(f"unknown actor_q {how!r}; choose first, min or mean")


def actor_loss(
    actor_params: Params,
    critic_params: Params,
    spec: AgentSpec,
    hp: AgentHyperparams,
    batch: Transition,
) -> jax.Array:
    """``-mean_b Q(s_c, pi(s))`` on ``batch`` rows ``[batch, ...]``, ``Q`` the critic heads
    reduced by ``spec.options.actor_q`` (:func:`reduce_heads`; default the first head).

    The actor acts on ``batch.obs``; the critic scores its action on the critic observation
    (:func:`~td3_jax.core.types.critic_observations`).
    """
    critic_obs, _ = critic_observations(batch)
    action = spec.actor.apply(actor_params, batch.obs)
    q = q_values(spec, hp, critic_params, critic_obs, action)
    return -jnp.mean(reduce_heads(q, spec.options.actor_q))


__all__ = [
    "actor_loss",
    "categorical_loss",
    "categorical_target",
    "critic_loss",
    "next_critic_output",
    "q_values",
    "reduce_heads",
    "target_action",
    "td_target",
]
