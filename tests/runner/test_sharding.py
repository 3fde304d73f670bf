"""Data parallelism (jax.sharding) and the multi-process runtime, on forced CPU devices.

JAX fixes its device count at import, so each scenario runs in a fresh Python process with
``--xla_force_host_platform_device_count``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
from support import read_records

from td3_jax.cli.local_processes import free_port

TINY = dict(
    num_envs=8,
    total_steps=512,
    eval_every=256,
    warmup_steps=64,
    batch_size=64,
    updates_per_iter=2,
    hidden_sizes=(32, 32),
    eval_envs=4,
    buffer_size=512,
)
TINY_FLAGS = [
    "--num-envs", "8", "--total-steps", "512", "--eval-every", "256", "--warmup-steps", "64",
    "--batch-size", "64", "--updates-per-iter", "2", "--hidden-sizes", "32", "32",
    "--eval-envs", "4", "--buffer-size", "512", "--quiet",
]  # fmt: skip
COMPARED = ("critic_loss", "actor_loss", "q_mean", "target_mean", "eval_return_mean")


def _env(devices: int, **extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    env["JAX_PLATFORMS"] = "cpu"
    env.update(extra)
    return env


def _python(code: str, devices: int) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env=_env(devices),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _assert_same_numbers(a: list[dict], b: list[dict], rtol: float) -> None:
    assert [r["env_steps"] for r in a] == [r["env_steps"] for r in b]
    assert [r["updates"] for r in a] == [r["updates"] for r in b]
    for ra, rb in zip(a, b, strict=True):
        for key in COMPARED:
            assert ra[key] == pytest.approx(rb[key], rel=rtol, abs=1e-4), key


@pytest.fixture(scope="module")
def four_device_runs(tmp_path_factory):
    """The same tiny config on 4 devices and on 1, and a 4-device run resumed on 1 device."""
    out = tmp_path_factory.mktemp("sharding")
    result = _python(
        f"""
        import dataclasses, json, jax
        from jax.sharding import PartitionSpec
        from td3_jax.config.schema import TrainConfig
        from td3_jax.config.build import make_population, members
        from td3_jax.runner.run import train
        from td3_jax.runner.sharding import make_mesh, state_shardings
        cfg = TrainConfig(**{TINY!r})
        train(cfg, "{out}/d4", progress=False, devices=4)
        train(cfg, "{out}/d1", progress=False, devices=1)
        train(cfg, "{out}/resumed", progress=False, devices=4, stop_after_chunks=1)
        train(cfg, "{out}/resumed", progress=False, devices=1, resume=True)
        sliced = dataclasses.replace(cfg, replay_shards=4)
        train(sliced, "{out}/sliced_d4", progress=False, devices=4)
        train(sliced, "{out}/sliced_d1", progress=False, devices=1)
        sliced_program = make_population(sliced, members(sliced))
        sliced_state = jax.jit(
            sliced_program.init,
            out_shardings=state_shardings(sliced_program.abstract_state, make_mesh(4)),
        )()
        program = make_population(cfg, members(cfg))
        shardings = state_shardings(program.abstract_state, make_mesh(4))
        state = jax.jit(program.init, out_shardings=shardings)()
        print(json.dumps({{
            "devices": jax.device_count(),
            "buffer_spec": list(state.buffer.data[0].obs.sharding.spec),
            "buffer_shard_rows": [
                x.data.shape[1] for x in state.buffer.data[0].obs.addressable_shards
            ],
            "env_shard_rows": [s.data.shape[1] for s in state.env_state.obs.addressable_shards],
            "actor_spec": list(jax.tree.leaves(state.agent.actor_params)[0].sharding.spec),
            "sliced_buffer_spec": list(sliced_state.buffer.data[0].obs.sharding.spec),
            "sliced_shard_shapes": [
                list(x.data.shape) for x in sliced_state.buffer.data[0].obs.addressable_shards
            ],
        }}))
        """,
        devices=4,
    )
    return out, result


@pytest.mark.processes
def test_state_is_split_along_envs_and_buffer(four_device_runs):
    _, info = four_device_runs
    assert info["devices"] == 4
    # [member, replay_shards=1, capacity, obs]: one slice, its rows split over the devices
    assert info["buffer_spec"] == [None, None, "data"]
    capacity = TINY["buffer_size"]
    assert info["buffer_shard_rows"] == [1] * 4  # shape[1] is the (unsplit) slice axis
    # --replay-shards 4: each device holds one whole slice of 512 / 4 rows
    assert info["sliced_buffer_spec"] == [None, "data"]
    assert info["sliced_shard_shapes"] == [[1, 1, capacity // 4, 3]] * 4
    assert info["env_shard_rows"] == [TINY["num_envs"] // 4] * 4
    assert info["actor_spec"] == []  # parameters replicated


@pytest.mark.processes
def test_four_devices_give_the_one_device_numbers(four_device_runs):
    out, _ = four_device_runs
    d4, d1 = read_records(out / "d4"), read_records(out / "d1")
    assert [r["devices"] for r in d4] == [4, 4] and [r["devices"] for r in d1] == [1, 1]
    _assert_same_numbers(d4, d1, rtol=1e-3)


@pytest.mark.processes
def test_replay_slices_on_four_devices_give_the_one_device_numbers(four_device_runs):
    out, _ = four_device_runs
    _assert_same_numbers(
        read_records(out / "sliced_d4"), read_records(out / "sliced_d1"), rtol=1e-3
    )


@pytest.mark.processes
def test_checkpoint_from_four_devices_resumes_on_one(four_device_runs):
    out, _ = four_device_runs
    resumed = read_records(out / "resumed")
    assert [r["devices"] for r in resumed] == [4, 1]
    _assert_same_numbers(resumed, read_records(out / "d1"), rtol=1e-3)


@pytest.mark.processes
def test_sizes_that_do_not_divide_are_refused():
    result = _python(
        """
        import json, subprocess, sys
        proc = subprocess.run(
            [sys.executable, "-m", "td3_jax", "train", "--num-envs", "6", "--out", "/tmp/none"],
            capture_output=True, text=True,
        )
        print(json.dumps({"rc": proc.returncode, "err": proc.stderr}))
        """,
        devices=4,
    )
    assert result["rc"] == 2
    assert "--num-envs (6) must be divisible by the number of devices (4)" in result["err"]
    assert "Traceback" not in result["err"]


@pytest.mark.processes
def test_two_processes_through_the_distributed_runtime(tmp_path, four_device_runs):
    """2 processes x 2 CPU devices, gloo collectives: the 1-device run's numbers."""
    out, _ = four_device_runs
    port = free_port()
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "td3_jax", "train", *TINY_FLAGS, "--out", str(tmp_path / "mp")],
            env=_env(
                2,
                JAX_COORDINATOR_ADDRESS=f"localhost:{port}",
                JAX_NUM_PROCESSES="2",
                JAX_PROCESS_ID=str(i),
            ),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outputs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outputs, strict=True):
        assert p.returncode == 0, err[-3000:]
    records = read_records(tmp_path / "mp")
    assert [r["devices"] for r in records] == [4, 4]
    _assert_same_numbers(records, read_records(out / "d1"), rtol=1e-3)
    assert sorted(p.name for p in (tmp_path / "mp" / "checkpoints").iterdir()) == ["1", "2"]


@pytest.mark.processes
def test_eval_of_a_four_device_run_on_one_device(four_device_runs):
    out, _ = four_device_runs
    proc = subprocess.run(
        [sys.executable, "-m", "td3_jax", "eval", "--run", str(out / "d4"), "--episodes", "2"],
        env=_env(1),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "seed=0" in proc.stdout


def test_replay_slices_off_whole_devices_are_warned_about():
    """The one-ring layout on several devices gathers every batch onto every device (seen in
    the compiled chunk: no gradient all-reduce, the batch all-reduced instead): a warning."""
    from td3_jax.config.schema import TrainConfig
    from td3_jax.runner.sharding import replay_layout_warning

    cfg = TrainConfig(**TINY)
    assert replay_layout_warning(cfg.replay_shards, 1) is None
    assert replay_layout_warning(8, 4) is None
    message = replay_layout_warning(cfg.replay_shards, 4)
    assert "--replay-shards 1 is not a multiple of the 4 devices" in message
    assert "--replay-shards 4" in message
    assert replay_layout_warning(2, 4) is not None

