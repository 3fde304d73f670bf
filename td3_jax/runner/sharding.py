"""Data parallelism over devices with ``jax.sharding`` (GSPMD): nothing hand-written.

The train state is placed on a 1-D device mesh with axis ``"data"``: environment states, OU
noise states, per-environment exploration draws, the running return sums of reward scaling
and the replay buffer are split along their environment / slice axis (with
``--replay-shards`` a multiple of the device count each device holds whole slices of the ring,
so inserts and sampling need no traffic between devices); everything
else (parameters, targets, optimiser states, normaliser, keys, counters) is replicated. The
chunk is the same program as on one device, jitted with these shardings; XLA partitions it and
inserts the collectives (the gradient and normaliser reductions over the sharded batch, the
gathers of sampled rows). The math is the one-device math: num_envs and batch_size are global,
and the random draws are the same, so a run on D devices gives the one-device numbers up to
float reassociation.

Several hosts: call :func:`initialize_distributed` first (``jax.distributed.initialize``); the
mesh then spans every process's devices and each process drives its local ones.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from td3_jax.common.errors import ConfigError
from td3_jax.runner.memory import larger_network_advice, size_text, state_bytes

AXIS = "data"
_SPLIT = (".env_state", ".ou_state", ".expl_draw", ".buffer.data", ".returns.returns")


def make_mesh(num_devices: int | None = None) -> Mesh:
    """A 1-D mesh over the first ``num_devices`` devices (default: all, across processes)."""
    devices = jax.devices()
    if num_devices is not None:
        check_devices(num_devices)
        if num_devices > len(devices):
            raise ConfigError(f"--devices {num_devices} asked, {len(devices)} available")
        devices = devices[:num_devices]
    return Mesh(np.array(devices), (AXIS,))


def check_devices(num_devices: int | None) -> None:
    """A one-line ConfigError for a device count (``--devices``) that is not positive."""
    if num_devices is not None and num_devices <= 0:
        raise ConfigError(f"--devices must be positive, got {num_devices}")


def memory_of(device: Any) -> tuple[int, str] | None:
    """``(bytes, what)``: the memory ``device`` can hold arrays in (an accelerator's own, the
    host's for a CPU), or ``None`` where it cannot be told."""
    stats = None
    try:
        stats = device.memory_stats()
    except Exception:  # not every backend reports statistics
        stats = None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"each {device.device_kind} holds"
    if device.platform == "cpu" and hasattr(os, "sysconf"):
        try:
            total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError):
            return None
        return int(total), "this machine's memory is"
    return None


def check_memory(abstract_state: Any, mesh: Mesh) -> None:
    """Raises :class:`ConfigError` before anything is allocated when the train state (arrays
    or their shapes) cannot fit in a device's memory: one line with both sizes and the flags
    that shrink it (the replay ring is nearly all of a large state)."""

    device = mesh.devices.flat[0]
    memory = memory_of(device)
    if memory is None:
        return
    limit, what = memory
    share = 1 if device.platform == "cpu" else mesh.size  # CPU "devices" share the host's
    need = state_bytes(abstract_state) // share
    if need <= limit:
        return
    ring = state_bytes(abstract_state.buffer) // share
    networks = state_bytes(abstract_state.agent)  # (replicated: every device holds them all)
    raise ConfigError(
        f"the train state needs {size_text(need)} per device (the replay ring "
        f"{size_text(ring)}, the networks and their optimiser states {size_text(networks)}) "
        f"but {what} {size_text(limit)}; use {_memory_advice(abstract_state, networks > ring)}"
    )


def _memory_advice(abstract_state: Any, networks_larger: bool) -> str:
    """The flags that shrink a train state, the likeliest first: fewer members where the run
    has several (each has its own networks and ring; the agent's leaves are ``[members,
    ...]``), else the larger part's size."""
    shrink = "a smaller --buffer-size"
    if networks_larger:
        shrink = larger_network_advice(abstract_state.agent)
    leaves = jax.tree.leaves(abstract_state.agent)
    count = int(leaves[0].shape[0]) if leaves and leaves[0].shape else 1
    envs = "" if networks_larger else " or fewer --num-envs"  # (the ring's default size)
    if count > 1:
        return (f"fewer --seeds or sweep values (the run has {count:,} members, each with its "
                f"own networks and ring), {shrink if envs else 'or ' + shrink}{envs}")  # fmt: skip
    return f"{shrink}{envs.replace(' or', ', or')}"


def check_program_memory(compiled: Any, device: Any, doing: str, advice: str) -> None:
    """Raises :class:`ConfigError` before a compiled program runs when its outputs and working
    memory (XLA's ``memory_analysis``) cannot fit in ``device``'s memory: one line with both
    sizes, ``doing`` (what the program is for, e.g. ``"evaluating 1,000 episodes"``) and
    ``advice`` (the flag that shrinks it). Memory the device already holds (a restored train
    state) counts against it where the device says how much. Nothing is checked where either
    size is unknown."""

    memory = memory_of(device)
    try:
        stats = compiled.memory_analysis()
        need = int(stats.temp_size_in_bytes) + int(stats.output_size_in_bytes)
    except Exception:  # not every backend analyses its programs
        return
    held = _bytes_in_use(device)
    if memory is None or need + held <= memory[0]:
        return
    limit, what = memory
    holding = f" and {size_text(held)} of it is in use" if held else ""
    raise ConfigError(f"{doing} needs {size_text(need)} of working memory but {what} "
                      f"{size_text(limit)}{holding}; use {advice}")  # fmt: skip


def _bytes_in_use(device: Any) -> int:
    """The bytes ``device`` holds now, by its own statistics (0 where it keeps none: a CPU)."""
    try:
        return int((device.memory_stats() or {}).get("bytes_in_use", 0))
    except Exception:  # not every backend reports statistics
        return 0


def replay_layout_warning(replay_shards: int, num_devices: int) -> str | None:
    """A warning when the replay ring's ``replay_shards`` slices do not fall on whole devices
    (``None`` when they do, or on one device).

    With ``--replay-shards`` not a multiple of the device count, each slice's rows are split over
    the devices: every gradient update then gathers its whole batch onto every device (one
    all-reduce of ``batch x n_step`` rows) and computes the update there in full, and every
    step's transitions are all-gathered before they are written. The numbers are right, but
    the learner is not data-parallel.
    """
    if num_devices <= 1 or replay_shards % num_devices == 0:
        return None
    return (
        f"--replay-shards {replay_shards} is not a multiple of the {num_devices} devices: "
        "each update gathers its whole batch onto every device and computes it there in full; "
        f"--replay-shards {num_devices} (or a multiple) keeps replay and updates on each device "
        "(stratified sampling, so the numbers differ from --replay-shards 1)"
    )


def state_shardings(abstract_state: Any, mesh: Mesh, member_axis: bool = True) -> Any:
    """NamedShardings for a train state: split env/buffer leaves, replicate the rest.

    Args:
      abstract_state: the state or its ``jax.eval_shape``.
      member_axis: leaves carry a leading population axis (as in :mod:`td3_jax.core.population`);
        the split axis is then the second one.
    """
    axis = 1 if member_axis else 0
    size = mesh.shape[AXIS]

    def spec(path, leaf) -> NamedSharding:
        name = jax.tree_util.keystr(path)
        if ".buffer.data" in name:
            # [members, shards, capacity / shards, ...]: whole slices per device when the shard
            # count allows (device-local inserts and samples), else split every slice.
            for buffer_axis in (axis, axis + 1):
                if leaf.shape[buffer_axis] % size == 0:
                    return NamedSharding(mesh, PartitionSpec(*([None] * buffer_axis), AXIS))
            return NamedSharding(mesh, PartitionSpec())
        split = (
            any(part in name for part in _SPLIT)
            and len(leaf.shape) > axis
            and leaf.shape[axis] % size == 0
        )
        if split:
            return NamedSharding(mesh, PartitionSpec(*([None] * axis), AXIS))
        return NamedSharding(mesh, PartitionSpec())

    return jax.tree_util.tree_map_with_path(spec, abstract_state)


def replicate(value: Any, mesh: Mesh) -> jax.Array:
    """``value`` as one array replicated over ``mesh`` (which may span several processes)."""
    local = np.asarray(value)
    sharding = NamedSharding(mesh, PartitionSpec())
    return jax.make_array_from_callback(local.shape, sharding, lambda index: local[index])


def host_value(x: jax.Array) -> np.ndarray:
    """A replicated array's value on this host (also when it spans several processes)."""
    if getattr(x, "is_fully_addressable", True):
        return np.asarray(jax.device_get(x))
    return np.asarray(x.addressable_data(0))


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> bool:
    """Starts JAX's multi-controller runtime when asked to; returns whether it did.

    Flags win over the standard environment variables (``JAX_COORDINATOR_ADDRESS``,
    ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``); with neither, nothing happens (one process).
    On CPU the collectives go through gloo.
    """
    coordinator_address = coordinator_address or os.environ.get("JAX_COORDINATOR_ADDRESS")
    if not coordinator_address:
        if num_processes is not None or process_id is not None:
            raise ConfigError(
                "--num-processes/--process-id need --coordinator-address "
                "(or JAX_COORDINATOR_ADDRESS)"
            )
        return False
    if num_processes is None and "JAX_NUM_PROCESSES" in os.environ:
        num_processes = int(os.environ["JAX_NUM_PROCESSES"])
    if process_id is None and "JAX_PROCESS_ID" in os.environ:
        process_id = int(os.environ["JAX_PROCESS_ID"])
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except Exception:  # pragma: no cover - option absent in some jax versions
        pass
    jax.distributed.initialize(
        coordinator_address=coordinator_address,
        num_processes=num_processes,
        process_id=process_id,
    )
    from td3_jax.envs.mjx_devices import place_on_local_devices

    place_on_local_devices()  # MJX would put every process's models on process 0's device
    return True


__all__ = [
    "AXIS",
    "check_memory",
    "host_value",
    "initialize_distributed",
    "make_mesh",
    "memory_of",
    "replicate",
    "state_shardings",
]
