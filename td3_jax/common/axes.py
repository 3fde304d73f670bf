"""Branch conditions shared by the members of a ``jax.vmap`` (seeds, sweep settings).

Under ``jax.vmap``, a ``lax.cond`` whose predicate differs per member becomes a ``select`` that
computes both branches for everyone. When the predicate is first reduced over the vmapped axis
it is the same for every member, and the ``cond`` stays a real branch: taken when *any* member
needs it (members that do not need it keep their values inside the branch).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def any_member(pred: jax.Array, axis_name: str | None) -> jax.Array:
    """``pred`` (a bool scalar) or-reduced over the vmapped axis ``axis_name`` (if any)."""
    if axis_name is None:
        return pred
    return jax.lax.psum(pred.astype(jnp.int32), axis_name) > 0


def max_member(value: jax.Array, axis_name: str | None) -> jax.Array:
    """``value`` (a scalar) max-reduced over the vmapped axis ``axis_name`` (if any)."""
    if axis_name is None:
        return value
    return jax.lax.pmax(value, axis_name)


__all__ = [
    "any_member",
    "max_member",
]
