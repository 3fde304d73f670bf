"""The categorical (C51) critic's target and loss as module-level pure functions.

A distributional critic head outputs logits ``[..., num_atoms]`` over the fixed support
``z_i = v_min + i * (v_max - v_min) / (num_atoms - 1)``; its Q-value is the mean of that
distribution, ``sum_i softmax(logits)_i z_i``. The target of a transition is TD3's, moved to
distributions (FastTD3, Seo et al. 2025; :func:`td3_jax.losses.categorical_target` composes it
from the functions here):

* the target action as for a plain critic (:func:`td3_jax.losses.target_action`);
* clipped double-Q per sample: the next-state distribution of the target head with the lower
  mean (the head :func:`td3_jax.losses.td_target` would take the minimum of);
* its atoms moved to ``r + discount * (1 - done) * z`` (with an n-step batch, ``reward`` is the
  discounted sum and ``discount * (1 - done)`` is ``discount ** k`` or 0, see
  :mod:`td3_jax.n_step`), clamped to ``[v_min, v_max]`` and projected back onto the support
  (:func:`project`);
* each online head minimises its cross-entropy to that one target distribution.

``v_min`` and ``v_max`` are traced (in :class:`~td3_jax.actor_critic.AgentHyperparams`, so they
can be swept); ``num_atoms`` is static (the networks' output size).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def support(num_atoms: int, v_min: jax.Array, v_max: jax.Array) -> jax.Array:
    """``z [num_atoms]``: ``num_atoms`` evenly spaced values from ``v_min`` to ``v_max``."""
    fraction = jnp.arange(num_atoms, dtype=jnp.float32) / (num_atoms - 1)
    return v_min + (v_max - v_min) * fraction


def mean_value(logits: jax.Array, z: jax.Array) -> jax.Array:
    """``[...]``: the mean ``sum_i softmax(logits)_i z_i`` of distributions ``[..., atoms]``."""
    return jnp.sum(jax.nn.softmax(logits, axis=-1) * z, axis=-1)


def project(probs: jax.Array, target_z: jax.Array, v_min: jax.Array, v_max: jax.Array) -> jax.Array:
    """Projects distributions onto the support of ``num_atoms`` atoms in ``[v_min, v_max]``.

    Args:
      probs: ``[..., num_atoms]`` probabilities of the moved atoms.
      target_z: ``[..., num_atoms]`` where each atom moved to (clamped to ``[v_min, v_max]``).

    Returns:
      ``[..., num_atoms]``: each moved atom's mass split between its two neighbours on the
      support in proportion to their closeness (all of it on one atom that it lands on
      exactly), i.e. atom ``i`` receives ``p_j * max(0, 1 - |b_j - i|)`` from moved atom ``j``
      at fractional index ``b_j``. Written as that dense sum (no scatter), which XLA fuses.
    """
    num_atoms = probs.shape[-1]
    delta = (v_max - v_min) / (num_atoms - 1)
    b = (jnp.clip(target_z, v_min, v_max) - v_min) / delta
    atoms = jnp.arange(num_atoms, dtype=b.dtype)
    weights = jnp.clip(1.0 - jnp.abs(b[..., :, None] - atoms), 0.0, 1.0)  # [..., j, i]
    return jnp.einsum("...j,...ji->...i", probs, weights)


def lower_mean_head(probs: jax.Array, z: jax.Array) -> jax.Array:
    """``[batch, atoms]``: per sample, the distribution of the head (of ``probs [heads, batch,
    atoms]``) with the lower mean (the first head on ties)."""
    means = jnp.sum(probs * z, axis=-1)  # [heads, batch]
    lower = jnp.argmin(means, axis=0)
    return jnp.take_along_axis(probs, lower[None, :, None], axis=0)[0]


def cross_entropy(target: jax.Array, logits: jax.Array) -> jax.Array:
    """``[...]``: ``-sum_i target_i log softmax(logits)_i`` over the last axis (atoms)."""
    return -jnp.sum(target * jax.nn.log_softmax(logits, axis=-1), axis=-1)


__all__ = [
    "cross_entropy",
    "lower_mean_head",
    "mean_value",
    "project",
    "support",
]
