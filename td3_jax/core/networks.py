"""Actor and critic-ensemble networks (flax.linen).

Every network takes ``layer_norm`` (LayerNorm after each hidden Dense, before the ReLU, as
FastTD3 does), ``residual`` (the :class:`ResidualMLP` body, FlashSAC's layout, in place of the
plain :class:`MLP`), the critics also ``feature_norm`` (each hidden layer's output, after the
ReLU, projected onto the sphere of radius ``sqrt(width)``, as SimbaV2/FlashSAC bound their
features; :func:`sphere_features`), and ``dtype`` (the computation dtype of the matmuls: ``None``
computes in the inputs' dtype, float32 here; ``jnp.bfloat16`` runs them in bf16). Parameters
are always float32 and every network's output is float32, so losses and optimiser states stay
in float32.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from td3_jax.common.errors import ConfigError


def sphere_features(x: jax.Array, eps: float = 1e-6) -> jax.Array:
    """``[..., width]`` features scaled to Euclidean norm ``sqrt(width)`` (root mean square 1);
    an all-zero row stays zero. Computed in float32 whatever ``x``'s dtype, returned in it."""
    x32 = x.astype(jnp.float32)
    rms = jnp.sqrt(jnp.mean(jnp.square(x32), axis=-1, keepdims=True))
    return (x32 / (rms + eps)).astype(x.dtype)


class MLP(nn.Module):
    """ReLU multilayer perceptron: ``[..., in] -> [..., out_size]`` (no output activation)."""

    hidden_sizes: Sequence[int]
    out_size: int
    layer_norm: bool = False
    dtype: Any = None
    feature_norm: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden_sizes:
            x = nn.Dense(width, dtype=self.dtype, param_dtype=jnp.float32)(x)
            if self.layer_norm:
                x = nn.LayerNorm(dtype=self.dtype, param_dtype=jnp.float32)(x)
            x = nn.relu(x)
            if self.feature_norm:
                x = sphere_features(x)
        out = nn.Dense(self.out_size, dtype=self.dtype, param_dtype=jnp.float32)(x)
        return out.astype(jnp.float32)


class ResidualMLP(nn.Module):
    """Residual network ``[..., in] -> [..., out_size]`` in FlashSAC's layout, with LayerNorm
    where FlashSAC's blocks have BatchNorm (per sample, so no batch statistics to keep, and
    evaluation computes what training does). FlashSAC also batch-normalises the network's input
    and its input layer has no bias; here the input (observations normalised by the run's
    running statistics with --normalize-obs) goes to a plain Dense layer::

        h = Dense(width)(x)
        h = h + relu(LN(Dense(width)(relu(LN(Dense(expansion * width)(h))))))   # per block
        out = Dense(out_size)(RMSNorm(h))                          # RMSNorm with a learned scale

    ``feature_norm``: each block's output ``h`` is projected onto the sphere of radius
    ``sqrt(width)`` (:func:`sphere_features`). Parameters: ``Dense_0`` (input), then per block
    ``Dense_{2b+1}``, ``LayerNorm_{2b}``, ``Dense_{2b+2}``, ``LayerNorm_{2b+1}``; ``RMSNorm_0``;
    the last ``Dense`` is the output.
    """

    width: int
    blocks: int
    out_size: int
    dtype: Any = None
    feature_norm: bool = False
    expansion: int = 4

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        dense = functools.partial(nn.Dense, dtype=self.dtype, param_dtype=jnp.float32)
        norm = functools.partial(nn.LayerNorm, dtype=self.dtype, param_dtype=jnp.float32)
        h = dense(self.width)(x)
        for _ in range(self.blocks):
            y = nn.relu(norm()(dense(self.expansion * self.width)(h)))
            h = h + nn.relu(norm()(dense(self.width)(y)))
            if self.feature_norm:
                h = sphere_features(h)
        h = nn.RMSNorm(dtype=self.dtype, param_dtype=jnp.float32)(h)
        return dense(self.out_size)(h).astype(jnp.float32)


def residual_layout(hidden_sizes: Sequence[int]) -> tuple[int, int]:
    """``(width, blocks)`` of a :class:`ResidualMLP` given as hidden sizes: one block per
    entry, every entry the width (``256 256``: two blocks of 256); ``ConfigError`` otherwise."""
    sizes = tuple(int(h) for h in hidden_sizes)
    if len(set(sizes)) != 1:
        shown = " ".join(map(str, sizes))
        raise ConfigError("a residual network's hidden sizes are one width, a block each (256 "
                         f"256: two blocks of 256), not {shown or 'none'}")  # fmt: skip
    return sizes[0], len(sizes)


def network_body(hidden_sizes: Sequence[int], out_size: int, layer_norm: bool, dtype: Any,
                 feature_norm: bool, residual: bool) -> nn.Module:  # fmt: skip
    """An actor's or a critic's network ``[..., in] -> [..., out_size]``: a
    :class:`ResidualMLP` laid out by :func:`residual_layout` when ``residual`` (its blocks
    always normalise, so ``layer_norm`` is not used), else the plain :class:`MLP`."""
    if residual:
        width, blocks = residual_layout(hidden_sizes)
        return ResidualMLP(width, blocks, out_size, dtype, feature_norm)
    return MLP(hidden_sizes, out_size, layer_norm, dtype, feature_norm)


class Actor(nn.Module):
    """Deterministic policy ``obs[..., obs_size] -> max_action * tanh(.)[..., action_size]``.

    ``max_action`` is a scalar or a per-dimension ``[action_size]`` array. Environments with
    bounds ``[low, high]`` are rescaled to ``[-1, 1]`` by the environment adapters, so the
    library's default is ``max_action = 1``. ``residual``: the :class:`ResidualMLP` body laid
    out by :func:`residual_layout` (FlashSAC's actor: ``128 128``), else the plain :class:`MLP`.
    """

    hidden_sizes: Sequence[int]
    action_size: int
    max_action: float = 1.0
    layer_norm: bool = False
    dtype: Any = None
    residual: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        body = network_body(self.hidden_sizes, self.action_size, self.layer_norm, self.dtype,
                            False, self.residual)  # fmt: skip
        raw = body(obs)
        return jnp.asarray(self.max_action) * jnp.tanh(raw)


class Critic(nn.Module):
    """One Q-function: ``(obs[..., o], action[..., a]) -> q[...]``."""

    hidden_sizes: Sequence[int]
    layer_norm: bool = False
    dtype: Any = None
    feature_norm: bool = False
    residual: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, action], axis=-1)
        body = network_body(self.hidden_sizes, 1, self.layer_norm, self.dtype,
                           self.feature_norm, self.residual)  # fmt: skip
        return body(x)[..., 0]


class DistributionalCritic(nn.Module):
    """One categorical (C51) Q-function: ``(obs, action) -> logits[..., num_atoms]`` over a
    fixed support of ``num_atoms`` values (the support lives in the loss, not the network)."""

    hidden_sizes: Sequence[int]
    num_atoms: int
    layer_norm: bool = False
    dtype: Any = None
    feature_norm: bool = False
    residual: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, action], axis=-1)
        body = network_body(self.hidden_sizes, self.num_atoms, self.layer_norm, self.dtype,
                           self.feature_norm, self.residual)  # fmt: skip
        return body(x)


def _ensemble(head: type[nn.Module], num_critics: int) -> type[nn.Module]:
    """``head`` with separate parameters per critic stacked along a leading axis, evaluated in
    one vectorised call (``nn.vmap``), not a Python loop."""
    return nn.vmap(
        head,
        variable_axes={"params": 0},
        split_rngs={"params": True},
        in_axes=None,
        out_axes=0,
        axis_size=num_critics,
    )


class CriticEnsemble(nn.Module):
    """``num_critics`` independent critics: ``(obs, action) -> q[num_critics, ...]``, or with
    ``num_atoms > 0`` C51 critics: ``(obs, action) -> logits[num_critics, ..., num_atoms]``."""

    hidden_sizes: Sequence[int]
    num_critics: int = 2
    layer_norm: bool = False
    dtype: Any = None
    num_atoms: int = 0
    feature_norm: bool = False
    residual: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        norms = dict(layer_norm=self.layer_norm, dtype=self.dtype, feature_norm=self.feature_norm,
                     residual=self.residual)  # fmt: skip
        if self.num_atoms:
            heads = _ensemble(DistributionalCritic, self.num_critics)
            return heads(self.hidden_sizes, self.num_atoms, **norms)(obs, action)
        return _ensemble(Critic, self.num_critics)(self.hidden_sizes, **norms)(obs, action)


__all__ = [
    "MLP",
    "Actor",
    "Critic",
    "CriticEnsemble",
    "DistributionalCritic",
    "ResidualMLP",
    "network_body",
    "residual_layout",
    "sphere_features",
]
