"""MuJoCo Warp's kernel precompile as a run drives it: off by its variable, on a thread of its
own beside XLA's compile (started once the programs are traced), the order and the listings of
its compile, and the CPU cores it counts. Warp itself is not needed: the precompile, or Warp's
functions it calls, are replaced where they would run."""

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


def test_beside_a_compile_the_precompile_runs_on_its_own_thread_until_waited_for(
    monkeypatch, capsys
):
    """Inside ``beside_compile``, on 8 cores (TD3_JAX_WARP_BESIDE unset), the task's precompile
    starts on another thread and the caller goes on at once; it begins its work once the
    caller says its programs are traced (``programs_traced``); ``wait_ready`` waits for it and
    says so; a failure there is the usual warning; an error leaving the block drops it.
    Outside, with the variable 0, or on 2 cores, it runs on the caller's thread."""
    import threading

    from td3_jax.common import runtime
    from td3_jax.envs import warp_kernels

    unblock, ran_on = threading.Event(), []

    def slow(task, njmax, naconmax):
        ran_on.append(threading.get_ident())
        assert task == "quick" or unblock.wait(10)
        if task == "broken":
            raise RuntimeError("no such kernel")
        return warp_kernels.Precompiled(modules=njmax, seconds=2.0)

    def precompile(mj_model, options, njmax, naconmax, cancel=None):
        return slow(mj_model, njmax, naconmax)

    monkeypatch.setattr(warp_kernels, "_task_model", lambda task: (task, {}))
    monkeypatch.setattr(warp_kernels, "precompile", precompile)
    monkeypatch.setattr(warp_kernels, "cores", lambda: 8)
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
    assert warp_kernels._PENDING and not warp_kernels._PENDING[0].future.done()  # (running)
    assert runtime.background_work_running()  # (a stopped run exits without waiting for it)
    time.sleep(0.3)
    assert len(ran_on) == 3  # (it has not begun: the caller's programs are not traced yet)
    warp_kernels.programs_traced()
    for _ in range(100):  # (now it begins, and waits for `unblock`)
        if len(ran_on) == 4:
            break
        time.sleep(0.05)
    assert len(ran_on) == 4 and ran_on[3] != threading.get_ident()
    unblock.set()
    assert warp_kernels.wait_ready() == [warp_kernels.Precompiled(37, 2.0)]
    assert ran_on[3] != threading.get_ident()
    out = capsys.readouterr().out
    assert "MuJoCo Warp: 37 kernel modules ready in 2 s" in out and "waited" in out
    assert warp_kernels.wait_ready() == [] and capsys.readouterr().out == ""  # (nothing left)

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

    # an error leaving beside_compile (the run will not wait) drops what it started
    with pytest.raises(RuntimeError, match="busy"), warp_kernels.beside_compile():
        warp_kernels.precompile_task("t1", njmax=9, naconmax=1)
        raise RuntimeError("busy run directory")
    assert not warp_kernels._PENDING

    assert warp_kernels.precompile_task("t1", njmax=5, naconmax=1) == (5, 2.0)
    assert ran_on[-1] == threading.get_ident() and not warp_kernels._PENDING


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
    fake_warp = SimpleNamespace(get_device=lambda: "gpu",
                                force_load=lambda device, modules, **kw: started.append(modules))
    monkeypatch.setitem(sys.modules, "warp", fake_warp)
    monkeypatch.setattr(warp_kernels, "SLOW_FIRST", ("solver",))
    assert warp_kernels._compile_modules(groups, workers=1) == 5
    assert started[0] == [solver] and len(started) == 5


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

    def compile_modules(groups, workers, cancel=None):
        compiled.append(groups)
        return sum(len(modules) for modules in groups.values())

    monkeypatch.setattr(warp_kernels, "_mujoco_warp_step", lambda *args: "step")
    monkeypatch.setattr(warp_kernels, "listed_modules", listed)
    monkeypatch.setattr(warp_kernels, "_compile_modules", compile_modules)
    done = warp_kernels.precompile("model", workers=2)
    assert listings == [False, True] and done.modules == 5
    assert compiled == [{None: ["a", "b"], 64: ["c"]}, {None: ["d"], 64: ["e"]}]
    listings.clear()
    cancel = threading.Event()
    cancel.set()
    assert warp_kernels.precompile("model", workers=2, cancel=cancel).modules == 3
    assert listings == [False]  # (a second listing would compile the queried modules itself)

    def second_fails(groups, workers, cancel=None):  # (left to the modules' first launch)
        if compiled:
            raise RuntimeError("nvrtc: error")
        return compile_modules(groups, workers, cancel)

    compiled.clear()
    monkeypatch.setattr(warp_kernels, "_compile_modules", second_fails)
    assert warp_kernels.precompile("model", workers=2).modules == 3
