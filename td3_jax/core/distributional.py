"""The categorical (C51) critic's target and loss as module-level pure functions.

A distributional critic head outputs logits ``[..., num_atoms]`` over the fixed support
``z_i = v_min + i * (v_max - v_min) / (num_atoms - 1)``; its Q-value is the mean of that
distribution, ``sum_i softmax(logits)_i z_i``. The target of a transition is TD3's, moved to
distributions (FastTD3, Seo et al. 2025; :func:`td3_jax.core.losses.categorical_target` composes it
from the functions here):

* the target action as for a plain critic (:func:`td3_jax.core.losses.target_action`);
* clipped double-Q per sample: the next-state distribution of the target head with the lower
  mean (the head :func:`td3_jax.core.losses.td_target` would take the minimum of);
* its atoms moved to ``r + discount * (1 - done) * z`` (with an n-step batch, ``reward`` is the
  discounted sum and ``discount * (1 - done)`` is ``discount ** k`` or 0, see
  :mod:`td3_jax.core.n_step`), clamped to ``[v_min, v_max]`` and projected back onto the support
  (:func:`project`);
* each online head minimises its cross-entropy to that one target distribution.

``v_min`` and ``v_max`` are traced (in :class:`~td3_jax.core.actor_critic.AgentHyperparams`, so they
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
      target_z: ``[..., num_atoms]`` where each atom moved to (clamped to ``[v_min, v_max]``),
        nondecreasing along the last axis, as ``r + c * z`` is for any ``c >= 0`` (a C51
        target's moved support; unsorted positions give a wrong result).

    Returns:
      ``[..., num_atoms]``: each moved atom's mass split between its two neighbours on the
      support in proportion to their closeness (all of it on one atom that it lands on
      exactly): moved atom ``j`` at fractional index ``b_j`` with ``l_j = floor(b_j)`` gives
      ``p_j (1 - (b_j - l_j))`` to atom ``l_j`` and ``p_j (b_j - l_j)`` to atom ``l_j + 1``.
      Computed without a floating-point scatter (its order would change the rounding) and
      without the ``[..., atoms, atoms]`` weights of the dense form ``sum_j p_j max(0, 1 -
      |b_j - i|)``: as ``l`` is sorted, the atoms with ``l_j = i`` are a contiguous run, found
      from the prefix sums of the histogram of ``l`` (:func:`_run_starts`), and each run's sum
      is a difference of prefix sums of the masses (:func:`_run_sums`): no ``[..., atoms,
      atoms]`` weight tensor is formed, which makes a large batch's C51 update faster than the
      dense form (``benchmarks/updates.py --projections library einsum`` measures both).
    """
    num_atoms = probs.shape[-1]
    delta = (v_max - v_min) / (num_atoms - 1)
    b = jnp.clip((jnp.clip(target_z, v_min, v_max) - v_min) / delta, 0.0, num_atoms - 1.0)
    lower = jnp.floor(b)
    frac = b - lower
    starts = _run_starts(lower.astype(jnp.int32))
    to_lower = _run_sums(probs * (1.0 - frac), starts)  # [..., i]: from atoms with l_j = i
    to_upper = _run_sums(probs * frac, starts)  # [..., i]: for atom i + 1
    shifted = jnp.concatenate([jnp.zeros_like(to_upper[..., :1]), to_upper[..., :-1]], axis=-1)
    return to_lower + shifted


def _run_starts(lower: jax.Array) -> jax.Array:
    """``[..., atoms + 1]``: for ``i = 0..atoms``, the number of entries of each sorted row of
    ``lower [..., atoms]`` (values in ``[0, atoms)``) below ``i`` (where the run of ``i``
    starts): the prefix sums of each row's histogram, counted by an integer scatter-add (exact,
    so the same in any order; a binary search per atom took 0.25 ms per update of batch 32768
    on an H100)."""
    num_atoms = lower.shape[-1]
    rows = lower.reshape(-1, num_atoms)
    row_index = jnp.arange(rows.shape[0])[:, None]
    counts = jnp.zeros(rows.shape, jnp.int32).at[row_index, rows].add(1)
    starts = jnp.cumsum(counts, axis=-1, dtype=jnp.int32)
    starts = jnp.concatenate([jnp.zeros_like(starts[:, :1]), starts], axis=-1)
    return starts.reshape(*lower.shape[:-1], num_atoms + 1)


def _run_sums(mass: jax.Array, starts: jax.Array) -> jax.Array:
    """``[..., atoms]``: the sums of ``mass [..., atoms]`` over each run ``starts[i] <= j <
    starts[i + 1]`` (differences of its prefix sums); ``starts`` broadcasts to ``mass``'s
    leading axes (one histogram serves every critic head)."""
    prefix = jnp.concatenate([jnp.zeros_like(mass[..., :1]), jnp.cumsum(mass, axis=-1)], axis=-1)
    at = jnp.take_along_axis(prefix, jnp.broadcast_to(starts, prefix.shape), axis=-1)
    return at[..., 1:] - at[..., :-1]


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
