"""Brax environments (``brax/NAME``), on the MJX backend unless another is asked for."""

from __future__ import annotations

import numpy as np

from td3_jax.envs.base import Environment


def names() -> list[str]:
    """The Brax environment names this installation knows."""
    from brax import envs

    return sorted(envs._envs)  # brax has no public listing; _envs is its registry


def make(name: str, *, backend: str = "mjx", episode_length: int = 1000, **kwargs) -> Environment:
    """A Brax environment without Brax's own episode/auto-reset wrappers (we add our own).

    Brax's ``done`` of an unwrapped environment is a true termination (e.g. the ant fell);
    Brax actions are already in ``[-1, 1]``.
    """
    from brax import envs

    env = envs.get_environment(name, backend=backend, **kwargs)

    def reset_fn(key):
        state = env.reset(key)
        return state, state.obs

    def step_fn(state, action, key):
        del key  # Brax steps are deterministic
        state = env.step(state, action)
        return state, state.obs, state.reward, state.done > 0.5

    return Environment(
        name=f"brax/{name}",
        observation_size=int(env.observation_size),
        action_size=int(env.action_size),
        episode_length=int(episode_length),
        action_low=-np.ones(env.action_size, np.float32),
        action_high=np.ones(env.action_size, np.float32),
        reset_fn=reset_fn,
        step_fn=step_fn,
    )
