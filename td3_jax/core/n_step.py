"""n-step TD targets folded into ordinary transitions.

A run of ``n`` consecutive steps of one environment becomes one transition whose reward is the
discounted sum of the rewards up to the end of the episode (or ``n`` steps) and whose
``next_obs`` is the observation after the last of those steps. So that the unchanged TD3/DDPG
update (target ``reward + discount * (1 - done) * Q'(next_obs)``) bootstraps with
``discount ** k`` after ``k`` steps, the folded ``done`` is ``1 - discount ** (k - 1) *
(1 - terminated)``: 1 after a termination, 0 for ``k = 1``, in between otherwise. With ``n = 1``
the transition is returned unchanged.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from td3_jax.core.types import Transition


def fold(run: Transition, ended: jax.Array, discount: float | jax.Array) -> Transition:
    """Folds runs of steps into n-step transitions.

    Args:
      run: leaves ``[batch, n, ...]``: ``n`` consecutive steps of one environment per row.
      ended: ``[batch, n]`` true (or 1.0) where the episode ended at that step (terminated or
        truncated); steps after the first end belong to the next episode and are ignored.
      discount: the discount factor (may be traced).

    Returns:
      Transition with leaves ``[batch, ...]``: ``obs``/``action`` of the first step, the
      discounted reward sum, ``next_obs`` and the folded ``done`` of the last step used.
    """
    n = run.reward.shape[1]
    ended = ended.astype(jnp.float32)
    # alive[:, j] = 1 while no step before j ended the episode.
    alive = jnp.cumprod(jnp.concatenate([jnp.ones_like(ended[:, :1]), 1.0 - ended[:, :-1]], 1), 1)
    powers = jnp.asarray(discount, jnp.float32) ** jnp.arange(n, dtype=jnp.float32)
    reward = jnp.sum(alive * powers * run.reward, axis=1)
    last = (jnp.sum(alive, axis=1) - 1).astype(jnp.int32)  # index of the last step used
    pick = jax.vmap(lambda x, i: x[i])
    terminated = pick(run.done, last)
    bootstrap = jnp.asarray(discount, jnp.float32) ** last.astype(jnp.float32) * (1 - terminated)
    return Transition(
        obs=run.obs[:, 0],
        action=run.action[:, 0],
        reward=reward,
        next_obs=pick(run.next_obs, last),
        done=1.0 - bootstrap,
    )


__all__ = [
    "fold",
]
