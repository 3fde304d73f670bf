"""benchmarks.startup times the start-up ``td3-jax train`` has: over the devices the command
would take (one GPU for MuJoCo Warp physics on a host of several)."""

from __future__ import annotations

import dataclasses

import pytest

from benchmarks import startup
from td3_jax.config.schema import TrainConfig

T1 = TrainConfig(env="playground/T1JoystickFlatTerrain")


@pytest.mark.parametrize(
    ("cfg", "resolved", "asked", "devices"),
    [(T1, "warp", None, 1), (T1, "jax", None, None), (T1, "warp", 2, 2),
     (dataclasses.replace(T1, impl="jax"), "jax", None, None),
     (TrainConfig(env="brax/ant"), "warp", None, None)],
)  # fmt: skip
def test_the_devices_are_those_train_takes(monkeypatch, cfg, resolved, asked, devices):
    seen = []
    monkeypatch.setattr(startup.physics, "resolve", lambda impl: seen.append(impl) or resolved)
    assert startup.run_devices(cfg, asked) == devices
    if seen:  # (the impl asked for, as train asks for it: None lets Warp be chosen)
        assert seen == [cfg.impl]
