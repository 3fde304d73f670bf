"""MuJoCo Playground tasks (``playground/NAME``), optional extra: the DM Control Suite here,
the locomotion tasks in :mod:`td3_jax.envs.locomotion`.

Stepped by MuJoCo Warp where it can run (an NVIDIA GPU, ``pip install 'td3-jax[warp]'``), else
by MJX's JAX implementation (:mod:`td3_jax.envs.physics`). Install with
``pip install 'td3-jax[playground]'`` (``[locomotion]`` adds the robots).
"""

from __future__ import annotations

from typing import Any

import jax

from td3_jax.common import upstream
from td3_jax.envs import locomotion, physics
from td3_jax.envs.base import Environment, EnvOptions, from_mjx_style, refuse_locomotion_options

__all__ = ["data_qpos", "from_env", "make", "names"]


def _suite():
    physics.import_mjx_quietly()  # (Playground imports MJX, which prints notes without Warp)
    try:
        return upstream.playground_module("mujoco_playground").dm_control_suite
    except ImportError as err:  # pragma: no cover - depends on the optional extra
        raise ImportError(
            "playground environments need MuJoCo Playground: pip install 'td3-jax[playground]'"
        ) from err


def names() -> list[str]:
    """DM Control Suite and locomotion task names, or an empty list without Playground."""
    try:
        suite = sorted(_suite().ALL_ENVS)
    except ImportError:
        return []
    return suite + locomotion.names()


def data_qpos(state: Any) -> jax.Array:
    """``[nq]`` joint positions of a Playground state (``state.data.qpos``)."""
    return state.data.qpos


def make(
    name: str,
    *,
    backend: str = "jax",
    episode_length: int | None = None,
    options: EnvOptions = EnvOptions(),
) -> Environment:
    """A Playground task. DM Control Suite: a flat observation, ``done`` a termination (rare
    in the suite); the locomotion tasks: :func:`td3_jax.envs.locomotion.make`. The physics is
    ``options.impl`` (:func:`td3_jax.envs.physics.resolve`); ``backend`` is not used.
    """
    del backend  # Brax's backends; Playground's physics is options.impl
    if name in locomotion.names():
        return locomotion.make(name, episode_length=episode_length, options=options)
    refuse_locomotion_options(f"playground/{name}", options)
    impl = physics.resolve(options.impl)
    suite = _suite()
    config = suite.get_default_config(name)
    overrides = {"impl": impl, **locomotion.warp_overrides(config, impl, options)}
    env = suite.load(name, config=config, config_overrides=overrides)
    if impl == "warp":
        locomotion.prepare_warp(env, config, options)
    length = int(episode_length or config.episode_length)
    overflow = locomotion.warp_overflow if impl == "warp" else None
    return from_mjx_style(f"playground/{name}", env, length, mj_model=env.mj_model,
                          qpos_fn=data_qpos, overflow_fn=overflow,
                          per_device=impl == "warp")  # fmt: skip


def from_env(
    env: Any, name: str, episode_length: int | None = None, options: EnvOptions = EnvOptions()
) -> Environment:
    """An already-made Playground ``env`` (an ``MjxEnv`` subclass of your own) as the
    environment ``name`` (:func:`td3_jax.envs.locomotion.from_task`): a flat observation, or a
    dict whose ``options.actor_obs_key`` the actor sees and ``options.critic_obs_key`` the
    critics (an asymmetric actor-critic). ``episode_length`` defaults to the config's
    ``episode_length``, else 1000; the physics is what ``env`` was built with."""
    config = getattr(env, "_config", None)
    length = episode_length or getattr(config, "episode_length", None) or 1000
    warp = getattr(config, "impl", "jax") == "warp"
    return locomotion.from_task(env, name, int(length), options, warp=warp)
