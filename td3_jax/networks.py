"""Actor and critic-ensemble networks (flax.linen)."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


class MLP(nn.Module):
    """ReLU multilayer perceptron: ``[..., in] -> [..., out_size]`` (no output activation)."""

    hidden_sizes: Sequence[int]
    out_size: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden_sizes:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(self.out_size)(x)


class Actor(nn.Module):
    """Deterministic policy ``obs[..., obs_size] -> max_action * tanh(.)[..., action_size]``.

    ``max_action`` is a scalar or a per-dimension ``[action_size]`` array. Environments with
    bounds ``[low, high]`` are rescaled to ``[-1, 1]`` by the environment adapters, so the
    library's default is ``max_action = 1``.
    """

    hidden_sizes: Sequence[int]
    action_size: int
    max_action: float = 1.0

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        raw = MLP(self.hidden_sizes, self.action_size)(obs)
        return jnp.asarray(self.max_action) * jnp.tanh(raw)


class Critic(nn.Module):
    """One Q-function: ``(obs[..., o], action[..., a]) -> q[...]``."""

    hidden_sizes: Sequence[int]

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, action], axis=-1)
        return MLP(self.hidden_sizes, 1)(x)[..., 0]


class CriticEnsemble(nn.Module):
    """``num_critics`` independent Q-functions: ``(obs, action) -> q[num_critics, ...]``.

    The heads have separate parameters stacked along a leading axis and are evaluated with one
    vectorised call (``nn.vmap``), not a Python loop.
    """

    hidden_sizes: Sequence[int]
    num_critics: int = 2

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        heads = nn.vmap(
            Critic,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=self.num_critics,
        )
        return heads(self.hidden_sizes)(obs, action)
