"""Reward scaling by the running statistics of discounted returns (FlashSAC's and SimbaV2's
reward normalisation), kept in the train state.

Every environment accumulates the discounted return of its episode so far,
``G_t = r_t + discount * G_{t-1}`` (``G`` starts at 0 after an episode ends); the running
variance of every ``G_t`` seen and the largest ``|G_t|`` give the scale

    scale = max(sqrt(var(G) + EPSILON), max|G| / bound),

by which the learner divides its sampled rewards (n-step sums too: the scale is linear). The
critics then learn returns of about unit spread that stay within about ``±bound``, whatever the
task's reward units (a distributional critic's support can be fixed, e.g. ``[-bound, bound]``).
No mean is subtracted: a reward's sign is kept. Evaluation returns are the environment's own.

FlashSAC resets ``G`` with the ``done`` of the same step (the last reward of an episode starts
the next one's sum); here an episode's last reward ends its own sum, as the formula says.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from td3_jax.core import normalization

#: The variance floor of :func:`scale` (the observation normaliser's).
EPSILON = normalization.EPSILON


@struct.dataclass
class ReturnScale:
    """The running return statistics of a run's ``num_envs`` training environments.

    Attributes:
      returns: ``[num_envs]`` discounted return of each environment's episode so far.
      stats: mean, variance and count of every return seen (``[1]`` each).
      max_abs: ``[]`` the largest ``|return|`` seen.
    """

    returns: jax.Array
    stats: normalization.RunningStats
    max_abs: jax.Array


def init(num_envs: int) -> ReturnScale:
    """No returns seen: zero sums, unit variance, count 0 (so :func:`scale` is 1)."""
    return ReturnScale(
        returns=jnp.zeros((num_envs,), jnp.float32),
        stats=normalization.init(1),
        max_abs=jnp.zeros((), jnp.float32),
    )


def update(
    state: ReturnScale, reward: jax.Array, ended: jax.Array, discount: jax.Array
) -> ReturnScale:
    """One vectorised step: ``reward [num_envs]`` added to each discounted sum, every sum
    merged into the statistics, and the sums of environments whose episode ``ended
    [num_envs]`` (terminated or truncated) set back to 0."""
    returns = discount * state.returns + reward.astype(jnp.float32)
    return ReturnScale(
        returns=jnp.where(ended, 0.0, returns),
        stats=normalization.update(state.stats, returns[:, None]),
        max_abs=jnp.maximum(state.max_abs, jnp.max(jnp.abs(returns))),
    )


def scale(state: ReturnScale, bound: jax.Array) -> jax.Array:
    """``max(sqrt(var + EPSILON), max_abs / bound)``: what rewards are divided by (a scalar;
    1 before any return was seen)."""
    spread = jnp.sqrt(state.stats.var[0] + EPSILON)
    return jnp.where(state.stats.count > 0, jnp.maximum(spread, state.max_abs / bound), 1.0)


__all__ = ["EPSILON", "ReturnScale", "init", "scale", "update"]
