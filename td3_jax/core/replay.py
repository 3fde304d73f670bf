"""A fixed-capacity replay ring buffer held as device arrays.

The buffer stores any pytree of transitions; every leaf gets a leading ``capacity`` axis.
``add`` scatters a batch into the ring at ``position`` (wrapping around), so its cost is
proportional to the batch, never to the buffer; donate the buffer to the jitted function that
calls ``add`` and the update happens in place. ``sample`` draws uniformly, with replacement, from
the filled part only. All functions are pure and work under ``jit``, ``vmap`` (one buffer per
seed) and ``scan``.

Edge cases (documented behaviour):

* ``add`` of more transitions than ``capacity`` at once raises ``ConfigError`` (shapes are static,
  so this is known when tracing).
* ``sample`` from an empty buffer raises ``ConfigError`` when the size is known on the host; inside
  a compiled program (where it cannot raise) it returns the zero-filled slot 0. The trainer never
  samples before its warm-up steps have been added.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from td3_jax.common.errors import ConfigError
from td3_jax.core import n_step
from td3_jax.core.types import PRNGKey, Transition


@struct.dataclass
class ReplayBuffer:
    """Ring-buffer state.

    Attributes:
      data: pytree whose leaves are ``[capacity, ...]`` arrays.
      position: int32 scalar, the slot the next transition is written to.
      size: int32 scalar, the number of filled slots (``<= capacity``).
    """

    data: Any
    position: jax.Array
    size: jax.Array

    @property
    def capacity(self) -> int:
        return jax.tree.leaves(self.data)[0].shape[0]


def init(capacity: int, example_transition: Any) -> ReplayBuffer:
    """An empty buffer for ``capacity`` transitions shaped like ``example_transition``.

    Args:
      capacity: number of transitions kept (static, > 0).
      example_transition: one transition (any pytree of arrays), without a batch axis.
    """
    capacity = int(capacity)
    if capacity <= 0:
        raise ConfigError(f"replay capacity must be positive, got {capacity}")
    data = jax.tree.map(
        lambda x: jnp.zeros((capacity, *jnp.shape(x)), jnp.result_type(x)), example_transition
    )
    return ReplayBuffer(data=data, position=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32))


def add(buffer: ReplayBuffer, transitions: Any) -> ReplayBuffer:
    """Writes a batch of transitions (leaves ``[n, ...]``) into the ring, oldest overwritten.

    Cost is O(n): a scatter of ``n`` rows at ``(position + arange(n)) % capacity``.
    """
    _check_rows(buffer, transitions)
    n = jax.tree.leaves(transitions)[0].shape[0]
    capacity = buffer.capacity
    if n > capacity:
        raise ConfigError(
            f"cannot add {n} transitions at once to a replay buffer of capacity {capacity}"
        )
    indices = (buffer.position + jnp.arange(n, dtype=jnp.int32)) % capacity
    data = jax.tree.map(
        lambda store, x: store.at[indices].set(x.astype(store.dtype), unique_indices=True),
        buffer.data,
        transitions,
    )
    return ReplayBuffer(
        data=data,
        position=(buffer.position + n) % capacity,
        size=jnp.minimum(buffer.size + n, capacity),
    )


def _check_rows(buffer: ReplayBuffer, transitions: Any) -> None:
    """``ConfigError`` naming the field unless ``transitions`` is the buffer's structure with one
    leading batch axis of the same size on every leaf."""
    if jax.tree.structure(transitions) != jax.tree.structure(buffer.data):
        raise ConfigError(
            f"added transitions have the structure {jax.tree.structure(transitions)}, the buffer "
            f"holds {jax.tree.structure(buffer.data)}"
        )
    stored = jax.tree_util.tree_leaves_with_path(buffer.data)
    added = jax.tree.leaves(transitions)
    n = jnp.shape(added[0])[0] if jnp.ndim(added[0]) else None
    for (path, store), leaf in zip(stored, added, strict=True):
        shape = tuple(jnp.shape(leaf))
        if n is None or shape != (n, *store.shape[1:]):
            want = "".join(f", {d}" for d in store.shape[1:])
            raise ConfigError(
                f"added transitions{jax.tree_util.keystr(path)} has shape {list(shape)}; "
                f"expected [n{want}] (a batch of rows shaped like the buffer's, the same n "
                "for every field)"
            )


def sample(buffer: ReplayBuffer, key: PRNGKey, batch_size: int) -> Any:
    """``batch_size`` transitions drawn uniformly with replacement from the filled slots.

    Returns a pytree shaped like ``buffer.data`` with leading axis ``batch_size``.

    An empty buffer is a ``ConfigError`` when its size is known here (outside ``jax.jit``).
    Inside a compiled function the size is not known until it runs, and an empty buffer
    gives rows of its initial zeros: sample only once transitions were added (td3-jax's
    own loop adds each iteration's transitions before its updates).
    """
    if not isinstance(buffer.size, jax.core.Tracer) and int(buffer.size) == 0:
        raise ConfigError("cannot sample from an empty replay buffer; add transitions first")
    indices = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree.map(lambda store: store[indices], buffer.data)


def sample_runs(
    buffer: ReplayBuffer, key: PRNGKey, batch_size: int, length: int, stride: int
) -> Any:
    """``batch_size`` runs of ``length`` rows ``i, i + stride, ..., i + (length - 1) * stride``.

    When every :func:`add` writes the same ``stride`` rows (one per environment, in a fixed
    order), row ``i + stride`` holds the step after row ``i`` of the same environment, so a run
    is ``length`` consecutive steps of one environment (for n-step returns). Starts are uniform
    over the rows whose whole run has been written, oldest first; with ``length == 1`` this is
    uniform over the filled slots, like :func:`sample`.

    Returns a pytree shaped like ``buffer.data`` with leading axes ``[batch_size, length]``.
    Too few filled slots are a ``ConfigError`` outside ``jax.jit`` only, as in :func:`sample`.
    """
    span = (length - 1) * stride
    if not isinstance(buffer.size, jax.core.Tracer) and int(buffer.size) <= span:
        raise ConfigError(
            f"runs of {length} rows {stride} apart need more than {span} filled slots, "
            f"the buffer holds {int(buffer.size)}"
        )
    capacity = buffer.capacity
    oldest = (buffer.position - buffer.size) % capacity
    offset = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size - span, 1))
    rows = (oldest + offset[:, None] + stride * jnp.arange(length)) % capacity
    return jax.tree.map(lambda store: store[rows], buffer.data)


# --------------------------------------------------------------------------------------------
# A ring in slices, holding ``(Transition, ended)`` rows, sampled as n-step transitions
# --------------------------------------------------------------------------------------------


def init_slices(capacity: int, shards: int, example_transition: Any) -> ReplayBuffer:
    """``shards`` independent rings of ``capacity / shards`` rows (leaves ``[shards, ...]``).

    Each slice is filled by its own group of environments and gives its share of every batch
    (stratified sampling), so on a mesh whose devices hold whole slices, inserts and samples
    stay on each device.
    """
    if capacity % shards:
        raise ConfigError(f"replay capacity {capacity} is not divisible into {shards} slices")
    one = init(capacity // shards, example_transition)
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (shards, *x.shape)), one)


def add_slices(buffer: ReplayBuffer, transitions: Any) -> ReplayBuffer:
    """Writes ``transitions`` (leaves ``[n, ...]``, ``n`` divisible by the slice count):
    contiguous group ``g`` of ``n / shards`` rows goes to slice ``g``."""
    shards = jax.tree.leaves(buffer.data)[0].shape[0]
    grouped = jax.tree.map(lambda x: x.reshape(shards, -1, *x.shape[1:]), transitions)
    return jax.vmap(add)(buffer, grouped)


def sample_n_step(
    buffer: ReplayBuffer,
    key: PRNGKey,
    batch_size: int,
    steps: int,
    stride: int,
    discount: float | jax.Array,
) -> Transition:
    """``batch_size`` uniform transitions of one slice holding ``(Transition, ended)`` rows,
    each folded over up to ``steps`` steps of its environment (:func:`td3_jax.core.n_step.fold`;
    a run of one step folds to the transition itself). ``stride``: rows per :func:`add`."""
    run, ended = sample_runs(buffer, key, batch_size, steps, stride)
    return n_step.fold(run, ended, discount)


def sample_slices(
    buffer: ReplayBuffer,
    key: PRNGKey,
    batch_size: int,
    steps: int,
    stride: int,
    discount: float | jax.Array,
) -> Transition:
    """A ``[batch_size, ...]`` batch: ``batch_size / shards`` rows of every slice of a buffer
    made by :func:`init_slices`, each an n-step folded transition (see :func:`sample_n_step`)."""
    shards = jax.tree.leaves(buffer.data)[0].shape[0]
    keys = key[None] if shards == 1 else jax.random.split(key, shards)
    sample_one = lambda b, k: sample_n_step(b, k, batch_size // shards, steps, stride, discount)
    rows = jax.vmap(sample_one)(buffer, keys)
    return jax.tree.map(lambda x: x.reshape(batch_size, *x.shape[2:]), rows)


def slice_rows(buffer: ReplayBuffer) -> int:
    """Rows of each slice of a buffer made by :func:`init_slices`, also under leading member
    axes (leaves ``[..., shards, rows, ...]``) and for its shapes (``ShapeDtypeStruct``s)."""
    return jax.tree.leaves(buffer.data)[0].shape[jnp.ndim(buffer.position)]


def resize_slices(buffer: ReplayBuffer, rows: int) -> ReplayBuffer:
    """Every slice of a ring that never wrapped, resized to ``rows`` rows: the same filled rows,
    zeros after them, the next write after the last filled row (``position = size``, 0 when
    full). The result is the buffer a ring of ``rows`` rows would be after the same adds
    (leading member axes kept): a run that ``--resume`` extends grows its ring, one it shortens
    cuts it. A slice with more filled rows than ``rows`` raises ``ConfigError`` where the sizes
    are concrete; under tracing the caller guarantees it (a resume never shortens a run below
    the steps it has taken).
    """
    axis = jnp.ndim(buffer.position)
    added = rows - slice_rows(buffer)
    if added < 0:
        _check_fits(buffer, rows)
        cut = lambda x: jax.lax.slice_in_dim(x, 0, rows, axis=axis)
        return buffer.replace(data=jax.tree.map(cut, buffer.data), position=buffer.size % rows)
    pad = lambda x: jnp.pad(x, [(0, added if i == axis else 0) for i in range(x.ndim)])
    return buffer.replace(data=jax.tree.map(pad, buffer.data), position=buffer.size % rows)


def _check_fits(buffer: ReplayBuffer, rows: int) -> None:
    """``ConfigError`` where a slice holds more filled rows than ``rows`` (nothing to check
    while tracing)."""
    try:
        filled = int(np.max(np.asarray(buffer.size)))
    except jax.errors.TracerArrayConversionError:
        return
    if filled > rows:
        raise ConfigError(f"cannot shrink a replay ring of {slice_rows(buffer)} rows to {rows}: "
                         f"{filled} rows of a slice are filled")  # fmt: skip


__all__ = [
    "ReplayBuffer",
    "add",
    "add_slices",
    "init",
    "init_slices",
    "resize_slices",
    "sample",
    "sample_n_step",
    "sample_runs",
    "sample_slices",
    "slice_rows",
]
