"""Sizes of train states in memory and on disk, and the flag that shrinks one."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def state_bytes(state: Any) -> int:
    """The bytes of every array in ``state`` (arrays or ``ShapeDtypeStruct``s): what a
    checkpoint of it holds, typed PRNG keys counted as their key data."""

    def nbytes(x: Any) -> int:
        if jnp.issubdtype(x.dtype, jax.dtypes.extended):
            x = jax.eval_shape(jax.random.key_data, x)
        return int(math.prod(x.shape)) * np.dtype(x.dtype).itemsize

    return sum(nbytes(x) for x in jax.tree.leaves(state))


def size_text(size: int) -> str:
    """``size`` bytes as text: in GB from 0.1 GB up, else in MB."""
    return f"{size / 1e9:.1f} GB" if size >= 1e8 else f"{size / 1e6:.1f} MB"


def larger_network_advice(agent: Any) -> str:
    """``smaller --critic-hidden-sizes`` where the critics' parameters outweigh the actor's,
    else ``smaller --actor-hidden-sizes`` (``--hidden-sizes`` sets both)."""
    critics = state_bytes(agent.critic_params) > state_bytes(agent.actor_params)
    return (f"smaller --{'critic' if critics else 'actor'}-hidden-sizes (or --hidden-sizes, "
            "which sets both)")  # fmt: skip


__all__ = ["larger_network_advice", "size_text", "state_bytes"]
