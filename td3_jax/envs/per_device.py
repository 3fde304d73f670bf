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
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
from jax.sharding import Mesh, PartitionSpec

from td3_jax.common import upstream
from td3_jax.common.errors import ConfigError
from td3_jax.envs.base import Environment

__all__ = ["over_devices", "split_call", "warp_shared_leaf"]


def over_devices(env: Environment, mesh: Mesh, axis: str = "data") -> Environment:
    """``env`` with its batched physics run on each device of ``mesh`` (axis ``axis``) apart,
    where it needs it (:attr:`~td3_jax.envs.base.Environment.per_device`: MuJoCo Warp's) and
    the mesh has more than one device; otherwise ``env`` itself. Batches must divide evenly
    over the devices (:class:`~td3_jax.common.errors.ConfigError` at trace time otherwise)."""
    if not env.per_device or mesh.shape[axis] == 1:
        return env
    split = functools.partial(split_call, mesh=mesh, axis=axis, shared=warp_shared_leaf())
    return dataclasses.replace(env, batch_map=split)


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
               shared: Callable[[Any], bool] = lambda path: False) -> Callable:  # fmt: skip
    """``batched_fn`` (a function over a batch of ``size`` environments: every argument and
    result leaf ``[size, ...]``, except those ``shared(path)`` names, which have no batch axis)
    run under ``jax.shard_map``: batched leaves split over ``axis``, one block per device,
    shared ones given whole to every device; each device's results are its block of the batch
    and its own copy of the shared leaves (see the module's docstring)."""
    devices = mesh.shape[axis]
    if size % devices:
        raise ConfigError(f"{size} environments cannot be split evenly over {devices} devices: "
                          f"use a number of environments divisible by {devices}")  # fmt: skip

    def call(*args: Any) -> Any:
        in_specs = _specs(args, axis, shared)
        local = jax.tree.map(lambda x, spec: _local(x, spec, devices), args, in_specs)
        out_specs = _specs(jax.eval_shape(batched_fn, *local), axis, shared)
        run = jax.shard_map(batched_fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs,
                            check_vma=False)  # (Warp's calls have no replication rule)
        return run(*args)

    return call


def _specs(tree: Any, axis: str, shared: Callable[[Any], bool]) -> Any:
    """A PartitionSpec per leaf of ``tree``: whole where ``shared`` names it, else split
    along ``axis``."""
    return jax.tree_util.tree_map_with_path(
        lambda path, x: PartitionSpec() if shared(path) else PartitionSpec(axis), tree)


def _local(x: Any, spec: PartitionSpec, devices: int) -> jax.ShapeDtypeStruct:
    """The shape and dtype one device sees of ``x`` under ``spec``."""
    shape = tuple(x.shape) if spec == PartitionSpec() else (x.shape[0] // devices, *x.shape[1:])
    return jax.ShapeDtypeStruct(shape, x.dtype)
