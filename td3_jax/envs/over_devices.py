"""An environment batch split over devices, each device stepping its own environments.

XLA splits a batched computation over the devices of a mesh by itself (GSPMD) when it can see
inside it: JAX physics (MJX, Brax, gymnax) needs nothing more. MuJoCo Warp's physics is a call
XLA cannot look into, so it cannot split it. :func:`over_devices` runs every batched physics
call of such an environment (:attr:`~td3_jax.envs.base.Environment.per_device`) under
``jax.shard_map``: each device resets and steps its own contiguous block of the batch, the
block the train state holds on that device, with no traffic between devices.

MuJoCo Warp keeps a few buffers once for all the environments stepped together, without a
batch axis (its contact buffer and counters). Each device keeps its own copy, sized as on one
device; they are scratch space that every step fills before it reads them, so the state keeps
one shape whatever the device count (a checkpoint written on two devices restores on one), and
what a device's copy holds between steps is never read.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
from jax.sharding import Mesh, PartitionSpec

from td3_jax.common.errors import ConfigError
from td3_jax.envs.base import Environment, batched

__all__ = ["over_devices", "split_call"]


def over_devices(env: Environment, mesh: Mesh, axis: str = "data") -> Environment:
    """``env`` with its batched physics run on each device of ``mesh`` (axis ``axis``) apart,
    where it needs it (:attr:`~td3_jax.envs.base.Environment.per_device`) and the mesh has
    more than one device; otherwise ``env`` itself. Batches must divide evenly over the
    devices (:class:`~td3_jax.common.errors.ConfigError` at trace time otherwise)."""
    if not env.per_device or mesh.shape[axis] == 1:
        return env
    return dataclasses.replace(env, batch_map=functools.partial(split_call, mesh=mesh, axis=axis))


def split_call(batched_fn: Callable, size: int, *, mesh: Mesh, axis: str = "data") -> Callable:
    """``batched_fn`` (a function over a batch of ``size`` environments: every argument and
    result leaf ``[size, ...]``, or without the batch axis) run under ``jax.shard_map``: leaves
    with the batch axis split over ``axis``, one block per device, leaves without it given
    whole to every device; each device's results are its block of the batch, and its own copy
    of the leaves without the batch axis (see the module's docstring)."""
    devices = mesh.shape[axis]
    if size % devices:
        raise ConfigError(f"{size} environments cannot be split evenly over {devices} devices: "
                          f"use a number of environments divisible by {devices}")  # fmt: skip

    def call(*args: Any) -> Any:
        in_specs = _specs(args, size, axis)
        out_specs = _out_specs(batched_fn, args, in_specs, size // devices, axis)
        run = jax.shard_map(batched_fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs,
                            check_vma=False)  # (Warp's calls have no replication rule)
        return run(*args)

    return call


def _specs(tree: Any, size: int, axis: str) -> Any:
    """A PartitionSpec per leaf of ``tree``: split along ``axis`` where it has a batch axis of
    ``size``, whole otherwise."""
    return jax.tree.map(lambda x: PartitionSpec(axis) if batched(x, size) else PartitionSpec(),
                        tree)  # fmt: skip


def _out_specs(batched_fn: Callable, args: Any, in_specs: Any, local: int, axis: str) -> Any:
    """The results' PartitionSpecs: split where a result has the batch axis, told by its
    shapes for batches of ``local`` and ``local + 1`` (a buffer of the batch's length is not
    taken for the batch axis)."""
    one, other = (jax.eval_shape(batched_fn, *_resized(args, in_specs, n))
                  for n in (local, local + 1))  # fmt: skip
    return jax.tree.map(
        lambda a, b: PartitionSpec(axis) if batched(a, local) and batched(b, local + 1)
        else PartitionSpec(), one, other)  # fmt: skip


def _resized(args: Any, in_specs: Any, size: int) -> Any:
    """Shapes and dtypes of ``args`` with every batch axis (a split leaf of ``in_specs``)
    ``size`` long."""

    def resize(x: Any, spec: PartitionSpec) -> jax.ShapeDtypeStruct:
        shape = tuple(x.shape) if spec == PartitionSpec() else (size, *x.shape[1:])
        return jax.ShapeDtypeStruct(shape, x.dtype)

    return jax.tree.map(resize, args, in_specs)
