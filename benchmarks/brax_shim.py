"""Puts back the JAX APIs that ``brax.training`` (Brax's PPO and SAC) still calls.

For the benchmarks only: the td3_jax library never imports ``brax.training`` and never needs this.

Newer JAX versions removed APIs that brax 0.14's ``brax.training`` uses. JAX 0.10 already raises
``AttributeError`` for ``jax.device_put_replicated`` (deprecated, then removed), and the GPU
machine's JAX 0.11 likewise; Brax PPO/SAC call it to replicate their train state for
``jax.pmap``. :func:`install` adds, only where JAX lacks them:

* ``jax.device_put_replicated(x, devices)``: stacks every leaf ``len(devices)`` times along a
  new leading axis (``jnp.stack([x] * len(devices))``) and ``jax.device_put``s it sharded along
  that axis, slice i on device i (JAX's documented drop-in replacement). The benchmarks use one
  device, where this is the stacked array on that device; several devices work the same way but
  were only checked on a CPU with forced host devices. The mesh axis is named ``'i'``, Brax's
  pmap axis name, so the arrays look exactly like the pmapped training epoch's own outputs and
  its second call does not compile again (:data:`AXIS_NAME`).
* ``jax.device_put_sharded(shards, devices)``: the same for a list of per-device pytrees
  (Brax does not call it today; shimmed in case a version does).
* ``jax.tree_map``, ``jax.tree_leaves``, ``jax.tree_flatten``, ``jax.tree_unflatten``,
  ``jax.tree_structure``, ``jax.tree_transpose``, ``jax.tree_reduce``: aliases of
  ``jax.tree_util`` (deprecated in JAX 0.4.26, absent from JAX 0.10; brax 0.14 itself already
  uses ``jax.tree_util``).
* ``jax.experimental.pjit`` (the module, imported by ``brax.training.replay_buffers``): a
  stand-in whose ``pjit`` is ``jax.jit``, if importing the real one fails.
* ``jax.pmap``: still present in JAX 0.11 (re-implemented on ``jax.shard_map``); if a later
  version drops it, a single-device stand-in (``jax.jit`` of ``jax.vmap`` with the same axis
  name, so ``psum``/``pmean`` over it still work) that refuses more than one device.

Each shim is installed only when the attribute is missing, so on a JAX that still has them
:func:`install` changes nothing. Call it before importing ``brax.training``.
"""

from __future__ import annotations

import importlib
import sys
import types
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["install", "missing"]

_TREE_ALIASES = (
    "tree_map",
    "tree_leaves",
    "tree_flatten",
    "tree_unflatten",
    "tree_structure",
    "tree_transpose",
    "tree_reduce",
)


def _has(module: Any, name: str) -> bool:
    """``hasattr`` that also treats JAX's deprecation errors (AttributeError) as missing."""
    try:
        getattr(module, name)
    except AttributeError:
        return False
    return True


#: The name of the mesh axis of replicated arrays: brax.training's pmap axis name
#: (``_PMAP_AXIS_NAME = 'i'`` in its PPO, SAC and APG). JAX's pmap (now built on shard_map)
#: returns arrays sharded over a mesh axis named after the pmap's axis; an input placed on a
#: differently named mesh, or on a plain device, makes the first call of a pmapped training
#: epoch trace and compile once more on its second call (seconds of a benchmark's budget; seen
#: with Brax PPO on a CPU).
AXIS_NAME = "i"


def _leading_axis_sharding(devices: Sequence[Any]) -> jax.sharding.NamedSharding:
    """Slice i of the leading axis on device i, as ``jax.pmap(..., axis_name='i')`` returns."""
    mesh = jax.sharding.Mesh(np.array(list(devices)), (AXIS_NAME,))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(AXIS_NAME))


def device_put_replicated(x: Any, devices: Sequence[Any]) -> Any:
    """Each leaf of ``x`` stacked ``len(devices)`` times on a new leading axis, one per device."""
    devices = list(devices)
    if not devices:
        raise ValueError("device_put_replicated needs at least one device")
    where = _leading_axis_sharding(devices)
    return jax.tree_util.tree_map(
        lambda leaf: jax.device_put(jnp.stack([jnp.asarray(leaf)] * len(devices)), where), x
    )


def device_put_sharded(shards: Sequence[Any], devices: Sequence[Any]) -> Any:
    """The pytrees ``shards`` stacked leafwise on a new leading axis, slice i on device i."""
    shards, devices = list(shards), list(devices)
    if len(shards) != len(devices):
        raise ValueError(f"{len(shards)} shards for {len(devices)} devices")
    where = _leading_axis_sharding(devices)
    return jax.tree_util.tree_map(
        lambda *leaves: jax.device_put(jnp.stack([jnp.asarray(v) for v in leaves]), where),
        *shards,
    )


def single_device_pmap(
    fun: Callable | None = None,
    axis_name: Any = None,
    *,
    in_axes: Any = 0,
    out_axes: Any = 0,
    static_broadcasted_argnums: Any = (),
    devices: Any = None,
    backend: Any = None,
    axis_size: int | None = None,
    donate_argnums: Any = (),
) -> Callable:
    """``jax.pmap`` on one device, as ``jit(vmap(fun, axis_name=...))``; used only if pmap is gone.

    Collectives over ``axis_name`` (``psum``, ``pmean``, ``pmin``...) work under ``vmap``. The
    mapped axis must have size 1 (one device), as pmap on one device requires.
    """
    del devices, backend
    if fun is None:
        return lambda f: single_device_pmap(
            f,
            axis_name,
            in_axes=in_axes,
            out_axes=out_axes,
            static_broadcasted_argnums=static_broadcasted_argnums,
            axis_size=axis_size,
            donate_argnums=donate_argnums,
        )
    if static_broadcasted_argnums not in ((), None):
        raise NotImplementedError("the pmap stand-in has no static_broadcasted_argnums")
    if jax.local_device_count() > 1:
        raise RuntimeError("the pmap stand-in of benchmarks/brax_shim.py runs on one device only")
    mapped = jax.jit(
        jax.vmap(fun, in_axes=in_axes, out_axes=out_axes, axis_name=axis_name, axis_size=axis_size),
        donate_argnums=donate_argnums,
    )

    def call(*args):
        axes = in_axes if isinstance(in_axes, (tuple, list)) else (in_axes,) * len(args)
        sizes = {
            np.shape(leaf)[axis]
            for arg, axis in zip(args, axes, strict=False)
            if isinstance(axis, int)
            for leaf in jax.tree_util.tree_leaves(arg)
            if np.ndim(leaf) > axis
        }
        if sizes - {1}:
            raise ValueError(f"pmap over one device needs a mapped axis of size 1, got {sizes}")
        return mapped(*args)

    return call


def _pjit_module() -> types.ModuleType:
    module = types.ModuleType("jax.experimental.pjit")
    module.__doc__ = "Stand-in from benchmarks/brax_shim.py: pjit is jax.jit."

    def pjit(fun, *args, **kwargs):
        return jax.jit(fun, *args, **kwargs)

    module.pjit = pjit
    return module


def missing() -> list[str]:
    """The JAX APIs used by brax.training that this JAX lacks (before :func:`install`)."""
    names = [n for n in ("device_put_replicated", "device_put_sharded", "pmap") if not _has(jax, n)]
    names += [n for n in _TREE_ALIASES if not _has(jax, n)]
    try:
        importlib.import_module("jax.experimental.pjit")
    except ImportError:
        names.append("jax.experimental.pjit")
    return names


def install() -> list[str]:
    """Adds the missing APIs to ``jax`` (a no-op where JAX has them); returns what it added."""
    added = []
    if not _has(jax, "device_put_replicated"):
        jax.device_put_replicated = device_put_replicated
        added.append("device_put_replicated")
    if not _has(jax, "device_put_sharded"):
        jax.device_put_sharded = device_put_sharded
        added.append("device_put_sharded")
    if not _has(jax, "pmap"):
        jax.pmap = single_device_pmap
        added.append("pmap")
    for name in _TREE_ALIASES:
        if not _has(jax, name) and _has(jax.tree_util, name):
            setattr(jax, name, getattr(jax.tree_util, name))
            added.append(name)
    try:
        importlib.import_module("jax.experimental.pjit")
    except ImportError:
        module = _pjit_module()
        sys.modules["jax.experimental.pjit"] = module
        importlib.import_module("jax.experimental").pjit = module
        added.append("jax.experimental.pjit")
    return added
