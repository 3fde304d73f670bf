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


def test_a_tiny_robot_run_trains_on_warp_and_records_it(warp_on_cpu, tmp_path, capsys):
    out = tmp_path / "run"
    code, stdout, err = main([*TINY_T1, "--out", str(out)], capsys)
    assert code == 0, err
    assert "physics: MuJoCo Warp (--impl warp)" in stdout
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
