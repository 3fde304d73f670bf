"""The MuJoCo Warp path end to end on Warp's CPU kernels (``TD3_JAX_WARP_ON_CPU=1``): a tiny T1
run trains on Warp and records it; one whose constraint buffer is too small stops with the
overflow message instead of simulating wrong physics. Skipped where Warp is not installed."""

from __future__ import annotations

import importlib.util
import json

import pytest
from support import main

from td3_jax.envs import physics

pytestmark = [
    pytest.mark.robots,
    pytest.mark.skipif(
        importlib.util.find_spec("warp") is None, reason="MuJoCo Warp (warp-lang) is not installed"
    ),
]

# (8-step episodes: the t1 preset evaluates inside the chunk, whose 8 iterations are one episode)
TINY_T1 = [
    "train", "--env", "playground/T1JoystickFlatTerrain", "--impl", "warp", "--num-envs", "4",
    "--total-steps", "64", "--eval-every", "32", "--warmup-steps", "16", "--batch-size", "16",
    "--eval-envs", "2", "--updates-per-iter", "1", "--hidden-sizes", "16", "16",
    "--actor-hidden-sizes", "16", "--critic-hidden-sizes", "16", "--num-atoms", "11",
    "--episode-length", "8", "--quiet",
]  # fmt: skip


@pytest.fixture
def warp_on_cpu(monkeypatch):
    monkeypatch.setenv(physics.WARP_ON_CPU, "1")


def test_a_tiny_robot_run_trains_on_warp_and_records_it(warp_on_cpu, tmp_path, capsys,
                                                        monkeypatch):  # fmt: skip
    """... with the kernels' precompile on a thread of its own beside the XLA compile, as on a
    machine of 8 cores or more (the default there)."""
    import threading

    from td3_jax.envs import warp_kernels

    ran_on, real = [], warp_kernels.precompile

    def precompile(*args, **kwargs):
        ran_on.append(threading.get_ident())
        return real(*args, **kwargs)

    monkeypatch.setattr(warp_kernels, "cores", lambda *args: 8)
    monkeypatch.setattr(warp_kernels, "precompile", precompile)
    out = tmp_path / "run"
    code, stdout, err = main([*TINY_T1, "--out", str(out)], capsys)
    assert code == 0, err
    assert len(ran_on) == 1 and ran_on[0] != threading.get_ident()  # (beside, then waited for)
    assert not warp_kernels._PENDING
    assert "physics: MuJoCo Warp (--impl warp)" in stdout
    assert "not compiled ahead" not in err  # (the kernels' precompile worked)
    saved = json.loads((out / "config.json").read_text())
    assert saved["impl"] == "warp" and saved["njmax"] is None
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in records] == [32, 64]
    assert all(r["physics_overflow"] == 0 for r in records)
    assert all(r["critic_loss"] == r["critic_loss"] for r in records)  # finite, not NaN


def test_a_constraint_buffer_too_small_stops_the_run_naming_the_flag(warp_on_cpu, tmp_path, capsys):
    """2 constraints per T1 (it needs about 60): every step overflows; the run stops after the
    first chunk with exit code 3 and no record of it. The chunk's 8 steps of 4 training and 2
    evaluation robots are counted."""
    out = tmp_path / "run"
    code, _, err = main([*TINY_T1, "--njmax", "2", "--out", str(out)], capsys)
    assert code == 3, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("td3-jax: error: MuJoCo Warp's contact or constraint buffer was full in")
    assert "48 environment steps of the chunk ending at env step 32" in last
    assert "raise --nconmax or --njmax" in last
    assert not (out / "metrics.jsonl").exists() or not (out / "metrics.jsonl").read_text()


def _modules_loaded_by(run) -> set[str]:
    """The names of the Warp modules that ``run`` loads (or finds loaded) as it launches."""
    from warp._src.context import Module

    names: set[str] = set()
    load = Module.load

    def recording(self, *args, **kwargs):
        names.add(self.name)
        return load(self, *args, **kwargs)

    Module.load = recording
    try:
        run()
    finally:
        Module.load = load
    return names


def test_the_precompile_lists_every_module_a_robot_step_launches(warp_on_cpu, monkeypatch):
    """MuJoCo Warp's step listed without running a kernel (:func:`listed_modules`) names every
    module that a real reset and step of T1 through MJX launches (MJX's own glue apart), and
    the task made on Warp is handed to the precompile with its buffers' sizes."""
    import jax
    import jax.numpy as jnp

    from td3_jax.common import upstream
    from td3_jax.envs import locomotion, warp_kernels
    from td3_jax.envs.base import EnvOptions

    handed = []
    monkeypatch.setattr(warp_kernels, "precompile_task", lambda task, **sizes: handed.append(sizes))
    env, config = locomotion.load("T1JoystickFlatTerrain", impl="warp",
                                  options=EnvOptions(impl="warp", worlds=3))  # fmt: skip
    assert handed == [{"njmax": int(config.njmax), "naconmax": int(config.naconmax) // 8192}]
    task = env.unwrapped
    options = warp_kernels.static_options(upstream.task_mjx_model(task).opt._impl)
    assert options["warn_overflow"] & (1 << 9) == 0  # (td3-jax quiets the iteration limits)
    step = warp_kernels._mujoco_warp_step(task.mj_model, options, **handed[0])
    listed = {m.name for group in warp_kernels.listed_modules(step).values() for m in group}

    def real_steps():  # (3 environments: a batch no other test captured, so Python launches)
        state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(1), 3))
        jax.block_until_ready(jax.jit(jax.vmap(env.step))(state, jnp.zeros((3, env.action_size))))

    launched = _modules_loaded_by(real_steps)
    assert len(launched) >= 20
    assert {name for name in launched if not name.startswith("mujoco.mjx.warp")} <= listed

    # On a GPU, Warp answers a block-size query by loading the module's default variant (on a
    # CPU it answers (1, 1) unasked): the listing lets that load happen, and goes on.
    import warp

    queried = []

    def cuda_like_query(kernel, device=None):
        exec_ = kernel.module.load(warp.get_device(device))
        if exec_ is None:
            raise RuntimeError(f"Failed to load module for kernel '{kernel.key}'")
        queried.append(kernel.module)
        return 64, 2

    monkeypatch.setattr(warp, "get_suggested_block_size", cuda_like_query)
    step = warp_kernels._mujoco_warp_step(task.mj_model, options, **handed[0])
    again = {m.name for group in warp_kernels.listed_modules(step).values() for m in group}
    assert any("broadphase" in module.name for module in queried)
    assert again == listed
    assert warp.get_suggested_block_size is cuda_like_query  # (put back after the listing)


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
    starts on another thread and the caller goes on at once; ``wait_ready`` waits for it and
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


def test_the_modules_are_compiled_once_each_over_the_threads_and_a_failure_stops_them(
    monkeypatch,
):
    import threading

    import warp

    from td3_jax.envs import warp_kernels

    loaded = []

    def force_load(device, modules, block_dim, max_workers):
        assert max_workers == 0 and len(modules) == 1
        if modules[0] == "bad":
            raise RuntimeError("nvrtc: error")
        loaded.append((modules[0], block_dim))

    monkeypatch.setattr(warp, "force_load", force_load)
    groups = {None: [f"m{i}" for i in range(20)], 64: ["m0", "x"]}
    assert warp_kernels._compile_modules(groups, workers=3) == 22
    assert sorted(loaded, key=str) == sorted(
        [(f"m{i}", None) for i in range(20)] + [("m0", 64), ("x", 64)], key=str
    )
    loaded.clear()
    with pytest.raises(RuntimeError, match="nvrtc"):
        warp_kernels._compile_modules({None: ["bad", *(f"m{i}" for i in range(50))]}, workers=1)
    assert loaded == []  # (one thread: nothing taken after the failure)
    cancel = threading.Event()
    cancel.set()  # (a run that ended: nothing more is started, and the count says so)
    assert warp_kernels._compile_modules({None: ["m1", "m2"]}, workers=2, cancel=cancel) == 0
    assert loaded == []


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
