"""The multi-process rehearsal (benchmarks.multiprocess): 2 CPU processes x 2 forced host
devices through jax.distributed (gloo collectives) against 1 process x 4 devices.

One end-to-end run (about a minute on 2 cores: three processes compile the tiny Pendulum
program) and unit tests of the comparison it reports.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


from benchmarks import multiprocess as mp  # noqa: E402


def _record(**changes) -> dict:
    base = {"env_steps": 256, "updates": 32, "devices": 4, "critic_loss": 0.5,
            "actor_loss": -1.0, "q_mean": 2.0, "target_mean": 2.0, "eval_return_mean": -1500.0,
            "eval_return_min": -1600.0, "eval_return_max": -1400.0}  # fmt: skip
    return {**base, **changes}


def test_identical_records_compare_equal():
    result = mp.compare([_record(), _record(env_steps=512)], [_record(), _record(env_steps=512)],
                        rtol=0.0, atol=0.0)  # fmt: skip
    assert result["equal"] and result["counts_equal"]
    assert result["max_abs_diff"] == 0.0
    assert result["quantities"]["critic_loss"]["multi"] == [0.5, 0.5]


def test_a_difference_is_measured_and_judged_against_the_tolerance():
    multi, single = [_record(critic_loss=0.5 + 1e-3)], [_record()]
    loose = mp.compare(multi, single, rtol=0.0, atol=2e-3)
    tight = mp.compare(multi, single, rtol=1e-4, atol=1e-5)
    q = tight["quantities"]["critic_loss"]
    assert q["max_abs_diff"] == pytest.approx(1e-3)
    assert q["max_rel_diff"] == pytest.approx(1e-3 / (0.5 + 1e-3))
    assert loose["equal"] and not tight["equal"] and not q["within"]
    assert tight["quantities"]["actor_loss"]["within"]


def test_counts_must_match_exactly():
    result = mp.compare([_record(updates=31)], [_record()], rtol=1.0, atol=1.0)
    assert not result["counts_equal"] and not result["equal"]
    assert not mp.compare([_record()], [_record(), _record()], 1.0, 1.0)["equal"]


def test_nan_on_both_sides_is_equal_on_one_side_is_not():
    assert mp.compare([_record(q_mean=math.nan)], [_record(q_mean=math.nan)], 0, 0)["equal"]
    one_sided = mp.compare([_record(q_mean=math.nan)], [_record()], 1.0, 1.0)
    assert not one_sided["equal"]
    assert one_sided["quantities"]["q_mean"]["max_abs_diff"] == math.inf
    # metrics.jsonl writes a diverged member's numbers as null
    logged = mp.compare([_record(q_mean=None)], [_record()], 1.0, 1.0)
    assert not logged["equal"] and logged["quantities"]["q_mean"]["max_abs_diff"] == math.inf
    assert mp.compare([_record(q_mean=None)], [_record(q_mean=None)], 0, 0)["equal"]


def test_cpu_processes_see_their_own_device_count():
    env = mp.process_env("cpu", [2, 3])
    assert "--xla_force_host_platform_device_count=2" in env["XLA_FLAGS"]
    assert env["JAX_PLATFORMS"] == "cpu"
    assert not any(k in env for k in ("JAX_COORDINATOR_ADDRESS", "JAX_PROCESS_ID"))


def test_gpu_processes_get_disjoint_gpus(monkeypatch):
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert mp.process_env("gpu", [4, 5, 6, 7])["CUDA_VISIBLE_DEVICES"] == "4,5,6,7"
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,2,1,0")
    assert mp.process_env("gpu", [2, 3])["CUDA_VISIBLE_DEVICES"] == "1,0"


def test_gpu_processes_run_deterministic_ops_unless_told_otherwise(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/d")
    assert mp.process_env("gpu", [0])["XLA_FLAGS"].split() == ["--xla_dump_to=/tmp/d",
                                                                mp.DETERMINISTIC]  # fmt: skip
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_deterministic_ops=false")
    assert mp.process_env("gpu", [0])["XLA_FLAGS"] == "--xla_gpu_deterministic_ops=false"
    monkeypatch.delenv("XLA_FLAGS")
    assert "deterministic" not in mp.process_env("cpu", [0, 1])["XLA_FLAGS"]  # CPUs already are


@pytest.mark.timeout(600)
@pytest.mark.processes
def test_two_processes_of_two_devices_give_the_four_device_numbers(tmp_path):
    """2 x 2 CPU devices through jax.distributed against 1 x 4: same records (up to the
    order of float sums in gloo's all-reduce)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.multiprocess", "--platform", "cpu",
         "--processes", "2", "--devices-per-process", "2", "--out", str(tmp_path)],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:] + proc.stdout[-3000:]
    result = json.loads((tmp_path / "comparison.json").read_text())
    assert result["records"] == [2, 2] and result["counts_equal"]
    assert result["equal"], result["quantities"]
    multi = [json.loads(x) for x in (tmp_path / "multi" / "metrics.jsonl").read_text().splitlines()]
    assert [r["devices"] for r in multi] == [4, 4]
    assert [r["env_steps"] for r in multi] == [256, 512]
    assert (tmp_path / "comparison.md").read_text().count("| True |") == len(mp.COMPARED)


@pytest.mark.timeout(600)
@pytest.mark.processes
def test_an_mjx_environment_trains_in_two_processes(tmp_path):
    """MJX puts models on jax.devices()[0], process 0's device; process 1 must get its own
    (td3_jax.envs.mjx_devices), or lowering its step fails. 2 x 1 against 1 x 2 CPU devices."""
    flags = ["--env", "brax/inverted_pendulum", "--num-envs", "4", "--total-steps", "64",
             "--eval-every", "32", "--warmup-steps", "16", "--batch-size", "16",
             "--updates-per-iter", "1", "--hidden-sizes", "8", "--eval-envs", "2",
             "--buffer-size", "128", "--episode-length", "16", "--replay-shards", "2",
             "--compile-cache", "off"]  # fmt: skip
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.multiprocess", "--platform", "cpu",
         "--processes", "2", "--devices-per-process", "1", "--side-by-side", "--out",
         str(tmp_path), "--", *flags],
        env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:] + proc.stdout[-3000:]
    result = json.loads((tmp_path / "comparison.json").read_text())
    assert result["records"] == [2, 2] and result["equal"], result["quantities"]
