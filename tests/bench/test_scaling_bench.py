"""The host side of benchmarks/scaling.py: the plan of points, speed-up and efficiency, the
collectives read from an HLO module, the outputs (no JAX program is compiled here)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
from benchmarks import scaling  # noqa: E402


def test_plan_sizes_weak_and_strong_points_and_skips_missing_devices(capsys):
    args = scaling.parse(["--env", "brax/ant", "--devices", "1", "2", "4", "8"])
    points = scaling.plan(args, available=4)
    assert "skipping --devices [8]" in capsys.readouterr().out
    weak = [(p["devices"], p["num_envs"], p["batch_size"]) for p in points if p["mode"] == "weak"]
    strong = [(p["devices"], p["num_envs"], p["batch_size"]) for p in points
              if p["mode"] == "strong"]  # fmt: skip
    assert weak == [(1, 4096, 8192), (2, 8192, 16384), (4, 16384, 32768)]
    assert strong == [(1, 16384, 32768), (2, 16384, 32768), (4, 16384, 32768)]
    assert {p["replay_shards"] for p in points} == {4}  # device-local replay at every count


def test_smoke_shrinks_every_size():
    args = scaling.parse(["--smoke"])
    assert (args.envs_per_device, args.batch_per_device, args.iterations) == (16, 64, 4)
    assert (args.global_envs, args.global_batch) == (64, 256)


def test_speedup_and_efficiency_against_the_one_device_point_of_the_same_mode():
    rows = [
        {"env": "e", "mode": "weak", "devices": 1, "env_steps_per_s": 100.0, "samples_per_s": 10.0},
        {"env": "e", "mode": "weak", "devices": 4, "env_steps_per_s": 360.0, "samples_per_s": 30.0},
        {"env": "e", "mode": "strong", "devices": 1, "error": "RESOURCE_EXHAUSTED"},
        {"env": "e", "mode": "strong", "devices": 2, "env_steps_per_s": 50.0, "samples_per_s": 5.0},
    ]  # fmt: skip
    scaling.add_ratios(rows)
    assert rows[0]["speedup_env_steps"] == 1.0 and rows[0]["efficiency_samples"] == 1.0
    assert rows[1]["speedup_env_steps"] == pytest.approx(3.6)
    assert rows[1]["efficiency_env_steps"] == pytest.approx(0.9)
    assert rows[1]["speedup_samples"] == pytest.approx(3.0)
    assert rows[1]["efficiency_samples"] == pytest.approx(0.75)
    assert rows[3]["speedup_env_steps"] is None  # its 1-device point failed


HLO = """
  %all-reduce.178 = (f32[2,256,35]{2,1,0}, f32[2,256]{1,0}, f32[]) all-reduce(%a, %b, %c), channel_id=3, metadata={op_name="jit(_lone_chunk)/while/body/transpose(jvp(CriticEnsemble))"}
  %add.1 = f32[8]{0} add(%x, %y)
  %all-gather-start = (s32[1,1]{1,0}, s32[1,4]{1,0}) all-gather-start(%p), channel_id=27
  %all-gather-done = s32[1,4]{1,0} all-gather-done(%all-gather-start)
  %ar = pred[16]{0} all-reduce(%q), channel_id=5
"""  # noqa: E501


def test_collectives_are_read_with_their_sizes():
    found = scaling.collectives(HLO)
    assert [f["op"] for f in found] == ["all-reduce", "all-gather", "all-reduce"]
    assert found[0]["bytes"] == (2 * 256 * 35 + 2 * 256 + 1) * 4
    assert "CriticEnsemble" in found[0]["op_name"]
    assert found[1]["bytes"] == 4 * 4  # the async start's result (its operand listed first)
    assert found[2]["bytes"] == 16  # pred: a byte each
    summary = scaling.summarize_collectives(found)
    assert summary["all-reduce"] == {"count": 2, "bytes": found[0]["bytes"] + 16}


def test_outputs_hold_every_row_and_the_failure(tmp_path):
    meta = {"date": "d", "platform": "gpu", "device_kind": "H200", "device_count": 2,
            "versions": {"jax": "0.11.2"}, "commit": "abc", "iterations": 50, "jobs": 1,
            "command": "scaling.py"}  # fmt: skip
    good = {"env": "brax/ant", "mode": "weak", "devices": 1, "num_envs": 4096,
            "batch_size": 8192, "env_steps_per_s": 400000.0, "updates_per_s": 1500.0,
            "samples_per_s": 1.2e7, "compile_chunk_s": 30.0}  # fmt: skip
    bad = {"env": "brax/ant", "mode": "weak", "devices": 2, "num_envs": 8192,
           "batch_size": 16384, "error": "XlaRuntimeError: RESOURCE_EXHAUSTED"}  # fmt: skip
    rows = [good, bad]
    scaling.add_ratios(rows)
    scaling.write_outputs(tmp_path, meta, rows)
    assert json.loads((tmp_path / "scaling.json").read_text())["rows"][1]["error"].endswith(
        "RESOURCE_EXHAUSTED"
    )
    csv_lines = (tmp_path / "scaling.csv").read_text().splitlines()
    assert len(csv_lines) == 3 and csv_lines[0].startswith("env,mode,devices")
    table = (tmp_path / "scaling.md").read_text()
    assert "400,000" in table and "failed: XlaRuntimeError" in table and "jax 0.11.2" in table


def test_a_point_builds_its_program_over_its_mesh(monkeypatch):
    """The point's program is made with its device mesh, as a training run's is: without it,
    physics that XLA cannot split (MuJoCo Warp) ran whole on every GPU of a two-GPU point
    (each GPU stepped all 4096 T1 environments; 0.93x one GPU instead of 1.35x)."""
    from td3_jax.config import build
    from td3_jax.config.schema import TrainConfig

    seen = {}

    class Built(Exception):
        pass

    def make_population(cfg, population, devices=1, env=None, mesh=None):
        seen.update(devices=devices, mesh=mesh)
        raise Built

    monkeypatch.setattr(build, "make_population", make_population)
    cfg = TrainConfig(env="gymnax/Pendulum-v1", num_envs=4, batch_size=8)
    with pytest.raises(Built):
        scaling.compile_point(cfg, 1)
    assert seen["devices"] == 1
    assert seen["mesh"] is not None and seen["mesh"].size == 1
