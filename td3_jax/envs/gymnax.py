"""gymnax environments with a continuous (Box) action space, e.g. ``gymnax/Pendulum-v1``."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from td3_jax.common.errors import CustomEnvironmentError
from td3_jax.envs.base import Environment, action_bound

__all__ = ["CONTINUOUS", "from_env", "make", "names", "pendulum_angle"]

CONTINUOUS = ("Pendulum-v1", "MountainCarContinuous-v0")


def names() -> list[str]:
    return list(CONTINUOUS)


def pendulum_angle(state: Any) -> jax.Array:
    """``[1]``: the pendulum's angle (0 upright) of a gymnax Pendulum state, for rendering."""
    return jnp.reshape(state.theta, (1,))


def make(
    name: str, *, backend: str | None = None, episode_length: int | None = None
) -> Environment:
    """The gymnax environment ``name`` (:func:`from_env`); ``backend`` is ignored (gymnax has
    one)."""
    del backend
    import gymnax

    if name not in CONTINUOUS:
        raise ValueError(f"gymnax/{name} is not a continuous-action gymnax environment")
    env, params = gymnax.make(name)
    return from_env(env, params, f"gymnax/{name}", episode_length)


def from_env(env: Any, params: Any, name: str, episode_length: int | None = None) -> Environment:
    """An already-made gymnax ``env`` with its ``params`` as the environment ``name``, driven
    through ``reset_env``/``step_env`` (no gymnax auto-reset); the time limit defaults to
    ``params.max_steps_in_episode``.

    gymnax's ``done`` may mix termination and the time limit; the time-limit part is removed
    here (our wrapper applies the limit itself and treats it as truncation). Raises
    :class:`CustomEnvironmentError` for an environment without a continuous (Box) action space.
    """
    from gymnax.environments import spaces

    space = env.action_space(params)
    if not isinstance(space, spaces.Box):
        raise CustomEnvironmentError(f"{name} has a {type(space).__name__} action space; "
                                     "td3-jax needs continuous (Box) actions")  # fmt: skip
    limit = int(params.max_steps_in_episode)
    action_size = int(np.prod(space.shape))
    obs_size = int(np.prod(env.observation_space(params).shape))

    def reset_fn(key):
        obs, state = env.reset_env(key, params)
        return state, obs.reshape(obs_size)

    def step_fn(state, action, key):
        action = action.reshape(space.shape)
        obs, state, reward, done, _ = env.step_env(key, state, action, params)
        terminated = done & (state.time < limit)
        return state, obs.reshape(obs_size), reward, terminated

    return Environment(
        name=name,
        observation_size=obs_size,
        action_size=action_size,
        episode_length=int(episode_length or limit),
        action_low=action_bound(space.low, action_size),
        action_high=action_bound(space.high, action_size),
        reset_fn=reset_fn,
        step_fn=step_fn,
        qpos_fn=pendulum_angle if env.name == "Pendulum-v1" else None,
    )
