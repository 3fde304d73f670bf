"""MuJoCo Warp's kernels compiled in parallel before the first physics step.

On a machine whose Warp kernel cache is cold, a Playground robot's first step compiles MuJoCo
Warp's kernels one module at a time, as each is first launched: T1's first reset and step
compiled 39 modules in 99 s on an H100, one CPU core busy. Most of those modules are made for
the model by MuJoCo Warp's kernel factories, so they cannot be listed before the model is known.
:func:`precompile` lists them by running MuJoCo Warp's step once in Python with every
module load recorded instead of done (no kernel runs: every launch returns before it starts
one; a block-size query is answered with a placeholder and its module listed), then has Warp
compile and load them on several threads (``warp.force_load``), the slowest first. The
compiled modules land in Warp's kernel cache as they would have, and the first real step finds
them loaded. A module the listing misses is compiled at its first launch, as without it (MJX's
own glue is one: its module is made at MJX's first call).

:func:`precompile_task` does this for a Playground task made on Warp (td3-jax's environments
call it); ``TD3_JAX_WARP_PRECOMPILE=0`` turns it off. Inside :func:`beside_compile` (a
training run's environment is made there), on a machine of 8 cores or more, it runs on threads
of its own while the caller traces its programs and XLA compiles them; :func:`wait_ready` waits
for it before the first physics step. The listing and the longest module (:data:`HEAD_START`,
one code generation of under a second) begin at once; the other modules once the caller has
traced its programs (:func:`programs_traced`: their code generation would slow the tracing,
which needs the same interpreter), on threads of lower CPU priority (:data:`NICENESS`), so that
the longest compile and XLA's, which bound the start, come first on the cores. Where Warp's
kernel cache holds a head-start module already (:func:`head_start_cached`), all of it waits
for the tracing. Warp's compile then costs the run only what XLA's does not cover
(``TD3_JAX_WARP_BESIDE=0``: first, then XLA's). The start-up it saves is measured in
docs/benchmarks.md ("XLA's compile of the chunk").
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import queue
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any, NamedTuple

from td3_jax.common import runtime, upstream

__all__ = [
    "BESIDE",
    "BESIDE_MIN_CORES",
    "CGROUP_ROOT",
    "HEAD_START",
    "MAX_WORKERS",
    "NICENESS",
    "PRECOMPILE",
    "PROC_CGROUP",
    "SLOW_FIRST",
    "Listing",
    "Precompiled",
    "beside_compile",
    "compile_listed",
    "cores",
    "cpu_quota",
    "default_workers",
    "drop_pending",
    "head_start_cached",
    "list_step",
    "listed_modules",
    "longest_first",
    "precompile",
    "precompile_task",
    "programs_traced",
    "static_options",
    "wait_ready",
]

#: Set to 0 (or false, off, no), Warp compiles each kernel module at its first launch (one at
#: a time), as it does on its own.
PRECOMPILE = "TD3_JAX_WARP_PRECOMPILE"
#: At most this many modules compile at once (each compile holds its own compiler's memory).
#: On a 16-core H200 host T1's cold precompile took 75 s on 8 threads and 24-55 s on 16.
MAX_WORKERS = 16
#: Parts of the names of the modules that take longest to compile, longest first: these are
#: started first, so that the longest is not left to start last. Measured for T1 on an H200
#: at 16 threads (docs/benchmarks.md, "Warp's kernels on a fresh machine"): the convex
#: collision kernel took 31-39 s, the next ones 13-23 s, all of them 190-285 s summed.
SLOW_FIRST = ("ccd_kernel", "_src.smooth", "_src.passive", "_src.sensor", "_src.forward",
              "_src.solver", "_update_gradient_cholesky", "_tile_cholesky")  # fmt: skip
#: Parts of the names of the modules that a precompile beside a compile starts at once, each on
#: a thread of its own, while the caller still traces its programs: the convex collision
#: kernel's compile alone outlasts XLA's compile of T1's chunk.
HEAD_START = ("ccd_kernel",)
#: How much lower the CPU priority (Linux's niceness, added) of the threads compiling the other
#: modules beside a compile is: they take the cores that the longest module's compile and XLA's
#: compiles, which bound the start, leave idle.
NICENESS = 10
#: Set to 0 (or false, off, no), a training run's precompile runs first, then its XLA
#: compile; otherwise (the default) on its own thread beside the XLA compile
#: (:func:`beside_compile`).
BESIDE = "TD3_JAX_WARP_BESIDE"
#: ... and only where the process may use this many cores; with fewer it runs first. (On 2
#: cores a tiny T1 run on Warp's CPU kernels took 233 s from launch with Warp compiling beside
#: XLA, against 151-180 s one after the other: XLA's compile slowed by more than Warp's whole
#: compile.)
BESIDE_MIN_CORES = 8


class Precompiled(NamedTuple):
    """What :func:`precompile` did: the modules it loaded (a module launched with two block
    sizes counts twice: each is compiled) and how long that took."""

    modules: int
    seconds: float


#: One listing at a time: its patches are the process's.
_LISTING = threading.Lock()


@contextlib.contextmanager
def _loads_recorded(seen: dict[tuple[Any, Any], None], answer_queries: bool) -> Iterator[None]:
    """Inside, a Warp module load on this thread is recorded in ``seen`` as ``(module,
    block_dim)`` (:func:`_variant`) and returns nothing, so each launch stops before it runs a
    kernel; a conditional loop runs its body once and a conditional runs both branches
    (:func:`_branches_run`). Other threads load and branch as usual. A block-size query on a
    GPU (which compiles and loads the module's own variant to ask it) is answered for real
    where ``answer_queries``; otherwise that load is recorded too and it is answered
    :func:`_placeholder_answer` (MuJoCo Warp sizes launch grids by the answer)."""
    import warp

    module_class, owner = upstream.warp_module_class(), threading.get_ident()
    real = (module_class.load, warp.capture_while, warp.capture_if, warp.get_suggested_block_size)
    mine = threading.get_ident

    def load(module: Any, device: Any, block_dim: Any = None, *args: Any, **kwargs: Any):
        if mine() != owner:
            return real[0](module, device, block_dim, *args, **kwargs)
        seen[(module, _variant(module, block_dim))] = None
        return None

    def suggested_block_size(kernel: Any, device: Any = None) -> tuple[int, int]:
        if mine() != owner:  # (swapping the load here could leave the recording one installed)
            return real[3](kernel, device)
        if not answer_queries and _query_loads(kernel, device):
            seen[(kernel.module, _variant(kernel.module, None))] = None
            return _placeholder_answer(device)
        module_class.load = real[0]
        try:
            return real[3](kernel, device)
        finally:
            module_class.load = load

    with _LISTING:
        module_class.load, warp.get_suggested_block_size = load, suggested_block_size
        warp.capture_while, warp.capture_if = _branches_run(owner, real[1], real[2])
        try:
            yield
        finally:
            module_class.load, warp.capture_while, warp.capture_if = real[:3]
            warp.get_suggested_block_size = real[3]


def _variant(module: Any, block_dim: Any) -> Any:
    """The block size of the variant that Warp's ``Module.load`` loads when given
    ``block_dim``: ``None`` is the module's own (``options["block_dim"]``)."""
    if block_dim is not None:
        return block_dim
    return getattr(module, "options", {}).get("block_dim")


def _branches_run(owner: int, real_while: Callable, real_if: Callable) -> tuple[Callable, ...]:
    """Warp's ``capture_while`` and ``capture_if`` as the listing thread ``owner`` runs them
    (a loop's body once, both branches of a conditional, no kernel deciding); other threads
    get Warp's own (``real_while``, ``real_if``)."""

    def capture_while(condition: Any, while_body: Callable, stream: Any = None, **kwargs: Any):
        if threading.get_ident() != owner:
            return real_while(condition, while_body, stream, **kwargs)
        return while_body(**kwargs)

    def capture_if(condition: Any, on_true: Any = None, on_false: Any = None, stream: Any = None,
                   **kwargs: Any) -> None:  # fmt: skip
        if threading.get_ident() != owner:
            return real_if(condition, on_true, on_false, stream, **kwargs)
        for branch in (on_true, on_false):
            if callable(branch):
                branch(**kwargs)
        return None

    return capture_while, capture_if


def _query_loads(kernel: Any, device: Any) -> bool:
    """Whether Warp's block-size query for ``kernel`` on ``device`` loads its module (on a GPU;
    a CPU is answered (1, 1) unasked, and a kernel of external constant parameters is asked
    without its module)."""
    import warp

    options = kernel.module.options | kernel.options
    if options.get("entry_point_abi", "warp") != "warp":
        return False
    return bool(warp.get_device(device).is_cuda)


def _placeholder_answer(device: Any) -> tuple[int, int]:
    """A block-size query's answer for the listing: 256 threads, one block per multiprocessor
    (the listing launches nothing, so only the launches' sizes see it)."""
    import warp

    return 256, max(1, int(getattr(warp.get_device(device), "sm_count", 1) or 1))


def listed_modules(run: Callable[[], Any], *, answer_queries: bool = True
                   ) -> dict[Any, list[Any]]:  # fmt: skip
    """The Warp modules that ``run`` (MuJoCo Warp's functions) would load, grouped by the
    block size of the variant each loads (a load without one is of the module's own, as in
    Warp), without running a kernel. A block-size query on a GPU loads (compiles) the module
    it asks about, one at a time; with ``answer_queries`` off it is answered with a
    placeholder and its module listed instead, so it can be compiled with the others (a
    variant listed twice is one compile)."""
    seen: dict[tuple[Any, Any], None] = {}
    with _loads_recorded(seen, answer_queries):
        run()
    groups: dict[Any, list[Any]] = {}
    for module, block_dim in seen:
        groups.setdefault(block_dim, []).append(module)
    return groups


def static_options(warp_option: Any) -> dict[str, Any]:
    """The plain (int and bool) fields of MJX's Warp options (``mjx.Model.opt._impl``), which
    can decide the kernels MuJoCo Warp makes (its iteration-limit warnings, for one)."""
    fields = getattr(warp_option, "__dataclass_fields__", {})
    return {name: value for name in fields
            if isinstance(value := getattr(warp_option, name), bool | int)}  # fmt: skip


def _mujoco_warp_step(mj_model: Any, options: dict[str, Any], njmax: int | None,
                      naconmax: int | None) -> Callable[[], Any]:  # fmt: skip
    """MuJoCo Warp's forward and step of ``mj_model`` for one world, as MJX calls them, with
    ``options`` (:func:`static_options`) set on the model's options where it has them."""
    import mujoco

    mjwarp = upstream.mjx_mujoco_warp()
    model = mjwarp.put_model(mj_model)
    for name, value in options.items():
        if hasattr(model.opt, name):
            setattr(model.opt, name, type(getattr(model.opt, name))(value))
    data = mjwarp.put_data(mj_model, mujoco.MjData(mj_model), nworld=1, njmax=njmax,
                           naconmax=naconmax)  # fmt: skip

    def run() -> None:
        mjwarp.forward(model, data)
        mjwarp.step(model, data)

    return run


#: Where the cgroups are mounted, and the file that names this process's own cgroups.
CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")


def cores(root: Path = CGROUP_ROOT, own: Path = PROC_CGROUP) -> int:
    """The CPU cores this process may use: those it may run on, at most its cgroup's CPU quota
    (:func:`cpu_quota`, rounded up; ``docker --cpus 2`` on a host of 64 cores is 2)."""
    count = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    quota = cpu_quota(root, own)
    if quota is not None:
        count = min(count or 1, math.ceil(quota))
    return max(1, count or 1)


def cpu_quota(root: Path = CGROUP_ROOT, own: Path = PROC_CGROUP) -> float | None:
    """The smallest CPU quota, in CPUs, of the cgroups over this process: cgroup v2's
    ``cpu.max`` ("QUOTA PERIOD"; "max": none) or v1's ``cpu.cfs_quota_us`` over
    ``cpu.cfs_period_us`` (-1: none), read at the mount's root (a container's own view) and at
    the process's own cgroup path named in ``own``; ``None``: no quota (or no file read)."""
    quotas = [quota for folder in _cgroup_folders(root, own)
              for quota in (_v2_quota(folder), _v1_quota(folder)) if quota]  # fmt: skip
    return min(quotas, default=None)


def _cgroup_folders(root: Path, own: Path) -> list[Path]:
    """Where a CPU quota of this process may be: the mount's root (v2) and its cpu controller's
    (v1), then this process's own cgroup and those above it under each (``/proc/self/cgroup``'s
    lines ``ID:CONTROLLERS:PATH``; v2's have no controllers)."""
    mounts = {"": [root], "cpu": [root / "cpu", root / "cpu,cpuacct", root / "cpuacct,cpu"]}
    folders = [*mounts[""], *mounts["cpu"]]
    try:
        lines = own.read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        _, controllers, path = [*line.split(":", 2), "", ""][:3]
        kind = "" if not controllers else "cpu" if "cpu" in controllers.split(",") else None
        if kind is None or not path.strip("/"):
            continue
        below = Path(path.strip("/"))
        for mount in mounts[kind]:
            folders += [mount / up for up in (below, *below.parents) if str(up) != "."]
    return folders


def _v2_quota(folder: Path) -> float | None:
    try:
        quota, period = (folder / "cpu.max").read_text().split()[:2]
        return int(quota) / int(period) if quota != "max" and int(period) > 0 else None
    except (OSError, ValueError):  # (no such file, or one not as expected: no limit)
        return None


def _v1_quota(folder: Path) -> float | None:
    try:
        quota = int((folder / "cpu.cfs_quota_us").read_text())
        period = int((folder / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota / period if quota > 0 and period > 0 else None


def default_workers() -> int:
    """One thread per CPU core this process may use, at most :data:`MAX_WORKERS`."""
    return min(cores(), MAX_WORKERS)


def _rank(job: tuple[Any, Any], parts: tuple[str, ...]) -> int:
    """The index in ``parts`` of the first that the name of ``job``'s module contains
    (``len(parts)``: none)."""
    name = str(getattr(job[0], "name", job[0]))
    return next((i for i, part in enumerate(parts) if part in name), len(parts))


def longest_first(groups: dict[Any, list[Any]]) -> list[tuple[Any, Any]]:
    """The ``(module, block size)`` pairs of ``groups`` (block size -> modules) in the order to
    compile them: those named in :data:`SLOW_FIRST` first, in its order, then the others as
    listed."""
    return sorted(((module, block_dim) for block_dim, modules in groups.items()
                   for module in modules), key=lambda job: _rank(job, SLOW_FIRST))  # fmt: skip


def _lower_priority() -> None:
    """This thread's CPU priority lowered by :data:`NICENESS` (Linux sets it per thread; where
    it cannot be set, nothing changes)."""
    try:
        thread = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, thread, os.getpriority(os.PRIO_PROCESS, thread) + NICENESS)
    except (AttributeError, OSError):  # (not Linux, or refused: the same compile, unranked)
        pass


class _Compiles:
    """What the threads of one :func:`_compile_modules` share: the modules they loaded, their
    failures, and when to take no new module (``cancel`` set, a failure, or the main thread
    ended: a process that stops waits for the modules in hand only)."""

    def __init__(self, device: Any, cancel: threading.Event | None) -> None:
        self.device, self.cancel = device, cancel
        self.loaded: list[tuple[Any, Any]] = []
        self.failures: list[BaseException] = []

    def stopped(self) -> bool:
        cancelled = self.cancel is not None and self.cancel.is_set()
        return bool(self.failures) or cancelled or not threading.main_thread().is_alive()

    def compile_one(self, job: tuple[Any, Any]) -> None:
        """Compiles and loads ``job``'s ``(module, block size)`` unless stopped; a failure is
        kept (raised by the caller, on its own thread)."""
        import warp

        if self.stopped():
            return
        try:
            warp.force_load(self.device, modules=[job[0]], block_dim=job[1], max_workers=0)
            self.loaded.append(job)
        except Exception as err:
            self.failures.append(err)

    def take(self, jobs: queue.SimpleQueue, later: threading.Event | None) -> None:
        """Compiles the ``jobs`` one at a time until none is left or stopped; with ``later``,
        only once it is set, at a lower CPU priority (:func:`_lower_priority`)."""
        if later is not None:
            while not later.wait(0.5):
                if self.stopped():
                    return
            _lower_priority()
        while not self.stopped():
            try:
                self.compile_one(jobs.get_nowait())
            except queue.Empty:
                return


def _compile_modules(groups: dict[Any, list[Any]], workers: int, device: Any = None,
                     cancel: threading.Event | None = None,
                     later: threading.Event | None = None) -> int:  # fmt: skip
    """Compiles and loads the modules of ``groups`` (block size -> modules) on Warp's ``device``
    (``None``: its default), ``workers`` threads taking one module at a time, the slowest first
    (:func:`longest_first`); returns how many it loaded. With ``later``, those named in
    :data:`HEAD_START` begin at once, a thread each, and the others once ``later`` is set, on
    threads of lower priority (:func:`_lower_priority`). A thread takes no new module once
    ``cancel`` is set or the main thread has ended; the first failure stops them all and is
    raised."""
    import warp

    jobs = longest_first(groups)
    head = [job for job in jobs if later is not None and _rank(job, HEAD_START) < len(HEAD_START)]
    rest: queue.SimpleQueue = queue.SimpleQueue()
    for job in jobs:
        if job not in head:
            rest.put(job)
    compiles = _Compiles(warp.get_device(device), cancel)
    threads = [threading.Thread(target=compiles.compile_one, args=(job,),
                                name=f"td3-jax-warp-compile-head-{i}")
               for i, job in enumerate(head)]  # fmt: skip
    threads += [threading.Thread(target=compiles.take, args=(rest, later),
                                 name=f"td3-jax-warp-compile-{i}")
                for i in range(max(1, workers - len(head)))]  # fmt: skip
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if compiles.failures:
        raise compiles.failures[0]
    return len(compiles.loaded)


class Listing(NamedTuple):
    """MuJoCo Warp's step of a model (:func:`list_step`): ``run`` steps one world, ``groups``
    are the modules it loads by block size (:func:`listed_modules`, block-size queries answered
    by a placeholder), ``device`` is Warp's device they are for."""

    run: Callable[[], Any]
    groups: dict[Any, list[Any]]
    device: Any


def list_step(mj_model: Any, options: dict[str, Any] | None = None, njmax: int | None = None,
              naconmax: int | None = None) -> Listing:  # fmt: skip
    """The :class:`Listing` of MuJoCo Warp's forward and step of ``mj_model`` (a
    ``mujoco.MjModel``) on Warp's default device, as :func:`precompile` takes them. Called on a
    thread that is not inside a ``warp.ScopedDevice`` (Warp's default device is the process's:
    MJX sets it to the CPU while it makes its data)."""
    import warp

    run = _mujoco_warp_step(mj_model, options or {}, njmax, naconmax)
    return Listing(run, listed_modules(run, answer_queries=False), warp.get_device())


def precompile(mj_model: Any, *, options: dict[str, Any] | None = None, njmax: int | None = None,
               naconmax: int | None = None, workers: int | None = None,
               cancel: threading.Event | None = None) -> Precompiled:  # fmt: skip
    """Compiles and loads the Warp modules of MuJoCo Warp's forward and step of ``mj_model``
    (a ``mujoco.MjModel``) on Warp's default device, ``workers`` at a time (default:
    :func:`default_workers`). ``njmax``/``naconmax``: the constraint and contact buffers the
    run uses (they decide which kernels some steps launch); ``options``: MJX's
    (:func:`static_options`); ``cancel``: once set, no further module is started. The count
    is of the modules loaded: :func:`list_step`, then :func:`compile_listed`."""
    start = time.perf_counter()
    listing = list_step(mj_model, options, njmax, naconmax)
    return compile_listed(listing, workers=workers, cancel=cancel, start=start)


def compile_listed(listing: Listing, *, workers: int | None = None,
                   cancel: threading.Event | None = None, later: threading.Event | None = None,
                   start: float | None = None) -> Precompiled:  # fmt: skip
    """Compiles and loads the modules of ``listing`` on its device, ``workers`` at a time
    (default: :func:`default_workers`); ``cancel``: once set, no further module is started;
    ``later``: only the :data:`HEAD_START` modules begin before it is set, the others after, at
    a lower CPU priority (:func:`_compile_modules`). ``start``: the ``time.perf_counter()`` the
    seconds count from (default: now).

    The listing answered MuJoCo Warp's block-size queries with a placeholder, so that the
    modules they ask about (the convex collision kernel, the slowest to compile) compile on the
    threads with the others instead of one at a time inside the listing. Those loaded, the
    step is listed again with real answers, and any module only that listing names is
    compiled too (:func:`_listed_again`)."""
    start = time.perf_counter() if start is None else start
    workers = workers or default_workers()
    loaded = _compile_modules(listing.groups, workers, listing.device, cancel, later)
    if cancel is None or not cancel.is_set():
        loaded += _listed_again(listing, workers, cancel)
    return Precompiled(loaded, time.perf_counter() - start)


def _listed_again(listing: Listing, workers: int, cancel: threading.Event | None) -> int:
    """How many modules the listing of ``listing.run`` with real block-size answers names
    beyond ``listing.groups`` (those the queries asked about are loaded by now), compiled on
    ``workers`` threads. A failure here is left to the module's first launch (which raises it,
    should it be real): the modules of ``listing.groups`` are loaded already."""
    try:
        extra = _not_in(listed_modules(listing.run), listing.groups)
        return _compile_modules(extra, workers, listing.device, cancel)
    except Exception:  # (an optimisation: the first launch compiles what is missing)
        return 0


def _not_in(groups: dict[Any, list[Any]], known: dict[Any, list[Any]]) -> dict[Any, list[Any]]:
    """The modules of ``groups`` (block size -> modules) that ``known`` has not."""
    left = {size: [m for m in modules if m not in known.get(size, ())]
            for size, modules in groups.items()}  # fmt: skip
    return {size: modules for size, modules in left.items() if modules}


class _Pending(NamedTuple):
    """A precompile running on its own thread (:func:`beside_compile`; counted by
    :func:`td3_jax.common.runtime.background_work_running`, so a stopped run exits without waiting
    for it): ``future`` gives its :class:`Precompiled` or raises its exception; ``cancel`` stops it
    taking further modules."""

    future: Future
    cancel: threading.Event


#: Where precompile_task runs its precompile on a thread: set inside beside_compile, per thread.
_BESIDE = threading.local()
#: The precompiles started beside a compile and not yet waited for (wait_ready).
_PENDING: list[_Pending] = []
#: Set once the caller has traced its programs (:func:`programs_traced`): a precompile started
#: beside a compile waits for it before the code generation of all but its :data:`HEAD_START`
#: modules, which holds the interpreter (all of them at once slow the tracing of T1's chunk
#: from 3 s to 7-20 s); XLA's compile, which follows, leaves the interpreter free.
_TRACED = threading.Event()
_TRACED.set()


@contextlib.contextmanager
def beside_compile() -> Iterator[None]:
    """Inside, unless :data:`BESIDE` is off (0, false, off, no), on :data:`BESIDE_MIN_CORES` cores,
    :func:`precompile_task` (called by this thread) lists the step's modules here (about half a
    second), starts them on threads of their own and returns: the :data:`HEAD_START` ones begin
    at once, the others once :func:`programs_traced`, :func:`wait_ready` or
    :func:`drop_pending` is called (where :func:`head_start_cached`, all of it, the listing
    too, waits so, and it returns at once); :func:`wait_ready` waits for them. A training run
    makes its environment inside, then traces its programs and compiles them while Warp's
    kernels compile. An exception leaving it drops the precompiles started inside
    (:func:`drop_pending`)."""
    before = getattr(_BESIDE, "on", False)
    _BESIDE.on = True
    _TRACED.clear()
    try:
        yield
    except BaseException:  # (the caller will not wait for them)
        drop_pending()
        raise
    finally:
        _BESIDE.on = before


def wait_ready(stop: Any = None) -> list[Precompiled]:
    """Waits for every precompile started beside a compile, says for each how long it took and
    how long this waited (a failure: the warning :func:`precompile_task` gives), and returns
    those that finished. Nothing started: ``[]`` at once. ``stop`` (a
    :class:`~td3_jax.common.runtime.StopToken`): once set, the precompiles are dropped
    (:func:`drop_pending`) and it raises as the token does."""
    done = []
    _TRACED.set()
    try:
        while _PENDING:
            pending, start = _PENDING[0], time.perf_counter()
            try:
                outcome = runtime.result(pending.future, stop)
            except Exception as err:  # (the precompile's own failure: a warning)
                outcome = err
            _PENDING.pop(0)
            if isinstance(outcome, Exception):
                _warn_failed(outcome)
                continue
            _say_ready(outcome, f"; waited {time.perf_counter() - start:.0f} s for them")
            done.append(outcome)
    except BaseException:
        drop_pending()
        raise
    return done


def drop_pending() -> None:
    """Stops every precompile started beside a compile from taking further modules and forgets
    it (a run that ends before its first physics step: nothing is said of them); a process
    that ends need not wait for the compiles in hand (:func:`~td3_jax.common.runtime.drop`)."""
    while _PENDING:
        pending = _PENDING.pop()
        pending.cancel.set()
        runtime.drop(pending.future)  # (a compile in hand is not waited for at exit)
    _TRACED.set()


def programs_traced() -> None:
    """Lets the precompiles started beside a compile (:func:`beside_compile`) begin: the
    caller's programs are traced and XLA compiles them now. (:func:`wait_ready` and
    :func:`drop_pending` also let them.) The caller does no more MJX or Warp work until
    :func:`wait_ready`: a second listing of the step (:func:`compile_listed`) launches on
    Warp's process-wide default device, which MJX sets to the CPU while it makes its data."""
    _TRACED.set()


def _warn_failed(err: BaseException) -> None:
    print(f"td3-jax: warning: MuJoCo Warp's kernels were not compiled ahead ({err}); each "
          "compiles at its first use instead", file=sys.stderr)  # fmt: skip


def _say_ready(done: Precompiled, waited: str = "") -> None:
    if done.seconds >= 1.0:
        print(f"MuJoCo Warp: {done.modules} kernel modules ready in {done.seconds:.0f} s "
              f"(compiled on {default_workers()} threads, or loaded from its cache{waited})",
              flush=True)  # fmt: skip


def _task_model(task: Any) -> tuple[Any, dict[str, Any]]:
    """The task's ``mujoco.MjModel`` and MJX's Warp options for it, read now (the caller's
    thread may later swap the task's model while it traces)."""
    return task.mj_model, static_options(upstream.mjx_warp_options(upstream.task_mjx_model(task)))


def _task_precompile(task: Any, njmax: int | None, naconmax: int | None) -> Precompiled:
    mj_model, options = _task_model(task)
    return precompile(mj_model, options=options, njmax=njmax, naconmax=naconmax)


def _start_beside(task: Any, njmax: int | None, naconmax: int | None) -> None:
    """The task's precompile started on a thread of its own (:data:`_PENDING`); a failure to
    start it is :func:`precompile_task`'s warning. Its listing is made here, on the caller's
    thread, and its :data:`HEAD_START` modules begin at once, unless Warp's kernel cache holds
    one of them already (:func:`head_start_cached`): the start is then likely warm, and the
    whole precompile, its listing too, waits for the caller's programs to be traced."""
    try:
        start, (mj_model, options) = time.perf_counter(), _task_model(task)
        cancel = threading.Event()
        if head_start_cached():
            work = functools.partial(_once_traced, functools.partial(
                precompile, mj_model, options=options, njmax=njmax, naconmax=naconmax,
                cancel=cancel), cancel)  # fmt: skip
        else:
            work = functools.partial(compile_listed, list_step(mj_model, options, njmax, naconmax),
                                     cancel=cancel, later=_TRACED, start=start)  # fmt: skip
        future = runtime.in_background(work, name="td3-jax warp precompile")
    except Exception as err:  # (an optimisation: the run goes on without it)
        _warn_failed(err)
        return
    _PENDING.append(_Pending(future, cancel))


def _once_traced(work: Callable[[], Precompiled], cancel: threading.Event) -> Precompiled:
    """``work()`` once the caller's programs are traced (:data:`_TRACED`); nothing (0 modules)
    where it was dropped (``cancel``) meanwhile."""
    _TRACED.wait()
    return Precompiled(0, 0.0) if cancel.is_set() else work()


def head_start_cached(cache: str | os.PathLike | None = None) -> bool:
    """Whether Warp's kernel cache (``cache``, default: Warp's ``config.kernel_cache_dir``)
    holds a GPU build of a module named in :data:`HEAD_START`, of any model: a folder named
    after it with a ``.cubin`` or ``.ptx`` file in it (not a build under way, whose folder ends
    ``_p<process>_t<thread>``). Where it does, a start is likely warm: the head start's
    listing on the caller's thread (about half a second on an H200) would cost more than it
    saves."""
    if cache is None:
        import warp

        cache = warp.config.kernel_cache_dir
    try:
        folders = [entry for entry in os.scandir(cache) if entry.is_dir()] if cache else []
    except OSError:  # (no cache folder yet: nothing cached)
        return False
    named = [folder for folder in folders if any(part in folder.name for part in HEAD_START)
             and not re.search(r"_p\d+_t\d+$", folder.name)]  # fmt: skip
    return any(_holds_gpu_build(folder.path) for folder in named)


def _holds_gpu_build(folder: str) -> bool:
    try:
        return any(name.endswith((".cubin", ".ptx")) for name in os.listdir(folder))
    except OSError:
        return False


def precompile_task(task: Any, *, njmax: int | None, naconmax: int | None) -> Precompiled | None:
    """:func:`precompile` for the Playground ``task`` (an ``MjxEnv`` on Warp), with the options
    of the MJX model it simulates; ``njmax``: its constraints per environment, ``naconmax``:
    contacts for one environment. Says how long it took where that was a second or more. Off
    (``None``) where :data:`PRECOMPILE` is off (0, false, off, no); a failure is a warning
    (``None``): each module is then compiled at its first launch, as without it. Inside
    :func:`beside_compile`, with :data:`BESIDE` not off, on a machine of
    :data:`BESIDE_MIN_CORES` cores or more: started on a thread of its own (``None`` at once;
    :func:`wait_ready` reports it)."""
    if runtime.env_switch(PRECOMPILE) is False:
        return None
    beside = runtime.env_switch(BESIDE) is not False and cores() >= BESIDE_MIN_CORES
    if getattr(_BESIDE, "on", False) and beside:
        _start_beside(task, njmax, naconmax)
        return None
    try:
        done = _task_precompile(task, njmax, naconmax)
    except Exception as err:  # (an optimisation: the run goes on without it)
        _warn_failed(err)
        return None
    _say_ready(done)
    return done
