"""td3-jax: TD3 and DDPG on thousands of vectorised environments, in compiled JAX programs.

The public, stable functional API::

    import td3_jax as tj
    agent = tj.td3(tj.TD3Config(), observation_size, action_size)
    state = agent.init(key)
    state, metrics = agent.update(state, tj.Transition(obs, action, reward, next_obs, done), key)
    buf = tj.replay.add(tj.replay.init(capacity, example_transition), transitions)
    batch = tj.replay.sample(buf, key, batch_size)

Without JAX importable, the package holds only :mod:`td3_jax.policy_file` (the NumPy-only
loader of exported policies), so an exported policy runs where JAX is not installed.
"""

try:
    import jax  # noqa: F401  (the API below needs it; td3_jax.policy_file does not)
except ImportError:  # pragma: no cover - exercised by a subprocess in tests/test_export.py
    pass
else:
    from td3_jax import noise, replay
    from td3_jax.td3 import DDPGConfig, TD3Config, ddpg, td3
    from td3_jax.types import Agent, AgentState, Transition

__all__ = [
    "Agent",
    "AgentState",
    "DDPGConfig",
    "TD3Config",
    "Transition",
    "ddpg",
    "noise",
    "replay",
    "td3",
]
__version__ = "0.1.0"
