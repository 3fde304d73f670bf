"""TD3 and DDPG as pure functions: ``td3(config, obs_size, action_size) -> Agent``.

TD3 (Fujimoto et al. 2018) follows steps 4 to 15 of the seed notes:

* target action ``a' = clip(pi'(s') + clip(N(0, policy_noise), -noise_clip, noise_clip),
  -max_action, max_action)`` (target policy smoothing);
* target ``y = r + discount * (1 - done) * min(Q1'(s', a'), Q2'(s', a'))``, no gradient
  (clipped double-Q);
* critic loss ``MSE(Q1(s, a), y) + MSE(Q2(s, a), y)``, one Adam step;
* every ``policy_freq``-th update (the 2nd, 4th, ... with the default 2): actor loss
  ``-mean Q1(s, pi(s))`` with the freshly updated critic, one Adam step, then Polyak averaging
  ``target <- tau * online + (1 - tau) * target`` of both actor and critic targets.

DDPG (the seed's tutorial, its missing ``done`` mask fixed) is the same machinery with one
critic, no target smoothing and the actor and soft target updates on every step.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from td3_jax.networks import Actor, CriticEnsemble
from td3_jax.types import Agent, AgentState, Metrics, Params, PRNGKey, Transition


@struct.dataclass
class TD3Config:
    """TD3 hyperparameters. Defaults are the TD3 paper's / the seed notes'.

    Float fields may be JAX arrays (so a sweep over them is a ``vmap``); ``policy_freq`` and
    ``hidden_sizes`` set the program's structure and are static.
    """

    discount: float = 0.99
    tau: float = 0.005
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    actor_lr: float = 1e-3
    critic_lr: float = 1e-3
    max_action: Any = 1.0
    policy_freq: int = struct.field(pytree_node=False, default=2)
    hidden_sizes: Sequence[int] = struct.field(pytree_node=False, default=(400, 300))


@struct.dataclass
class DDPGConfig:
    """DDPG hyperparameters. Defaults are the seed tutorial's (Pendulum, 256-256)."""

    discount: float = 0.99
    tau: float = 1e-2
    actor_lr: float = 1e-4
    critic_lr: float = 1e-3
    max_action: Any = 1.0
    hidden_sizes: Sequence[int] = struct.field(pytree_node=False, default=(256, 256))


def td3(
    config: TD3Config, observation_size: int, action_size: int, *, axis_name: str | None = None
) -> Agent:
    """Builds a TD3 agent (two critics, target smoothing, delayed actor and target updates).

    ``axis_name``: when ``update`` runs under ``jax.vmap(..., axis_name=...)`` (one agent per
    seed), the delayed actor update stays a real branch, taken when any agent on that axis is
    due (each agent still only updates on its own schedule), instead of becoming a select that
    computes the actor update on every step.
    """
    _check_common(config, observation_size, action_size)
    if int(config.policy_freq) < 1:
        raise ValueError(f"policy_freq must be >= 1, got {config.policy_freq}")
    return _actor_critic(
        config,
        observation_size,
        action_size,
        num_critics=2,
        policy_noise=config.policy_noise,
        noise_clip=config.noise_clip,
        policy_freq=int(config.policy_freq),
        axis_name=axis_name,
    )


def ddpg(config: DDPGConfig, observation_size: int, action_size: int) -> Agent:
    """Builds a DDPG agent (one critic, no smoothing, actor and targets updated every step)."""
    _check_common(config, observation_size, action_size)
    return _actor_critic(
        config,
        observation_size,
        action_size,
        num_critics=1,
        policy_noise=None,
        noise_clip=None,
        policy_freq=1,
    )


def _check_common(config: Any, observation_size: int, action_size: int) -> None:
    if observation_size <= 0 or action_size <= 0:
        raise ValueError(
            f"observation_size and action_size must be positive, got {observation_size}, "
            f"{action_size}"
        )
    if not config.hidden_sizes or any(int(h) <= 0 for h in config.hidden_sizes):
        raise ValueError(f"hidden_sizes must be positive integers, got {config.hidden_sizes}")


def _actor_critic(
    config: Any,
    observation_size: int,
    action_size: int,
    *,
    num_critics: int,
    policy_noise: Any,
    noise_clip: Any,
    policy_freq: int,
    axis_name: str | None = None,
) -> Agent:
    """The shared TD3/DDPG machinery; ``policy_noise=None`` switches target smoothing off."""
    hidden = tuple(int(h) for h in config.hidden_sizes)
    actor = Actor(hidden, action_size, config.max_action)
    critic = CriticEnsemble(hidden, num_critics)
    actor_opt = optax.adam(config.actor_lr)
    critic_opt = optax.adam(config.critic_lr)
    max_action = jnp.asarray(config.max_action, jnp.float32)

    def actor_apply(actor_params: Params, obs: jax.Array) -> jax.Array:
        return actor.apply(actor_params, obs)

    def critic_apply(critic_params: Params, obs: jax.Array, action: jax.Array) -> jax.Array:
        return critic.apply(critic_params, obs, action)

    def init(key: PRNGKey) -> AgentState:
        actor_key, critic_key = jax.random.split(key)
        obs = jnp.zeros((1, observation_size), jnp.float32)
        action = jnp.zeros((1, action_size), jnp.float32)
        actor_params = actor.init(actor_key, obs)
        critic_params = critic.init(critic_key, obs, action)
        return AgentState(
            actor_params=actor_params,
            critic_params=critic_params,
            target_actor_params=actor_params,
            target_critic_params=critic_params,
            actor_opt_state=actor_opt.init(actor_params),
            critic_opt_state=critic_opt.init(critic_params),
            step=jnp.zeros((), jnp.int32),
        )

    def target_values(state: AgentState, batch: Transition, key: PRNGKey) -> jax.Array:
        next_action = actor_apply(state.target_actor_params, batch.next_obs)
        if policy_noise is not None:
            noise = policy_noise * jax.random.normal(key, next_action.shape, next_action.dtype)
            noise = jnp.clip(noise, -noise_clip, noise_clip)
            next_action = jnp.clip(next_action + noise, -max_action, max_action)
        next_q = critic_apply(state.target_critic_params, batch.next_obs, next_action)
        bootstrap = config.discount * (1.0 - batch.done) * jnp.min(next_q, axis=0)
        return jax.lax.stop_gradient(batch.reward + bootstrap)

    def critic_loss_fn(critic_params: Params, batch: Transition, target: jax.Array):
        q = critic_apply(critic_params, batch.obs, batch.action)  # [heads, batch]
        loss = jnp.sum(jnp.mean(jnp.square(q - target[None]), axis=-1))
        return loss, q

    def actor_loss_fn(actor_params: Params, critic_params: Params, obs: jax.Array):
        q = critic_apply(critic_params, obs, actor_apply(actor_params, obs))
        return -jnp.mean(q[0])

    def update_actor_and_targets(state: AgentState, obs: jax.Array):
        actor_loss, grads = jax.value_and_grad(actor_loss_fn)(
            state.actor_params, state.critic_params, obs
        )
        updates, actor_opt_state = actor_opt.update(
            grads, state.actor_opt_state, state.actor_params
        )
        actor_params = optax.apply_updates(state.actor_params, updates)
        state = state.replace(
            actor_params=actor_params,
            actor_opt_state=actor_opt_state,
            target_actor_params=optax.incremental_update(
                actor_params, state.target_actor_params, config.tau
            ),
            target_critic_params=optax.incremental_update(
                state.critic_params, state.target_critic_params, config.tau
            ),
        )
        return state, actor_loss

    def update(state: AgentState, batch: Transition, key: PRNGKey) -> tuple[AgentState, Metrics]:
        target = target_values(state, batch, key)
        (critic_loss, q), grads = jax.value_and_grad(critic_loss_fn, has_aux=True)(
            state.critic_params, batch, target
        )
        updates, critic_opt_state = critic_opt.update(
            grads, state.critic_opt_state, state.critic_params
        )
        state = state.replace(
            critic_params=optax.apply_updates(state.critic_params, updates),
            critic_opt_state=critic_opt_state,
            step=state.step + 1,
        )
        if policy_freq == 1:
            state, actor_loss = update_actor_and_targets(state, batch.obs)
            actor_updated = jnp.ones((), jnp.float32)
        else:
            due = state.step % policy_freq == 0
            actor_updated = due.astype(jnp.float32)

            def update_due(state, obs):
                new_state, loss = update_actor_and_targets(state, obs)
                if axis_name is None:
                    return new_state, loss
                # The branch runs when any agent on the axis is due; the others keep theirs.
                keep = lambda new, old: jnp.where(due, new, old)
                return jax.tree.map(keep, new_state, state), jnp.where(due, loss, 0.0)

            any_due = due
            if axis_name is not None:
                any_due = jax.lax.psum(due.astype(jnp.int32), axis_name) > 0
            state, actor_loss = jax.lax.cond(
                any_due,
                update_due,
                lambda s, _: (s, jnp.zeros((), jnp.float32)),
                state,
                batch.obs,
            )
        metrics = {
            "critic_loss": critic_loss,
            "actor_loss": actor_loss,  # 0 where the actor was not updated; see actor_updated
            "actor_updated": actor_updated,
            "q_mean": jnp.mean(q),
            "target_mean": jnp.mean(target),
        }
        return state, metrics

    return Agent(
        init=init,
        update=update,
        act=actor_apply,
        actor_apply=actor_apply,
        critic_apply=critic_apply,
        config=config,
    )
