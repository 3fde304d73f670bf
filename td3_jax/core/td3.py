"""TD3 and DDPG: their configs and thin aliases of the one actor-critic builder
(:func:`td3_jax.core.actor_critic.actor_critic`), in optax's ``alias.py`` style.

TD3 follows Algorithm 1 of Fujimoto, van Hoof and Meger (2018), "Addressing Function
Approximation Error in Actor-Critic Methods" (ICML):

* target action ``a' = clip(pi'(s') + clip(N(0, policy_noise), -noise_clip, noise_clip),
  -max_action, max_action)`` (target policy smoothing);
* target ``y = r + discount * (1 - done) * min(Q1'(s', a'), Q2'(s', a'))``, no gradient
  (clipped double-Q);
* critic loss ``MSE(Q1(s, a), y) + MSE(Q2(s, a), y)``, one Adam step;
* every ``policy_freq``-th update (the 2nd, 4th, ... with the default 2): actor loss
  ``-mean Q1(s, pi(s))`` with the freshly updated critic, one Adam step, then Polyak averaging
  ``target <- tau * online + (1 - tau) * target`` of both actor and critic targets.

DDPG (Lillicrap et al. 2016, "Continuous control with deep reinforcement learning", ICLR),
with the target masked by ``1 - done`` at terminations, is the same machinery with one critic,
no target smoothing and the actor and soft target updates on every step.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from flax import struct

from td3_jax.common.keywords import keywords_named
from td3_jax.core.actor_critic import actor_critic, hyperparams, make_spec
from td3_jax.core.types import Agent


@keywords_named
@struct.dataclass
class TD3Config:
    """TD3 hyperparameters. Defaults are the TD3 paper's.

    Float fields may be JAX arrays (so a sweep over them is a ``vmap``); ``policy_freq`` and
    ``hidden_sizes`` set the program's structure and are static.
    """

    discount: float = 0.99
    tau: float = 0.005
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    actor_lr: float = 1e-3
    critic_lr: float = 1e-3
    max_action: Any = 1.0
    policy_freq: int = struct.field(pytree_node=False, default=2)
    hidden_sizes: Sequence[int] = struct.field(pytree_node=False, default=(400, 300))


@keywords_named
@struct.dataclass
class DDPGConfig:
    """DDPG hyperparameters. Defaults suit Pendulum (256-256 networks)."""

    discount: float = 0.99
    tau: float = 1e-2
    actor_lr: float = 1e-4
    critic_lr: float = 1e-3
    max_action: Any = 1.0
    hidden_sizes: Sequence[int] = struct.field(pytree_node=False, default=(256, 256))


def td3(
    config: TD3Config,
    observation_size: int,
    action_size: int,
    critic_obs_size: int | None = None,
    *,
    axis_name: str | None = None,
) -> Agent:
    """Builds a TD3 agent (two critics, target smoothing, delayed actor and target updates).

    ``critic_obs_size``: an asymmetric actor-critic; the critics learn from
    ``Transition.critic_obs [batch, critic_obs_size]`` (e.g. a robot's privileged state) while
    the actor acts on ``obs [batch, observation_size]``. ``None``: the critics see ``obs``.

    ``axis_name``: when ``update`` runs under ``jax.vmap(..., axis_name=...)`` (one agent per
    seed), the delayed actor update stays a real branch, taken when any agent on that axis is
    due (each agent still only updates on its own schedule), instead of becoming a select that
    computes the actor update on every step.
    """
    _check_config(config, TD3Config, "td3", "ddpg")
    spec = make_spec(config.hidden_sizes, observation_size, action_size, num_critics=2,
                     target_smoothing=True, policy_freq=config.policy_freq,
                     max_action=config.max_action,
                     critic_observation_size=critic_obs_size)  # fmt: skip
    return actor_critic(spec, hyperparams(config), config, axis_name)


def ddpg(
    config: DDPGConfig, observation_size: int, action_size: int, critic_obs_size: int | None = None
) -> Agent:
    """Builds a DDPG agent (one critic, no smoothing, actor and targets updated every step);
    ``critic_obs_size`` as for :func:`td3`."""
    _check_config(config, DDPGConfig, "ddpg", "td3")
    spec = make_spec(config.hidden_sizes, observation_size, action_size, num_critics=1,
                     target_smoothing=False, policy_freq=1, max_action=config.max_action,
                     critic_observation_size=critic_obs_size)  # fmt: skip
    return actor_critic(spec, hyperparams(config), config)


def _check_config(config: Any, expected: type, builder: str, other: str) -> None:
    """A ``TypeError`` naming the right builder when ``config`` is not an ``expected``."""
    if not isinstance(config, expected):
        hint = f"; tj.{other} takes a {type(config).__name__}" if (
            type(config).__name__ in ("TD3Config", "DDPGConfig")) else ""  # fmt: skip
        raise TypeError(f"tj.{builder} takes a {expected.__name__}, got "
                        f"{type(config).__name__}{hint}")  # fmt: skip


__all__ = [
    "DDPGConfig",
    "TD3Config",
    "ddpg",
    "td3",
]
