"""MuJoCo Playground DM Control Suite tasks (``playground/NAME``), optional extra.

Loaded with ``impl="jax"`` (MJX in pure JAX) by default; Playground's default ``"warp"`` needs
warp-lang. Install with ``pip install 'td3-jax[playground]'``.
"""

from __future__ import annotations

from td3_jax.envs.base import Environment, from_mjx_style


def _suite():
    try:
        from mujoco_playground import dm_control_suite
    except ImportError as err:  # pragma: no cover - depends on the optional extra
        raise ImportError(
            "playground environments need MuJoCo Playground: pip install 'td3-jax[playground]'"
        ) from err
    return dm_control_suite


def names() -> list[str]:
    """DM Control Suite task names, or an empty list when Playground is not installed."""
    try:
        return sorted(_suite().ALL_ENVS)
    except ImportError:
        return []


def make(name: str, *, backend: str = "jax", episode_length: int | None = None) -> Environment:
    """A Playground DM Control Suite task; its ``done`` is a termination (rare in the suite).

    ``backend``: Playground's ``impl`` (``jax`` or ``warp``); a Brax backend name means jax.
    """
    impl = backend if backend in ("jax", "warp") else "jax"
    suite = _suite()
    config = suite.get_default_config(name)
    env = suite.load(name, config=config, config_overrides={"impl": impl})
    length = int(episode_length or config.episode_length)

    return from_mjx_style(f"playground/{name}", env, length)
