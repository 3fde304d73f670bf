"""The presets as data: every preset, the defaults and the device defaults give exactly the
TrainConfig recorded in data/presets.json (written from the presets before they became a base
with overrides and ``seed-ddpg-pendulum`` was renamed), field by field; a former name still
works and says in one line what it is called now."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from td3_jax.config.presets import NAMES, PRESETS, RENAMED, device_defaults, preset

RECORDED = json.loads((Path(__file__).parent / "data" / "presets.json").read_text())


def as_recorded(cfg) -> dict:
    """A config as the JSON fixture holds it (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


@pytest.mark.parametrize("recorded_name", sorted(RECORDED["presets"]))
def test_every_preset_keeps_its_recorded_values(recorded_name):
    name = RENAMED.get(recorded_name, recorded_name)
    assert as_recorded(preset(name)) == RECORDED["presets"][recorded_name]


def test_the_presets_are_the_recorded_ones_under_their_current_names():
    current = {RENAMED.get(name, name) for name in RECORDED["presets"]}
    assert set(NAMES) == current
    assert set(PRESETS) == current | set(RENAMED)
    assert not set(RENAMED) & set(NAMES)


def test_the_defaults_keep_their_recorded_values():
    assert as_recorded(preset(None)) == RECORDED["default"]


@pytest.mark.parametrize("key", sorted(RECORDED["device_defaults"]))
def test_device_defaults_keep_their_recorded_values(key):
    env, _, accelerator = key.partition(" accelerator=")
    cfg = device_defaults(env, accelerator == "True")
    assert as_recorded(cfg) == RECORDED["device_defaults"][key]


def test_a_former_name_gives_its_preset_and_says_once_that_it_was_renamed(capsys):
    cfg = preset("seed-ddpg-pendulum")
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith("\n")
    assert "'seed-ddpg-pendulum' was renamed 'ddpg-pendulum'" in err
    assert cfg == preset("ddpg-pendulum")
    assert capsys.readouterr().err == ""  # the current name says nothing


def test_the_command_line_takes_a_former_name_and_says_it_was_renamed(capsys):
    from td3_jax.cli import main

    main(["presets", "seed-ddpg-pendulum"])
    out, err = capsys.readouterr()
    assert err.strip().splitlines() == [
        "td3-jax: preset 'seed-ddpg-pendulum' was renamed 'ddpg-pendulum' (the old name still "
        "works)"
    ]
    assert out.startswith("seed-ddpg-pendulum: ") and "--algo ddpg" in out
