"""Running observation statistics that travel inside the train state."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

#: The variance floor and the clip of :func:`normalize` (exported policies use the same).
EPSILON = 1e-8
CLIP = 10.0


@struct.dataclass
class RunningStats:
    """Mean and variance of every observation seen so far (``[obs_size]`` each)."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array


def init(size: int) -> RunningStats:
    return RunningStats(
        mean=jnp.zeros((size,), jnp.float32),
        var=jnp.ones((size,), jnp.float32),
        count=jnp.zeros((), jnp.float32),
    )


def update(stats: RunningStats, batch: jax.Array) -> RunningStats:
    """Merges a batch ``[n, size]`` into the statistics (Chan et al.'s parallel update)."""
    n = jnp.asarray(batch.shape[0], jnp.float32)
    batch_mean = jnp.mean(batch, axis=0)
    batch_var = jnp.var(batch, axis=0)
    total = stats.count + n
    delta = batch_mean - stats.mean
    mean = stats.mean + delta * n / total
    m2 = stats.var * stats.count + batch_var * n + jnp.square(delta) * stats.count * n / total
    return RunningStats(mean=mean, var=m2 / total, count=total)


def normalize(stats: RunningStats, obs: jax.Array, clip: float = CLIP) -> jax.Array:
    """``clip((obs - mean) / sqrt(var + EPSILON), -clip, clip)``; identity before any update."""
    normalized = (obs - stats.mean) / jnp.sqrt(stats.var + EPSILON)
    normalized = jnp.clip(normalized, -clip, clip)
    return jnp.where(stats.count > 0, normalized, obs)


__all__ = [
    "RunningStats",
    "init",
    "normalize",
    "update",
]
