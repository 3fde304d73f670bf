"""Brax environments (``brax/NAME``), on the MJX backend unless another is asked for."""

from __future__ import annotations

from typing import Any

import jax

from td3_jax.common import upstream
from td3_jax.envs.base import Environment, from_mjx_style
from td3_jax.envs.physics import import_mjx_quietly

__all__ = ["from_env", "make", "names", "pipeline_qpos"]


def names() -> list[str]:
    """The Brax environment names this installation knows."""
    import_mjx_quietly()  # (Brax imports MJX, which prints notes where Warp is missing)
    return upstream.brax_env_names()


def pipeline_qpos(state: Any) -> jax.Array:
    """``[nq]`` joint positions of a Brax state (``pipeline_state.q``: MuJoCo's ``qpos`` on
    every Brax backend)."""
    return state.pipeline_state.q


def from_env(env: Any, name: str, episode_length: int | None = None) -> Environment:
    """An already-made Brax ``env`` (without Brax's episode/auto-reset wrappers: td3-jax adds
    its own) as the environment ``name``; ``episode_length`` defaults to Brax's 1000.

    Brax's ``done`` of an unwrapped environment is a true termination (e.g. the ant fell);
    Brax actions are already in ``[-1, 1]``. A pipeline environment (one with a ``sys``) keeps
    its ``MjModel`` and joint positions for rendering.
    """
    pipeline_sys = getattr(env, "sys", None)
    mj_model = getattr(pipeline_sys, "mj_model", None)
    return from_mjx_style(name, env, episode_length or 1000, mj_model=mj_model,
                          qpos_fn=pipeline_qpos if pipeline_sys is not None else None)  # fmt: skip


def make(
    name: str, *, backend: str = "mjx", episode_length: int | None = None, **kwargs
) -> Environment:
    """The Brax environment ``name`` on ``backend`` (:func:`from_env`)."""
    import_mjx_quietly()
    from brax import envs

    env = envs.get_environment(name, backend=backend, **kwargs)
    return from_env(env, f"brax/{name}", episode_length)
