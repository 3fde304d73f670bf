"""MuJoCo Warp's kernel precompile as a run drives it: off by its variable, on threads of its
own beside XLA's compile (the head start at once, the other modules once the programs are
traced), the order and the listings of its compile, and the CPU cores it counts. Warp itself
is not needed: the precompile, or Warp's functions it calls, are replaced where they would
run."""

from __future__ import annotations

import sys
import threading
import time
from types import SimpleNamespace

import pytest


def test_the_precompile_is_off_by_its_variable_and_a_failure_is_a_warning(monkeypatch, capsys):
    from td3_jax.envs import warp_kernels

    class NotATask:
        mj_model = None

    monkeypatch.setenv(warp_kernels.PRECOMPILE, "0")
    assert warp_kernels.precompile_task(NotATask(), njmax=8, naconmax=8) is None
    assert capsys.readouterr().err == ""
    monkeypatch.delenv(warp_kernels.PRECOMPILE)
    assert warp_kernels.precompile_task(NotATask(), njmax=8, naconmax=8) is None
    err = capsys.readouterr().err
    assert err.startswith("td3-jax: warning: MuJoCo Warp's kernels were not compiled ahead (")
    assert err.rstrip().endswith("each compiles at its first use instead")


def _fake_precompiles(monkeypatch) -> SimpleNamespace:
    """The task's precompile replaced where it would run Warp: ``slow`` records its thread in
    ``ran_on`` and, but for the task "quick", waits for ``unblock``; "broken" fails. The fake
    ``list_step`` records its thread in ``listed_on``, the fake ``compile_listed`` the
    ``cancel`` it was given in ``cancels``. 8 cores; no head-start module cached."""
    from td3_jax.envs import warp_kernels

    fakes = SimpleNamespace(unblock=threading.Event(), ran_on=[], listed_on=[], cancels=[])

    def slow(task, njmax, naconmax):
        fakes.ran_on.append(threading.get_ident())
        assert task == "quick" or fakes.unblock.wait(10)
        if task == "broken":
            raise RuntimeError("no such kernel")
        return warp_kernels.Precompiled(modules=njmax, seconds=2.0)

    def precompile(mj_model, options, njmax, naconmax, cancel=None):
        return slow(mj_model, njmax, naconmax)

    def list_step(mj_model, options, njmax, naconmax):
        fakes.listed_on.append(threading.get_ident())
        return warp_kernels.Listing(mj_model, {None: [njmax]}, "gpu")

    def compile_listed(listing, *, cancel=None, later=None, start=None):
        assert later is warp_kernels._TRACED and not later.is_set() and start is not None
        fakes.cancels.append(cancel)
        return slow(listing.run, listing.groups[None][0], None)

    monkeypatch.setattr(warp_kernels, "_task_model", lambda task: (task, {}))
    monkeypatch.setattr(warp_kernels, "precompile", precompile)
    monkeypatch.setattr(warp_kernels, "list_step", list_step)
    monkeypatch.setattr(warp_kernels, "compile_listed", compile_listed)
    monkeypatch.setattr(warp_kernels, "cores", lambda: 8)
    monkeypatch.setattr(warp_kernels, "head_start_cached", lambda: False)
    return fakes


def test_beside_a_compile_the_precompile_runs_on_its_own_thread_until_waited_for(
    monkeypatch, capsys
):
    """Inside ``beside_compile``, on 8 cores (TD3_JAX_WARP_BESIDE unset), the task's step is
    listed on the caller's thread (outside MJX's CPU-device scopes) and its modules compile on
    another thread, told to hold all but the head start until the caller says its programs are
    traced (``programs_traced``); the caller goes on at once; ``wait_ready`` waits for it and
    says so; a failure there is the usual warning; an error leaving the block drops it.
    Outside, with the variable 0, or on 2 cores, it runs on the caller's thread."""
    from td3_jax.common import runtime
    from td3_jax.envs import warp_kernels

    fakes = _fake_precompiles(monkeypatch)
    unblock, ran_on, listed_on = fakes.unblock, fakes.ran_on, fakes.listed_on
    for off in ("0", "Off"):
        monkeypatch.setenv(warp_kernels.BESIDE, off)
        with warp_kernels.beside_compile():  # (turned off: run first, as outside)
            assert warp_kernels.precompile_task("quick", njmax=3, naconmax=4) == (3, 2.0)
    monkeypatch.delenv(warp_kernels.BESIDE)
    monkeypatch.setattr(warp_kernels, "cores", lambda: 2)  # (too few cores: the same)
    with warp_kernels.beside_compile():
        assert warp_kernels.precompile_task("quick", njmax=3, naconmax=4) == (3, 2.0)
    assert ran_on == [threading.get_ident()] * 3 and not warp_kernels._PENDING
    monkeypatch.setattr(warp_kernels, "cores", lambda: 8)
    with warp_kernels.beside_compile():
        assert warp_kernels.precompile_task("t1", njmax=37, naconmax=4) is None
    assert listed_on == [threading.get_ident()]  # (listed here, before the caller traces)
    assert warp_kernels._PENDING and not warp_kernels._PENDING[0].future.done()  # (running)
    assert runtime.background_work_running()  # (a stopped run exits without waiting for it)
    for _ in range(100):  # (it began at once, and waits for `unblock`)
        if len(ran_on) == 4:
            break
        time.sleep(0.05)
    assert len(ran_on) == 4 and ran_on[3] != threading.get_ident()
    warp_kernels.programs_traced()
    unblock.set()
    assert warp_kernels.wait_ready() == [warp_kernels.Precompiled(37, 2.0)]
    assert ran_on[3] != threading.get_ident()
    out = capsys.readouterr().out
    assert "MuJoCo Warp: 37 kernel modules ready in 2 s" in out and "waited" in out
    assert warp_kernels.wait_ready() == [] and capsys.readouterr().out == ""  # (nothing left)


def test_a_precompile_beside_a_compile_that_fails_or_cannot_start_is_a_warning(
    monkeypatch, capsys
):
    """A failure of the compile is the usual warning at ``wait_ready``; a failure to start it
    (reading the task's model, or listing its step on the caller's thread) is the warning at
    once, nothing left pending; an error leaving ``beside_compile`` drops what it started; and
    outside it the precompile runs on the caller's thread."""
    from td3_jax.envs import warp_kernels

    fakes = _fake_precompiles(monkeypatch)
    fakes.unblock.set()
    with warp_kernels.beside_compile():
        warp_kernels.precompile_task("broken", njmax=1, naconmax=1)
    assert warp_kernels.wait_ready() == []
    assert "not compiled ahead (no such kernel)" in capsys.readouterr().err

    def no_model(task):
        raise RuntimeError("no model here")

    with monkeypatch.context() as patched, warp_kernels.beside_compile():
        patched.setattr(warp_kernels, "_task_model", no_model)  # (failing to start: a warning)
        assert warp_kernels.precompile_task("t1", njmax=1, naconmax=1) is None
    assert not warp_kernels._PENDING and "(no model here)" in capsys.readouterr().err

    def unlisted(*args):
        raise RuntimeError("no step to list")

    with monkeypatch.context() as patched, warp_kernels.beside_compile():
        patched.setattr(warp_kernels, "list_step", unlisted)
        assert warp_kernels.precompile_task("t1", njmax=1, naconmax=1) is None
    assert not warp_kernels._PENDING and "(no step to list)" in capsys.readouterr().err

    # an error leaving beside_compile (the run will not wait) drops what it started
    with pytest.raises(RuntimeError, match="busy"), warp_kernels.beside_compile():
        warp_kernels.precompile_task("t1", njmax=9, naconmax=1)
        raise RuntimeError("busy run directory")
    assert not warp_kernels._PENDING

    assert warp_kernels.precompile_task("t1", njmax=5, naconmax=1) == (5, 2.0)
    assert fakes.ran_on[-1] == threading.get_ident() and not warp_kernels._PENDING


def test_a_dropped_precompile_is_cancelled_and_an_exit_does_not_wait_for_it(monkeypatch):
    """A run that ends before its first step drops its precompile: the compile is told to stop
    (the ``cancel`` it was given is set), and the work still in hand is marked dropped, so the
    command's exit, even a failure's, ends the process at once (os._exit) instead of joining a
    collision kernel's compile; once that work ends, nothing is left marked."""
    from td3_jax.cli import interrupts
    from td3_jax.common import runtime
    from td3_jax.envs import warp_kernels

    fakes, exits = _fake_precompiles(monkeypatch), []

    def fake_exit(code):
        exits.append(code)
        raise SystemExit(code)

    monkeypatch.setattr(interrupts, "leave_processes", lambda wait_s: True)
    monkeypatch.setattr(interrupts.os, "_exit", fake_exit)
    with pytest.raises(RuntimeError, match="busy"), warp_kernels.beside_compile():
        warp_kernels.precompile_task("t1", njmax=9, naconmax=1)
        raise RuntimeError("busy run directory")
    assert not warp_kernels._PENDING and fakes.cancels[-1].is_set()
    assert runtime.dropped_work_running()  # (the fake compile waits for `unblock`)
    with pytest.raises(SystemExit):
        interrupts.exit_process(None, 2, abandon_work=False)
    assert exits == [2]
    fakes.unblock.set()
    for _ in range(100):
        if not runtime.dropped_work_running():
            break
        time.sleep(0.05)
    assert not runtime.dropped_work_running()
    with pytest.raises(SystemExit):  # (nothing dropped runs: a plain exit)
        interrupts.exit_process(None, 2, abandon_work=False)
    assert exits == [2]


def test_with_a_head_start_module_cached_the_whole_precompile_waits_for_the_tracing(
    monkeypatch,
):
    """A head-start module in Warp's cache (likely a warm start): nothing is listed on the
    caller's thread, and the precompile begins only once the programs are traced."""
    from td3_jax.envs import warp_kernels

    fakes = _fake_precompiles(monkeypatch)
    monkeypatch.setattr(warp_kernels, "head_start_cached", lambda: True)
    with warp_kernels.beside_compile():
        assert warp_kernels.precompile_task("quick", njmax=6, naconmax=1) is None
    time.sleep(0.3)
    assert fakes.listed_on == [] and fakes.ran_on == []  # (not begun)
    warp_kernels.programs_traced()
    assert warp_kernels.wait_ready() == [warp_kernels.Precompiled(6, 2.0)]
    assert fakes.ran_on and fakes.ran_on[0] != threading.get_ident()


def test_a_head_start_module_in_warps_cache_is_found_by_its_gpu_build(tmp_path):
    """A folder named after a HEAD_START module counts where it holds a .cubin or .ptx file;
    not a CPU build, an empty folder, a build under way (``_p<pid>_t<tid>``) or other modules."""
    from td3_jax.envs import warp_kernels

    def folder(name: str, *files: str) -> None:
        (tmp_path / name).mkdir()
        for file in files:
            (tmp_path / name / file).write_text("")

    ccd = "wp_ccd_kernel_builder__locals__ccd_kernel_eff81976_6aab1fe"
    assert not warp_kernels.head_start_cached(tmp_path / "none yet")
    folder("wp_mujoco_warp._src.smooth_1a2b3c4", "wp_smooth.sm90.cubin")
    folder(ccd, f"{ccd}.cpu0eee9287.o", f"{ccd}.meta")
    folder(f"{ccd}_p4242_t1397", f"{ccd}.sm90.cubin")
    folder("wp_ccd_kernel_builder__locals__ccd_kernel_0badc0de_1234567")
    assert not warp_kernels.head_start_cached(tmp_path)
    folder("wp_ccd_kernel_builder__locals__ccd_kernel_eff81976_7bbb2ff", "x.sm90.ptx")
    assert warp_kernels.head_start_cached(tmp_path)


def test_the_cores_counted_are_at_most_the_cgroups_cpu_quota(tmp_path):
    """cgroup v2's cpu.max: "200000 100000" is 2 CPUs, "150000 100000" rounds up to 2, "max"
    is no limit; a missing or odd file is no limit either. v1's cfs quota over its period
    counts too (-1: none), as does a quota at the process's own cgroup path
    (/proc/self/cgroup), the smallest one found winning."""
    import os

    from td3_jax.envs import warp_kernels

    here = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    root, own = tmp_path / "cgroup", tmp_path / "self-cgroup"
    root.mkdir()
    assert warp_kernels.cores(root, own) == here  # (nothing to read: no limit)
    for text, limit in [("200000 100000\n", 2), ("150000 100000\n", 2), ("50000 100000", 1),
                        ("max 100000\n", here), ("nonsense", here)]:  # fmt: skip
        (root / "cpu.max").write_text(text)
        assert warp_kernels.cores(root, own) == min(here, limit), text
    (root / "cpu.max").write_text("max 100000\n")
    v1 = root / "cpu,cpuacct"
    v1.mkdir()
    (v1 / "cpu.cfs_period_us").write_text("100000\n")
    for quota, limit in [("-1\n", here), ("250000\n", 3)]:
        (v1 / "cpu.cfs_quota_us").write_text(quota)
        assert warp_kernels.cores(root, own) == min(here, limit), quota
        assert warp_kernels.cpu_quota(root, own) == (2.5 if quota == "250000\n" else None)
    (v1 / "cpu.cfs_quota_us").write_text("-1\n")
    job = root / "user.slice" / "job-7"
    job.mkdir(parents=True)
    (job / "cpu.max").write_text("100000 100000\n")  # (a v2 limit on this process's own group)
    own.write_text("0::/user.slice/job-7\n")
    assert warp_kernels.cores(root, own) == 1
    (job / "cpu.max").write_text("max 100000\n")
    (root / "user.slice" / "cpu.max").write_text("200000 100000\n")  # (on a group above it)
    assert warp_kernels.cores(root, own) == min(here, 2)
    v1_job = root / "cpuacct,cpu" / "docker" / "abc"
    v1_job.mkdir(parents=True)
    (v1_job / "cpu.cfs_quota_us").write_text("100000\n")
    (v1_job / "cpu.cfs_period_us").write_text("100000\n")
    own.write_text("5:cpuacct,cpu:/docker/abc\n")  # (v1, the controllers in the other order)
    assert warp_kernels.cores(root, own) == 1
    own.write_text("0::/\n4:memory:/user.slice/job-7\n")  # (a root path; no cpu controller)
    assert warp_kernels.cores(root, own) == here


class _Module:
    """What the precompile reads of a Warp module: its name and options."""

    def __init__(self, name: str, block_dim: int = 256):
        self.name, self.options = name, {"block_dim": block_dim}


def test_the_slowest_modules_are_compiled_first_in_the_listed_order_otherwise(monkeypatch):
    from td3_jax.envs import warp_kernels

    first, solver, ccd = _Module("a"), _Module("x._src.solver"), _Module("ccd_kernel_ab12")
    smooth, last = _Module("mujoco_warp._src.smooth"), _Module("b")
    groups = {None: [first, solver, smooth], 64: [last, ccd]}
    named = [(job[0].name, job[1]) for job in warp_kernels.longest_first(groups)]
    assert named == [("ccd_kernel_ab12", 64), ("mujoco_warp._src.smooth", None),
                     ("x._src.solver", None), ("a", None), ("b", 64)]  # fmt: skip
    monkeypatch.setattr(warp_kernels, "SLOW_FIRST", ())
    assert warp_kernels.longest_first(groups) == [(first, None), (solver, None), (smooth, None),
                                                  (last, 64), (ccd, 64)]  # fmt: skip
    started = []
    fake_warp = SimpleNamespace(get_device=lambda device=None: device or "gpu",
                                force_load=lambda device, modules, **kw: started.append(modules))
    monkeypatch.setitem(sys.modules, "warp", fake_warp)
    monkeypatch.setattr(warp_kernels, "SLOW_FIRST", ("solver",))
    assert warp_kernels._compile_modules(groups, workers=1) == 5
    assert started[0] == [solver] and len(started) == 5


def test_the_head_start_compiles_before_the_caller_is_traced_and_the_rest_after_ranked_lower(
    monkeypatch,
):
    """With ``later``: the modules named in HEAD_START begin at once, a thread each, at the
    caller's priority; the others only once ``later`` is set, on threads whose niceness rises
    by NICENESS (Linux's per-thread priority), all on the device given. A cancel while they
    wait: none of the others is compiled."""
    from td3_jax.envs import warp_kernels

    ccd, smooth, other = _Module("ccd_kernel_ab12"), _Module("x._src.smooth"), _Module("b")
    groups = {None: [smooth, other], 64: [ccd]}
    loads, lowered, head_loaded = [], [], threading.Event()

    def force_load(device, modules, block_dim=None, max_workers=None):
        loads.append((device, modules[0].name, block_dim, threading.current_thread().name))
        if modules[0] is ccd:
            head_loaded.set()

    fake_warp = SimpleNamespace(get_device=lambda device=None: device, force_load=force_load)
    monkeypatch.setitem(sys.modules, "warp", fake_warp)
    monkeypatch.setattr(warp_kernels, "_lower_priority",
                        lambda: lowered.append(threading.current_thread().name))  # fmt: skip
    later = threading.Event()
    done = []
    worker = threading.Thread(target=lambda: done.append(warp_kernels._compile_modules(
        groups, 3, "cuda:1", later=later)), daemon=True)  # fmt: skip
    worker.start()
    assert head_loaded.wait(10)
    time.sleep(0.2)
    assert [load[1:3] for load in loads] == [("ccd_kernel_ab12", 64)] and not lowered
    later.set()
    worker.join(10)
    assert not worker.is_alive()
    assert done == [3] and {load[0] for load in loads} == {"cuda:1"}
    assert sorted(load[1] for load in loads[1:]) == ["b", "x._src.smooth"]
    assert len(lowered) == 2 and loads[0][3] not in lowered  # (two waiting threads, lowered)
    assert all(load[3] in lowered for load in loads[1:])

    loads.clear()
    cancel, later = threading.Event(), threading.Event()
    worker = threading.Thread(target=lambda: done.append(warp_kernels._compile_modules(
        groups, 3, "cuda:0", cancel=cancel, later=later)), daemon=True)  # fmt: skip
    worker.start()
    assert head_loaded.wait(10)
    cancel.set()
    worker.join(10)
    assert not worker.is_alive() and done[-1] <= 1 and all(load[1] != "b" for load in loads)
    monkeypatch.setattr(warp_kernels, "HEAD_START", ())  # (none named: all wait for `later`)
    loads.clear()
    later = threading.Event()
    worker = threading.Thread(target=lambda: warp_kernels._compile_modules(
        groups, 2, "cuda:0", later=later), daemon=True)  # fmt: skip
    worker.start()
    time.sleep(0.3)
    assert loads == []
    later.set()
    worker.join(10)
    assert len(loads) == 3


def test_lowering_a_threads_priority_raises_its_niceness_by_the_constant(monkeypatch):
    """On Linux a thread's niceness is its own: the compile threads' ``_lower_priority`` adds
    NICENESS to this thread's and leaves the process's other threads as they were."""
    import os

    from td3_jax.envs import warp_kernels

    if not hasattr(os, "getpriority"):
        pytest.skip("no per-thread priority here")
    main_before, seen = os.getpriority(os.PRIO_PROCESS, 0), []

    def lower():
        thread = threading.get_native_id()
        before = os.getpriority(os.PRIO_PROCESS, thread)
        warp_kernels._lower_priority()
        seen.append((before, os.getpriority(os.PRIO_PROCESS, thread)))

    thread = threading.Thread(target=lower)
    thread.start()
    thread.join()
    before, after = seen[0]
    assert after == min(19, before + warp_kernels.NICENESS)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main_before


def test_the_listing_records_loads_as_warp_resolves_them_and_answers_gpu_queries_itself(
    monkeypatch,
):
    """A load without a block size is of the module's own (as Warp's ``Module.load``), so a
    module loaded both ways is one compile; with ``answer_queries`` off, a GPU's block-size
    query is answered with a placeholder and its module's own variant listed, without asking
    Warp (which would compile it there and then); on, Warp answers, its load the real one."""
    from td3_jax.common import upstream
    from td3_jax.envs import warp_kernels

    class FakeModuleClass:  # (Warp's Module: its load is what the listing replaces)
        def load(self, device, block_dim=None):
            raise AssertionError("no module is loaded while listed")

    class Module(FakeModuleClass, _Module):
        pass

    own, other = Module("own", 128), Module("other", 256)
    kernel = SimpleNamespace(module=own, options={})
    asked = []

    def real_query(kernel, device=None):  # (Warp's: loads the module's own variant, then asks)
        asked.append(FakeModuleClass.load is real_load)
        return 64, 3

    real_load = FakeModuleClass.load
    gpu = SimpleNamespace(is_cuda=True, sm_count=132)
    monkeypatch.setitem(sys.modules, "warp", SimpleNamespace(
        capture_while=None, capture_if=None, get_suggested_block_size=real_query,
        get_device=lambda device=None: gpu))  # fmt: skip
    monkeypatch.setattr(upstream, "warp_module_class", lambda: FakeModuleClass)
    answers = []

    def run():
        warp = sys.modules["warp"]
        for module, size in ((own, None), (own, 128), (other, None), (other, 64)):
            module.load("cuda:0", size)
        answers.append(warp.get_suggested_block_size(kernel, "cuda:0"))

    listed = warp_kernels.listed_modules(run, answer_queries=False)
    assert listed == {128: [own], 256: [other], 64: [other]}
    assert answers == [(256, 132)] and asked == []
    assert warp_kernels.listed_modules(run) == listed
    assert answers[-1] == (64, 3) and asked == [True]
    assert FakeModuleClass.load is real_load and sys.modules["warp"].get_suggested_block_size is (
        real_query
    )
    gpu.is_cuda = False  # (a CPU: Warp answers (1, 1) without loading; the listing asks it)
    warp_kernels.listed_modules(run, answer_queries=False)
    assert asked == [True, True]


def test_the_precompile_compiles_what_the_second_listing_adds_unless_cancelled(monkeypatch):
    from td3_jax.envs import warp_kernels

    listings, compiled = [], []

    def listed(run, *, answer_queries=True):
        listings.append(answer_queries)
        return {None: ["a", "b"], 64: ["c"]} if not answer_queries else {None: ["b", "d"],
                                                                         64: ["c", "e"]}

    def compile_modules(groups, workers, device=None, cancel=None, later=None):
        compiled.append((groups, device))
        return sum(len(modules) for modules in groups.values())

    monkeypatch.setitem(sys.modules, "warp", SimpleNamespace(get_device=lambda: "cuda:0"))
    monkeypatch.setattr(warp_kernels, "_mujoco_warp_step", lambda *args: "step")
    monkeypatch.setattr(warp_kernels, "listed_modules", listed)
    monkeypatch.setattr(warp_kernels, "_compile_modules", compile_modules)
    done = warp_kernels.precompile("model", workers=2)
    assert listings == [False, True] and done.modules == 5
    assert compiled == [({None: ["a", "b"], 64: ["c"]}, "cuda:0"),
                        ({None: ["d"], 64: ["e"]}, "cuda:0")]  # (the listing's own device)
    listings.clear()
    cancel = threading.Event()
    cancel.set()
    assert warp_kernels.precompile("model", workers=2, cancel=cancel).modules == 3
    assert listings == [False]  # (a second listing would compile the queried modules itself)

    def second_fails(groups, workers, device=None, cancel=None, later=None):
        if compiled:  # (left to the modules' first launch)
            raise RuntimeError("nvrtc: error")
        return compile_modules(groups, workers, device, cancel)

    compiled.clear()
    monkeypatch.setattr(warp_kernels, "_compile_modules", second_fails)
    assert warp_kernels.precompile("model", workers=2).modules == 3
