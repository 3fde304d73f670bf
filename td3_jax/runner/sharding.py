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

import json
import os
from concurrent import futures
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from td3_jax.common import library_noise, runtime, upstream
from td3_jax.common.errors import ConfigError, ProcessLostError
from td3_jax.config.schema import as_flag, flag
from td3_jax.runner.memory import (
    WORKING_ADVICE,
    available_memory,
    larger_network_advice,
    size_text,
    state_bytes,
    working_total,
)

AXIS = "data"
_SPLIT = (".env_state", ".ou_state", ".expl_draw", ".buffer.data", ".returns.returns")


def make_mesh(num_devices: int | None = None) -> Mesh:
    """A 1-D mesh over the first ``num_devices`` devices (default: all, across processes)."""
    devices = jax.devices()
    if num_devices is not None:
        check_devices(num_devices)
        if num_devices > len(devices):
            hint = ("; JAX counts a CPU as one device (XLA_FLAGS="
                    "--xla_force_host_platform_device_count=N emulates N)"
                    if all(d.platform == "cpu" for d in devices) else "")  # fmt: skip
            raise ConfigError(f"--devices {num_devices} asked, {len(devices)} available{hint}")
        devices = devices[:num_devices]
    return Mesh(np.array(devices), (AXIS,))


def check_devices(num_devices: int | None) -> None:
    """A one-line ConfigError for a device count (``--devices``) that is not positive."""
    if num_devices is not None and num_devices <= 0:
        raise ConfigError(f"--devices must be positive, got {num_devices}")


def memory_of(device: Any) -> tuple[int, str] | None:
    """``(bytes, what)``: the memory ``device`` has available for new arrays now (an
    accelerator's own less what it holds, by its statistics; for a CPU the host's available
    memory, :func:`~td3_jax.runner.memory.available_memory`), and the words that name it in a
    message (``"this machine's memory has"``); ``None`` where it cannot be told."""
    stats = None
    try:
        stats = device.memory_stats()
    except Exception:  # not every backend reports statistics
        stats = None
    if stats and stats.get("bytes_limit"):
        free = int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
        return max(free, 0), f"each {device.device_kind}'s memory has"
    if device.platform == "cpu":
        available = available_memory()
        return None if available is None else (available, "this machine's memory has")
    return None


def check_memory(abstract_state: Any, mesh: Mesh, working: dict[str, int] | None = None, *,
                 resident: bool = False) -> None:  # fmt: skip
    """Raises :class:`ConfigError` before anything is allocated when the train state (arrays
    or their shapes) and ``working``, the programs' working memory per device
    (:func:`~td3_jax.runner.memory.working_bytes`; none given: the state alone), do not fit in
    the memory a device has available now: one line with the sizes, what is available and the
    flags that shrink the largest part. ``resident``: the state is in memory already (restored),
    so only the working memory is still to come."""
    device = mesh.devices.flat[0]
    memory = memory_of(device)
    if memory is None:
        return
    limit, what = memory
    share = 1 if device.platform == "cpu" else mesh.size  # CPU "devices" share the host's
    state = 0 if resident else state_bytes(abstract_state) // share
    extra = working_total(working or {})
    if state + extra <= limit:
        return
    ring = state_bytes(abstract_state.buffer) // share
    networks = state_bytes(abstract_state.agent)  # (replicated: every device holds them all)
    parts = {**(working or {}), "ring": 0 if resident else ring,
             "networks": (0 if resident else networks) + (working or {}).get("networks", 0)}
    sizes = (f"the replay ring {size_text(ring)}, the networks and their optimiser states "
             f"{size_text(networks)}")
    raise ConfigError(f"{_needs(sizes, state, extra, resident)} but {what} {size_text(limit)} "
                      f"available now; use {_memory_advice(abstract_state, parts)}")  # fmt: skip


def _needs(sizes: str, state: int, extra: int, resident: bool) -> str:
    """What a run needs, in words: the train state's bytes (``sizes``: its parts) and the
    programs' working memory (``extra``), or that alone beside a ``resident`` state."""
    if resident:
        return (f"the training programs need about {size_text(extra)} of working memory per "
                f"device beside the restored train state ({sizes})")
    needs = f"the train state needs {size_text(state)} per device ({sizes})"
    if not extra:
        return needs
    return (f"{needs} and the training programs about {size_text(extra)} of working memory, "
            f"{size_text(state + extra)} in all,")


def _memory_advice(abstract_state: Any, parts: dict[str, int]) -> str:
    """The flags that shrink the largest part of what a run needs (``parts``: ``ring``,
    ``networks`` and :func:`~td3_jax.runner.memory.working_bytes`' parts), the likeliest first:
    fewer members where the run has several (each has its own networks, ring and
    environments; the agent's leaves are ``[members, ...]``), then that part's own flag."""
    largest = max(parts, key=lambda name: parts[name])
    if largest == "networks":
        shrink = larger_network_advice(abstract_state.agent)
    else:
        shrink = WORKING_ADVICE.get(largest, "a smaller --buffer-size")
    leaves = jax.tree.leaves(abstract_state.agent)
    count = int(leaves[0].shape[0]) if leaves and leaves[0].shape else 1
    if count > 1:
        return (f"fewer --seeds or sweep values (the run has {count:,} members, each with its "
                f"own networks, ring and environments), or {shrink}")  # fmt: skip
    return shrink


def check_program_memory(compiled: Any, device: Any, doing: str, advice: str) -> None:
    """Raises :class:`ConfigError` before a compiled program runs when its outputs and working
    memory (XLA's ``memory_analysis``) do not fit in the memory ``device`` has available now
    (:func:`memory_of`: memory it already holds, a restored train state, is not available):
    one line with both sizes, ``doing`` (what the program is for, e.g. ``"evaluating 1,000
    episodes"``) and ``advice`` (the flag that shrinks it). Nothing is checked where either
    size is unknown."""

    memory = memory_of(device)
    try:
        stats = compiled.memory_analysis()
        need = int(stats.temp_size_in_bytes) + int(stats.output_size_in_bytes)
    except Exception:  # not every backend analyses its programs
        return
    if memory is None or need <= memory[0]:
        return
    limit, what = memory
    raise ConfigError(f"{doing} needs {size_text(need)} of working memory but {what} "
                      f"{size_text(limit)} available now; use {advice}")  # fmt: skip


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
    """NamedShardings for a train state: split env/buffer leaves, replicate the rest (and the
    environment leaves without the batch axis: MuJoCo Warp's buffers shared by a device's
    environments, each device's own, :mod:`td3_jax.envs.per_device`).

    Args:
      abstract_state: the state or its ``jax.eval_shape``.
      member_axis: leaves carry a leading population axis (as in :mod:`td3_jax.core.population`);
        the split axis is then the second one.
    """
    axis = 1 if member_axis else 0
    size = mesh.shape[AXIS]
    worlds = _env_batch(abstract_state, axis)

    def spec(path, leaf) -> NamedSharding:
        name = jax.tree_util.keystr(path)
        unbatched = worlds is not None and len(leaf.shape) > axis and leaf.shape[axis] != worlds
        if ".env_state" in name and unbatched:
            return NamedSharding(mesh, PartitionSpec())  # (MuJoCo Warp's shared buffers)
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


def _env_batch(abstract_state: Any, axis: int) -> int | None:
    """The environment batch of a train state (its ``env_state.steps``' length along
    ``axis``); ``None`` where it has none."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(abstract_state):
        if jax.tree_util.keystr(path).endswith(".env_state.steps") and len(leaf.shape) > axis:
            return leaf.shape[axis]
    return None


def replicate(value: Any, mesh: Mesh) -> jax.Array:
    """``value`` as one array replicated over ``mesh`` (which may span several processes)."""
    local = np.asarray(value)
    sharding = NamedSharding(mesh, PartitionSpec())
    return jax.make_array_from_callback(local.shape, sharding, lambda index: local[index])


def host_value(x: jax.Array) -> np.ndarray:
    """A replicated array's value on this host (also when it spans several processes), waited
    for in JAX's wait, which runs Python's signal handlers meanwhile: NumPy's copy of an array
    still being computed runs none, so in a process of several a Ctrl-C's line (and a second
    Ctrl-C) came only once the chunk had ended."""
    if getattr(x, "is_fully_addressable", True):
        return np.asarray(jax.device_get(x))
    return np.asarray(x.block_until_ready().addressable_data(0))


#: Key prefix of each process's settings in the distributed key-value store.
SETTINGS_KEY = "td3_jax/settings"
#: Key prefix of each process's word on stopping at a chunk boundary.
STOP_KEY = "td3_jax/stop"
#: Seconds a process waits at a chunk boundary for the others' word on stopping (they may still
#: be compiling, evaluating or writing a checkpoint).
STOP_WAIT_S = 3600
#: Seconds a process waits for all the others to join (``jax.distributed.initialize``'s
#: ``initialization_timeout``); past it JAX aborts the process (exit status 134).
JOIN_TIMEOUT_S = 300


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
    num_processes = _whole_or_env(num_processes, "JAX_NUM_PROCESSES")
    process_id = _whole_or_env(process_id, "JAX_PROCESS_ID")
    check_processes(coordinator_address, num_processes, process_id)
    launched = runtime.local_processes() is not None  # (--local-processes said where they join)
    if num_processes is not None and num_processes > 1 and process_id is not None and not launched:
        print(f"td3-jax: waiting for {num_processes} processes at {coordinator_address} (this "
              f"is process {process_id}; each runs the same command with its own --process-id, "
              f"0 to {num_processes - 1}; JAX gives up after {JOIN_TIMEOUT_S} s)...",
              flush=True)  # fmt: skip
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except Exception:  # pragma: no cover - option absent in some jax versions
        pass
    # JAX's preemption service would take SIGTERM for itself from the moment the processes
    # join (td3-jax never asks it), so a SIGTERM before training was lost and the run trained
    # on: td3-jax's own handlers stop the processes together (stop_agreed, start_agreed).
    jax.config.update("jax_enable_preemption_service", False)
    _start_runtime(coordinator_address, num_processes, process_id)
    from td3_jax.envs.mjx_devices import place_on_local_devices

    place_on_local_devices()  # MJX would put every process's models on process 0's device
    return True


def check_same_settings(settings: dict[str, Any]) -> None:
    """Raises :class:`ConfigError` unless every process of this ``jax.distributed`` run was
    given the same ``settings`` (``{flag's field: value}``, as each process parsed them;
    nothing to do without ``jax.distributed``). Every process that gets here finds the
    difference and says it, so none is left waiting for the others at a collective.

    Each process publishes its settings in the runtime's key-value store and reads the
    others' (waiting up to :data:`JOIN_TIMEOUT_S` for each: a process that stopped before
    publishing is named, it says why itself)."""
    store = upstream.distributed_store()
    if store is None:  # (one process: JAX's backend is not started for nothing)
        return
    here, texts = jax.process_index(), _as_texts(settings)
    store.key_value_set(f"{SETTINGS_KEY}/{here}", json.dumps(texts))
    for other in range(jax.process_count()):
        if other != here:
            theirs = _published(store, other)
            differ = sorted(k for k in texts | theirs if texts.get(k) != theirs.get(k))
            if differ:
                raise ConfigError(_differ_message(differ, theirs, texts, other, here))


def stop_agreed(reason: str, chunk: int, end: bool, call: int = 0) -> str:
    """Whether the processes of this ``jax.distributed`` run stop at the start (or ``end``) of
    chunk ``chunk`` (0-based) of their training call ``call`` (counted in each process),
    agreed so that none goes on into a chunk whose collectives the others will never join.
    ``reason`` is this process's own: ``""`` (go on), ``"limit"`` (its chunk limit, or
    ``--time-budget-s`` read from its own clock) or ``"token"`` (a Ctrl-C or SIGTERM of its
    own). Returns the agreed one: ``"token"`` if any process has one, else ``"limit"`` if any,
    else ``""``. One process: ``reason`` itself.

    Each process publishes its reason in the runtime's key-value store and reads the others'
    (up to :data:`STOP_WAIT_S` each). :class:`ProcessLostError` names a process that stopped
    with an error (:func:`stop_failed`) or never gives its reason."""
    where = f"the {'end' if end else 'start'} of chunk {chunk + 1}"
    return _agreed(reason, _boundary(call, chunk, end), where)


def start_agreed(reason: str, call: int = 0) -> str:
    """:func:`stop_agreed` at the point where each process of training call ``call`` has
    its programs compiled and has run none of them (a resumed run has read its checkpoint):
    a stop asked while the processes start (``"token"``) is agreed there, so none is left
    waiting for the others at their first collective. One process: ``reason`` itself."""
    return _agreed(reason, _boundary(call, -1, False), "the start of training")


def prepared_agreed(reason: str, call: int = 0) -> str:
    """:func:`stop_agreed` where each process of training call ``call`` has checked its
    settings, environment and run directory, before anything that needs the others (orbax's
    checkpoint steps already do): a process refused there by a check of its own (its host's
    ``--out``, say) is named at once, where the others waited for it in their first collective
    and failed with a traceback. One process: ``reason`` itself."""
    return _agreed(reason, _boundary(call, -2, False), "the start of training")


def stop_before_training(reason: str, call: int = 0) -> None:
    """Tells the other processes of this ``jax.distributed`` run that this one stops before
    training call ``call`` trains: for ``reason`` ``"token"`` (a Ctrl-C or SIGTERM, they stop
    as interrupted) or ``"error"`` (they stop with :class:`ProcessLostError`), where they
    agree to go on (:func:`prepared_agreed`, :func:`start_agreed`). Nothing to do in one
    process; where this process already gave its reason at one of them, that one is kept."""
    store = _store_of_several()
    if store is not None:
        for step in (-2, -1):
            _announce(store, _boundary(call, step, False), reason)


def _agreed(reason: str, boundary: str, where: str) -> str:
    """The reason agreed at ``boundary`` (:func:`stop_agreed`), ``where`` it is in words."""
    store = _store_of_several()
    if store is None:
        return reason
    here = jax.process_index()
    store.key_value_set(f"{STOP_KEY}/{boundary}/{here}", reason)
    reasons = {reason}
    for other in range(jax.process_count()):
        if other != here:
            key = f"{STOP_KEY}/{boundary}/{other}"
            try:
                reasons.add(store.blocking_key_value_get(key, STOP_WAIT_S * 1000))
            except jax.errors.JaxRuntimeError:
                raise ProcessLostError(
                    f"process {other} did not reach {where} within {STOP_WAIT_S} s of this "
                    "process (its own output says why it stopped, if it did); this process "
                    "stops too"
                ) from None
            if "error" in reasons:
                raise ProcessLostError(f"process {other} stopped with an error before {where} "
                                       "(its own output says which); this process stops too")
    return "token" if "token" in reasons else "limit" if "limit" in reasons else ""


def stop_failed(chunk: int, call: int = 0) -> None:
    """Tells the other processes of this ``jax.distributed`` run that this one stops with an
    error in chunk ``chunk`` of training call ``call``: they stop at that chunk's boundaries
    (:func:`stop_agreed`) instead of waiting for it. Nothing to do in one process."""
    store = _store_of_several()
    if store is None:
        return
    for boundary in (_boundary(call, chunk, False), _boundary(call, chunk, True),
                     _boundary(call, chunk + 1, False)):  # fmt: skip
        _announce(store, boundary, "error")


def _announce(store: Any, boundary: str, reason: str) -> None:
    """This process's ``reason`` at ``boundary``, unless it already gave one there (kept)."""
    try:
        store.key_value_set(f"{STOP_KEY}/{boundary}/{jax.process_index()}", reason)
    except jax.errors.JaxRuntimeError:
        pass


def _store_of_several() -> Any:
    """The key-value store of a ``jax.distributed`` run of several processes; None for one
    process (nothing of JAX's private runtime is asked then)."""
    return None if jax.process_count() == 1 else upstream.distributed_store()


def _boundary(call: int, chunk: int, end: bool) -> str:
    """The key of a chunk boundary in the store (under :data:`STOP_KEY`)."""
    return f"{call}/{chunk}/{'end' if end else 'start'}"


def _as_texts(settings: dict[str, Any]) -> dict[str, str]:
    """Each setting's value as JSON text (tuples as lists, paths as text; NaN equals NaN)."""
    return {k: json.dumps(v, sort_keys=True, default=str) for k, v in settings.items()}


def _published(store: Any, other: int) -> dict[str, str]:
    """Process ``other``'s settings from the key-value store; ConfigError when it published
    none within :data:`JOIN_TIMEOUT_S` (it stopped before, or hangs)."""
    try:
        return json.loads(store.blocking_key_value_get(f"{SETTINGS_KEY}/{other}",
                                                       JOIN_TIMEOUT_S * 1000))  # fmt: skip
    except jax.errors.JaxRuntimeError:
        raise ConfigError(
            f"process {other} did not give its settings within {JOIN_TIMEOUT_S} s: it stopped "
            "before (its own output says why) or is stuck"
        ) from None


def _differ_message(differ: list[str], theirs: dict, mine: dict, other: int, here: int) -> str:
    """One line naming the first setting of ``differ``, as each process was given it on the
    command line, and how many more differ."""
    name = differ[0]
    more = f" (and {len(differ) - 1} more)" if len(differ) > 1 else ""
    return (f"process {other} was given other settings than this process ({here}): "
            f"{_given_as(name, theirs)} there, {_given_as(name, mine)} here{more}; start every "
            "process with the same flags (only --process-id, --menagerie, --quiet and "
            "--compile-cache may differ)")  # fmt: skip


def _given_as(name: str, texts: dict[str, str]) -> str:
    """Setting ``name`` of a process's published ``texts`` as command-line text (``--hidden-sizes
    256 256``, ``--no-resume``, ``td3-jax sweep`` for the subcommand; ``no --NAME`` where that
    process has no such setting, or it is unset)."""
    value = json.loads(texts[name]) if name in texts else None
    if value is None:
        return f"no {flag(name)}"
    return f"td3-jax {value}" if name == "command" else as_flag(name, value)


def leave_distributed(wait_s: float | None = None) -> bool:
    """Ends this process's part of the ``jax.distributed`` run it joined, waiting for the
    others to end theirs (JAX's coordination service then sees each leave rather than lose
    it), the last thing the process does: the service's warnings as the processes leave, which
    its threads may write until the process ends, are dropped from its stderr from here on
    (:data:`~td3_jax.common.library_noise.LEAVING`). The wait runs on a thread of
    :func:`~td3_jax.common.runtime.in_background`, so signals are handled meanwhile; past
    ``wait_s`` (None: no limit) it returns False and the wait goes on there (the CLI then ends
    the process at once). True where it left, or joined none."""
    if not jax.distributed.is_initialized():
        return True
    library_noise.filtered_stderr_until_exit(library_noise.LEAVING)  # (its threads' lines)
    leaving = runtime.in_background(jax.distributed.shutdown, name="td3-jax leaving")
    done, _ = futures.wait([leaving], timeout=wait_s)
    if done:
        leaving.result()
    return bool(done)


def _start_runtime(address: str, num_processes: int | None, process_id: int | None) -> None:
    """``jax.distributed.initialize``; where JAX finds no process count or id (none given, and
    no cluster manager such as SLURM or Open MPI to read them from), its refusal as one line."""
    try:
        jax.distributed.initialize(coordinator_address=address, num_processes=num_processes,
                                   process_id=process_id, initialization_timeout=JOIN_TIMEOUT_S,
                                   coordinator_bind_address=_bind_address(address))  # fmt: skip
    except ValueError as err:
        if "must be defined" not in str(err):
            raise
        raise ConfigError(
            "--coordinator-address needs --num-processes and --process-id (or JAX_NUM_PROCESSES "
            "and JAX_PROCESS_ID) where no cluster manager (SLURM, Open MPI, ...) sets them; "
            f"JAX: {err}"
        ) from None


def _bind_address(address: str) -> str | None:
    """Where the first process's coordination service listens: ``address`` itself where it is
    this host's loopback address 127.0.0.1 (``--local-processes``: the service is then out of
    reach of other hosts), else JAX's default (every interface, at its port)."""
    return address if address.rpartition(":")[0] == "127.0.0.1" else None


def _whole_or_env(value: int | None, variable: str) -> int | None:
    """``value``, else the whole number in environment variable ``variable`` (if set)."""
    if value is not None or variable not in os.environ:
        return value
    text = os.environ[variable]
    try:
        return int(text)
    except ValueError:
        raise ConfigError(f"{variable}={text!r} is not a whole number") from None


def check_processes(address: str, num_processes: int | None, process_id: int | None) -> None:
    """Raises :class:`ConfigError` for a coordinator address that is not ``HOST:PORT``, fewer
    than one process, or a process id outside ``0 .. num_processes - 1``."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--coordinator-address {address!r} must be HOST:PORT (e.g. "
                          "10.0.0.1:12345): the first process's host and a free port")  # fmt: skip
    if num_processes is not None and num_processes < 1:
        raise ConfigError(f"--num-processes must be at least 1, got {num_processes}")
    beyond = num_processes is not None and process_id is not None and process_id >= num_processes
    if process_id is not None and (process_id < 0 or beyond):
        top = f"{num_processes - 1}" if num_processes is not None else "--num-processes - 1"
        raise ConfigError(f"--process-id must be from 0 to {top} (one per process), got "
                          f"{process_id}")  # fmt: skip


__all__ = [
    "AXIS",
    "JOIN_TIMEOUT_S",
    "SETTINGS_KEY",
    "STOP_KEY",
    "STOP_WAIT_S",
    "check_memory",
    "check_processes",
    "check_same_settings",
    "host_value",
    "initialize_distributed",
    "leave_distributed",
    "make_mesh",
    "memory_of",
    "prepared_agreed",
    "replicate",
    "start_agreed",
    "state_shardings",
    "stop_agreed",
    "stop_before_training",
    "stop_failed",
]
