"""Brax environments (``brax/NAME``), on the MJX backend unless another is asked for."""

from __future__ import annotations

from typing import Any

import jax

from td3_jax import upstream
from td3_jax.envs.base import Environment, from_mjx_style


def names() -> list[str]:
    """The Brax environment names this installation knows."""
    return upstream.brax_env_names()


def pipeline_qpos(state: Any) -> jax.Array:
    """``[nq]`` joint positions of a Brax state (``pipeline_state.q``: MuJoCo's ``qpos`` on
    every Brax backend)."""
    return state.pipeline_state.q


def make(
    name: str, *, backend: str = "mjx", episode_length: int | None = None, **kwargs
) -> Environment:
    """A Brax environment without Brax's own episode/auto-reset wrappers (we add our own);
    ``episode_length`` defaults to Brax's 1000.

    Brax's ``done`` of an unwrapped environment is a true termination (e.g. the ant fell);
    Brax actions are already in ``[-1, 1]``.
    """
    from brax import envs

    env = envs.get_environment(name, backend=backend, **kwargs)

    return from_mjx_style(f"brax/{name}", env, episode_length or 1000,
                          mj_model=env.sys.mj_model, qpos_fn=pipeline_qpos)  # fmt: skip
