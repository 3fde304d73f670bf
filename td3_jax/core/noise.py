"""Exploration noise as pure functions with explicit state and keys.

Both processes act on one environment's action ``[action_size]``; ``jax.vmap`` them over
environments (their states then carry a leading ``num_envs`` axis).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from td3_jax.core.types import PRNGKey


def gaussian(
    key: PRNGKey,
    action: jax.Array,
    expl_noise: float | jax.Array,
    max_action: float | jax.Array = 1.0,
) -> jax.Array:
    """``clip(action + N(0, expl_noise * max_action), -max_action, max_action)`` (TD3's rule).

    ``expl_noise`` may be a scalar or broadcast against ``action`` (e.g. per environment).
    """
    std = jnp.asarray(expl_noise) * jnp.asarray(max_action)
    noisy = action + std * jax.random.normal(key, action.shape, action.dtype)
    return jnp.clip(noisy, -max_action, max_action)


@struct.dataclass
class OUParams:
    """Ornstein-Uhlenbeck parameters (defaults: theta 0.15, sigma 0.3, no decay).

    ``sigma`` decays linearly from ``max_sigma`` to ``min_sigma`` over ``decay_period`` steps.
    """

    mu: float = 0.0
    theta: float = 0.15
    max_sigma: float = 0.3
    min_sigma: float = 0.3
    decay_period: float = 100_000.0


@struct.dataclass
class OUState:
    """The process value ``x [action_size]`` and the step count ``t`` used by the sigma decay."""

    x: jax.Array
    t: jax.Array


def ou_init(action_size: int, params: OUParams = OUParams()) -> OUState:
    """A process at rest at ``mu`` (call again at each episode start)."""
    return OUState(x=jnp.full((action_size,), params.mu, jnp.float32), t=jnp.zeros((), jnp.int32))


def ou_sigma(params: OUParams, t: jax.Array) -> jax.Array:
    """``max_sigma - (max_sigma - min_sigma) * min(1, t / decay_period)``."""
    frac = jnp.minimum(1.0, t / jnp.maximum(params.decay_period, 1.0))
    return params.max_sigma - (params.max_sigma - params.min_sigma) * frac


def ou_step(
    key: PRNGKey, state: OUState, params: OUParams = OUParams()
) -> tuple[OUState, jax.Array]:
    """One step ``x <- x + theta * (mu - x) + sigma(t) * N(0, 1)``; returns ``(state, x)``."""
    sigma = ou_sigma(params, state.t)
    dx = params.theta * (params.mu - state.x) + sigma * jax.random.normal(
        key, state.x.shape, state.x.dtype
    )
    x = state.x + dx
    return OUState(x=x, t=state.t + 1), x


def ou_reset(state: OUState, reset: jax.Array, params: OUParams = OUParams()) -> OUState:
    """Puts ``x`` back to ``mu`` where ``reset`` is true; keeps ``t`` (the decay is global)."""
    return state.replace(x=jnp.where(reset, jnp.full_like(state.x, params.mu), state.x))


def ou_action(
    key: PRNGKey,
    state: OUState,
    action: jax.Array,
    params: OUParams = OUParams(),
    max_action: float | jax.Array = 1.0,
) -> tuple[OUState, jax.Array]:
    """The exploratory action ``clip(action + ou_step(), -max_action, max_action)``."""
    state, x = ou_step(key, state, params)
    return state, jnp.clip(action + x, -max_action, max_action)


__all__ = [
    "OUParams",
    "OUState",
    "gaussian",
    "ou_action",
    "ou_init",
    "ou_reset",
    "ou_sigma",
    "ou_step",
]
