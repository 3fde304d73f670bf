"""The presets as data: every preset, the defaults and the device defaults give exactly the
TrainConfig recorded in data/presets.json (written from the presets before they became a base
with overrides), field by field."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from td3_jax.config.presets import PRESETS, device_defaults, preset

RECORDED = json.loads((Path(__file__).parent / "data" / "presets.json").read_text())


def as_recorded(cfg) -> dict:
    """A config as the JSON fixture holds it (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


@pytest.mark.parametrize("name", sorted(RECORDED["presets"]))
def test_every_preset_keeps_its_recorded_values(name):
    assert as_recorded(preset(name)) == RECORDED["presets"][name]


def test_no_preset_is_missing_from_the_record():
    assert set(PRESETS) <= set(RECORDED["presets"])


def test_the_defaults_keep_their_recorded_values():
    assert as_recorded(preset(None)) == RECORDED["default"]


@pytest.mark.parametrize("key", sorted(RECORDED["device_defaults"]))
def test_device_defaults_keep_their_recorded_values(key):
    env, _, accelerator = key.partition(" accelerator=")
    cfg = device_defaults(env, accelerator == "True")
    assert as_recorded(cfg) == RECORDED["device_defaults"][key]
