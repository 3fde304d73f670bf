"""An environment batch split over devices, each device stepping its own environments.

XLA splits a batched computation over the devices of a mesh by itself (GSPMD) when it can see
inside it: JAX physics (MJX, Brax, gymnax) needs nothing more. MuJoCo Warp's physics is a call
XLA cannot look into, so it cannot split it. :func:`over_devices` runs every batched physics
call of such an environment (:attr:`~td3_jax.envs.base.Environment.per_device`) under
``jax.shard_map``: each device resets and steps its own contiguous block of the batch, the
block the train state holds on that device, with no traffic between devices.

MuJoCo Warp keeps a few buffers once for all the environments stepped together, without a
batch axis (its contact buffer and counters, named by MJX: :func:`warp_shared_leaf`). Each
device keeps its own copy, sized as on one device; they are scratch space that every step fills
before it reads them, so the state keeps one shape whatever the device count (a checkpoint
written on two devices restores on one), and what a device's copy holds between steps is never
read.

XLA's Shardy partitioner crashed the process (a segmentation fault) compiling Warp's calls under
``shard_map`` on two H200 GPUs (jax 0.11.2), where GSPMD compiles them: an environment split by
:func:`over_devices` turns Shardy off for the process (:func:`use_gspmd`), unless
``JAX_USE_SHARDY_PARTITIONER`` asks for it.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
from collections.abc import Callable
from typing import Any

import jax
from jax.sharding import Mesh, PartitionSpec

from td3_jax.common import runtime, upstream
from td3_jax.common.errors import ConfigError
from td3_jax.envs.base import Environment

__all__ = ["members_map", "over_devices", "split_call", "use_gspmd", "warp_shared_leaf"]


def over_devices(env: Environment, mesh: Mesh, axis: str = "data") -> Environment:
    """``env`` with its batched physics run on each device of ``mesh`` (axis ``axis``) apart,
    where it needs it (:attr:`~td3_jax.envs.base.Environment.per_device`: MuJoCo Warp's) and
    the mesh has more than one device; otherwise ``env`` itself. Batches must divide evenly
    over the devices (:class:`~td3_jax.common.errors.ConfigError` at trace time otherwise).

    A split turns JAX's Shardy partitioner off for the rest of the process
    (``jax_use_shardy_partitioner``; :func:`use_gspmd`): every program compiled afterwards,
    yours included, uses GSPMD, and a function exported with Shardy on cannot be called in that
    process. ``JAX_USE_SHARDY_PARTITIONER=true`` in the environment keeps Shardy (a warning)."""
    if not env.per_device or mesh.shape[axis] == 1:
        return env
    use_gspmd()
    split = functools.partial(split_call, mesh=mesh, axis=axis, shared=warp_shared_leaf())
    return dataclasses.replace(env, batch_map=split)


#: JAX's environment variable for its partitioner: where it asks for Shardy, it is kept.
SHARDY_VARIABLE = "JAX_USE_SHARDY_PARTITIONER"


def use_gspmd() -> None:
    """Turns JAX's Shardy partitioner off for the whole process (``jax_use_shardy_partitioner``;
    read by every later lowering and compile, on every thread), so that programs holding
    :func:`split_call` compile with GSPMD (see the module's docstring); where
    :data:`SHARDY_VARIABLE` asks for Shardy, keeps it and warns once (the first process)."""
    if not jax.config.jax_use_shardy_partitioner:
        return
    if runtime.env_switch(SHARDY_VARIABLE):
        _warn_shardy_kept()
        return
    jax.config.update("jax_use_shardy_partitioner", False)


@functools.cache
def _warn_shardy_kept() -> None:
    """The warning of :func:`use_gspmd`, said once a process, by the first process only."""
    if jax.process_index() == 0:
        print(f"td3-jax: warning: {SHARDY_VARIABLE}={os.environ[SHARDY_VARIABLE]} keeps Shardy "
              "for MuJoCo Warp split over several devices, whose compile crashed the process on "
              "two GPUs (jax 0.11.2); unset it to compile with GSPMD", file=sys.stderr)  # fmt: skip


def warp_shared_leaf() -> Callable[[Any], bool]:
    """``shared(path) -> bool``: whether the leaf at ``path`` (a key path of a Playground state
    on Warp) is one of the buffers MuJoCo Warp keeps once for a batch, without a batch axis
    (``data._impl.NAME``, NAME one of MJX's ``DATA_NON_VMAP``)."""
    names = upstream.warp_shared_data_fields()

    def shared(path: Any) -> bool:
        keys = [getattr(k, "name", getattr(k, "key", None)) for k in path]
        return len(keys) >= 2 and keys[-2] == "_impl" and keys[-1] in names

    return shared


def split_call(batched_fn: Callable, size: int, *, mesh: Mesh, axis: str = "data",
               shared: Callable[[Any], bool] = lambda path: False, lead: int = 0
               ) -> Callable:  # fmt: skip
    """``batched_fn`` (a function over a batch of ``size`` environments: every argument and
    result leaf ``[*L, size, ...]``, ``L`` the ``lead`` leading axes, except those
    ``shared(path)`` names, which have neither) run under ``jax.shard_map``: batched leaves
    split along their batch axis over ``axis``, one block per device, shared ones given whole
    to every device; each device's results are its block of the batch and its own copy of the
    shared leaves (see the module's docstring).

    Under ``jax.vmap`` (several seeds or sweep members) the call is not vmapped around the
    ``shard_map``, which MuJoCo Warp's calls do not survive (their lowered program keeps
    values of another trace); the vmap moves inside it instead (:func:`_members_rule`).
    """
    devices = mesh.shape[axis]
    if size % devices:
        raise ConfigError(f"{size} environments cannot be split evenly over {devices} devices: "
                          f"use a number of environments divisible by {devices}")  # fmt: skip

    @jax.custom_batching.custom_vmap
    def call(*args: Any) -> Any:
        in_specs = _specs(args, axis, shared, lead)
        local = jax.tree.map(lambda x, spec: _local(x, spec, devices, lead), args, in_specs)
        out_specs = _specs(jax.eval_shape(batched_fn, *local), axis, shared, lead)
        run = jax.shard_map(batched_fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs,
                            check_vma=False)  # (Warp's calls have no replication rule)
        return run(*args)

    call.def_vmap(functools.partial(_members_rule, batched_fn, size, mesh, axis, shared, lead))
    return call


def _members_rule(batched_fn: Callable, size: int, mesh: Mesh, axis: str,
                  shared: Callable[[Any], bool], lead: int, axis_size: int, in_batched: Any,
                  *args: Any) -> tuple[Any, Any]:  # fmt: skip
    """:func:`split_call`'s ``vmap`` rule: :func:`split_call` of :func:`members_map` of
    ``batched_fn``, one more leading axis on every leaf but the shared ones (a leaf the vmap
    leaves unbatched is repeated for each member), which stay one buffer for every member, as
    MuJoCo Warp keeps them. A shared leaf that differs between members raises ValueError."""
    leaves, tree = jax.tree_util.tree_flatten_with_path(args)
    batched = jax.tree.leaves(tuple(in_batched))
    for (path, _), is_batched in zip(leaves, batched, strict=True):
        if is_batched and shared(path):
            raise ValueError(f"{jax.tree_util.keystr(path)} is kept once for all environments "
                             "but differs between members")  # fmt: skip
    args = tree.unflatten([
        x if is_batched or shared(path) else _repeated(x, axis_size)
        for (path, x), is_batched in zip(leaves, batched, strict=True)])  # fmt: skip
    inner = split_call(members_map(batched_fn, shared), size, mesh=mesh, axis=axis,
                       shared=shared, lead=lead + 1)  # fmt: skip
    out = inner(*args)
    return out, jax.tree_util.tree_map_with_path(lambda path, _: not shared(path), out)


def members_map(fn: Callable, shared: Callable[[Any], bool]) -> Callable:
    """``jax.vmap(fn)`` over a leading members axis of every leaf except those ``shared(path)``
    names, which every member uses as they are, in its arguments and in its results (as
    MuJoCo Warp keeps them: one buffer for all the worlds it steps together)."""

    def mapped(*args: Any) -> Any:
        (own, common), kept = _parted(args, shared)
        tree = jax.tree.structure(args)
        out_tree: list = []

        def one(own: list, common: list) -> tuple[list, list]:
            out = fn(*tree.unflatten(_joined(kept, own, common)))
            parts, out_kept = _parted(out, shared)
            out_tree[:] = [jax.tree.structure(out), out_kept]
            return parts

        out_own, out_common = jax.vmap(one, in_axes=(0, None), out_axes=(0, None))(own, common)
        structure, out_kept = out_tree
        return structure.unflatten(_joined(out_kept, out_own, out_common))

    return mapped


def _parted(tree: Any, shared: Callable[[Any], bool]) -> tuple[tuple[list, list], list[bool]]:
    """``((own, common), kept)``: ``tree``'s leaves that ``shared`` does not name and those it
    names, in order, and which of its leaves it names."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    kept = [shared(path) for path, _ in leaves]
    own = [x for (_, x), k in zip(leaves, kept, strict=True) if not k]
    common = [x for (_, x), k in zip(leaves, kept, strict=True) if k]
    return (own, common), kept


def _joined(kept: list[bool], own: list, common: list) -> list:
    """The leaves :func:`_parted` separated, back in their order."""
    own_it, common_it = iter(own), iter(common)
    return [next(common_it) if k else next(own_it) for k in kept]


def _repeated(x: Any, count: int) -> jax.Array:
    """``x`` repeated ``count`` times along a new leading axis."""
    return jax.numpy.broadcast_to(x, (count, *jax.numpy.shape(x)))


def _specs(tree: Any, axis: str, shared: Callable[[Any], bool], lead: int = 0) -> Any:
    """A PartitionSpec per leaf of ``tree``: whole where ``shared`` names it, else split
    along ``axis`` on its batch axis (after ``lead`` leading axes)."""
    split = PartitionSpec(*([None] * lead), axis)
    return jax.tree_util.tree_map_with_path(
        lambda path, x: PartitionSpec() if shared(path) else split, tree)


def _local(x: Any, spec: PartitionSpec, devices: int, lead: int = 0) -> jax.ShapeDtypeStruct:
    """The shape and dtype one device sees of ``x`` under ``spec`` (batch axis ``lead``)."""
    shape = list(x.shape)
    if spec != PartitionSpec():
        shape[lead] //= devices
    return jax.ShapeDtypeStruct(tuple(shape), x.dtype)
