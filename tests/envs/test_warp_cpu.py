"""The MuJoCo Warp path end to end on Warp's CPU kernels (``TD3_JAX_WARP_ON_CPU=1``): a tiny T1
run trains on Warp and records it; one whose constraint buffer is too small stops with the
overflow message instead of simulating wrong physics. Skipped where Warp is not installed."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

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
    machine of 8 cores or more (the default there), its head start listed and begun at once,
    as where Warp's cache holds none of it."""
    import threading

    from td3_jax.envs import warp_kernels

    ran_on, real = [], warp_kernels.compile_listed

    def compile_listed(*args, **kwargs):
        ran_on.append(threading.get_ident())
        return real(*args, **kwargs)

    monkeypatch.setattr(warp_kernels, "cores", lambda *args: 8)
    monkeypatch.setattr(warp_kernels, "compile_listed", compile_listed)
    monkeypatch.setattr(warp_kernels, "head_start_cached", lambda: False)
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

    # The precompile's first listing answers a GPU's query itself and lists the module asked
    # about (its default variant), so that it compiles on the threads with the others.
    asked = list(queried)
    queried.clear()
    monkeypatch.setattr(warp_kernels, "_query_loads", lambda kernel, device: True)
    first = warp_kernels.listed_modules(step, answer_queries=False)
    assert queried == []
    assert all(module in first[module.options["block_dim"]] for module in asked)
    assert {m.name for group in first.values() for m in group} == listed


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


def _cli(args: list[str], devices: int) -> subprocess.CompletedProcess:
    """``td3-jax ARGS`` in a fresh process with ``devices`` CPU devices, Warp on the CPU."""
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}",
           "JAX_PLATFORMS": "cpu", physics.WARP_ON_CPU: "1"}  # fmt: skip
    return subprocess.run([sys.executable, "-m", "td3_jax", *args], env=env, capture_output=True,
                          text=True, timeout=1200)  # fmt: skip


def test_a_robot_run_split_over_two_devices_gives_the_one_device_numbers(tmp_path):
    """``--devices 2``: each CPU device steps its own 2 robots and 1 evaluation robot on
    Warp's CPU kernels (:mod:`td3_jax.envs.per_device`); the records equal the one-device
    run's, and the two-device run's checkpoint evaluates on one device."""
    runs = {}
    for devices in (1, 2):
        out = tmp_path / f"devices{devices}"
        proc = _cli([*TINY_T1, "--devices", str(devices), "--out", str(out)], devices)
        assert proc.returncode == 0, proc.stderr[-3000:]
        runs[devices] = [json.loads(line) for line in (out / "metrics.jsonl").open()]
    compared = ("env_steps", "critic_loss", "actor_loss", "q_mean", "eval_return_mean")
    for one, two in zip(runs[1], runs[2], strict=True):
        for name in compared:
            assert two[name] == pytest.approx(one[name], rel=1e-5), name
    evaluated = _cli(["eval", "--run", str(tmp_path / "devices2"), "--episodes", "2"], 1)
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    assert "seed=0" in evaluated.stdout


def test_two_seeds_split_over_two_devices_give_the_one_device_numbers(tmp_path):
    """``--seeds 2 --devices 2``: the members' vmap runs inside the split physics
    (:func:`td3_jax.envs.per_device.members_map`), each device stepping its 2 robots of each
    seed; every seed's record equals the one-device run's."""
    runs = {}
    for devices in (1, 2):
        out = tmp_path / f"devices{devices}"
        proc = _cli([*TINY_T1, "--seeds", "2", "--devices", str(devices), "--out", str(out)],
                    devices)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        runs[devices] = [json.loads(line) for line in (out / "metrics.jsonl").open()]
    compared = {"critic_loss": 1e-3, "actor_loss": 1e-3, "eval_return_mean": 1e-4,
                "eval_return_max": 1e-4}  # fmt: skip
    for one, two in zip(runs[1], runs[2], strict=True):
        assert two["env_steps"] == one["env_steps"]
        for seed_one, seed_two in zip(one["per_member"], two["per_member"], strict=True):
            assert seed_two["seed"] == seed_one["seed"]
            for name, rel in compared.items():
                assert seed_two[name] == pytest.approx(seed_one[name], rel=rel), name


@pytest.mark.processes
def test_a_robot_run_in_two_processes_gives_the_two_device_numbers(tmp_path):
    """Two processes of one CPU device each through ``jax.distributed`` (gloo) against one
    process of two devices (``benchmarks.multiprocess``): each process steps its own block of
    robots on Warp's CPU kernels under the ``shard_map`` over the global mesh, and every record
    agrees (up to the order of the all-reduce's float sums)."""
    flags = [flag for flag in TINY_T1[1:] if flag != "--quiet"] + ["--compile-cache", "off"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]),
           physics.WARP_ON_CPU: "1"}  # fmt: skip
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.multiprocess", "--platform", "cpu", "--processes",
         "2", "--devices-per-process", "1", "--timeout-s", "1200", "--out", str(tmp_path),
         "--", *flags],
        env=env, capture_output=True, text=True, timeout=2600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:] + proc.stdout[-3000:]
    result = json.loads((tmp_path / "comparison.json").read_text())
    assert result["records"] == [2, 2] and result["counts_equal"]
    assert result["equal"], result["quantities"]
    multi = [json.loads(x) for x in (tmp_path / "multi" / "metrics.jsonl").read_text().splitlines()]
    assert [r["devices"] for r in multi] == [2, 2]
