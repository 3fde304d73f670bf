"""benchmarks/humanoid_table.py: which runs count at the table's env steps, one per seed, and
their IQM against a hand-computed one."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from td3_jax.config.presets import preset


@pytest.fixture(scope="module")
def humanoid_table():
    from benchmarks import humanoid_table

    return humanoid_table


#: Preset t1's whole config as config.json holds it (a run of the preset as it is).
_T1 = json.loads(json.dumps(dataclasses.asdict(preset("t1"))))
_ABSENT = object()  # an option so marked is left out of config.json (an older run's file)


def _run(
    folder: Path, name: str, seed: int, returns: dict[int, float], pushes: str | None, **options
):
    """``NAME-metrics.jsonl`` with a record per ``{env_steps: return}`` (and its config, with
    ``options`` in it)."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = [json.dumps({"env": "playground/T1JoystickFlatTerrain", "seed": seed,
                         "env_steps": steps, "eval_return_mean": value})
             for steps, value in returns.items()]  # fmt: skip
    (folder / f"{name}-metrics.jsonl").write_text("\n".join(lines) + "\n")
    if pushes is not None:
        config = {**_T1, "preset": "t1", "pushes": pushes, **options}
        for absent in [n for n, v in options.items() if v is _ABSENT]:
            del config[absent]
        (folder / f"{name}-config.json").write_text(json.dumps(config))
    return folder / f"{name}-metrics.jsonl"


def test_the_table_counts_finished_seeds_once_and_gives_their_iqm(humanoid_table, tmp_path):
    """Seeds with returns 1, 2 and 10 at 100 steps: IQM 3.1667 (each value covers a third of
    the distribution; [0.25, 0.75] keeps 1/12 of 1, 1/3 of 2 and 1/12 of 10: 1.5833 / 0.5).
    A run that stopped short, and an earlier file of a seed run again, do not count; a run
    with pushes on is a row of its own; a run without its config is 'unknown'."""
    files = [
        _run(tmp_path / "a", "s0", 0, {50: 0.5, 100: 7.0}, "off"),  # replaced by b/s0
        _run(tmp_path / "a", "s1", 1, {50: 0.5, 100: 2.0}, "off"),
        _run(tmp_path / "a", "s2", 2, {50: 0.5, 100: 10.0}, "off"),
        _run(tmp_path / "a", "s3", 3, {50: 30.0}, "off"),  # stopped at 50
        _run(tmp_path / "b", "s0", 0, {100: 1.0}, "off"),
        _run(tmp_path / "b", "p0", 0, {100: 5.0}, "default"),
        _run(tmp_path / "b", "n0", 0, {100: 4.0}, None),
    ]
    finals = [f for f in (humanoid_table.final_of(path, 100) for path in files) if f]
    rows = humanoid_table.table(finals).splitlines()[2:]
    off = next(r for r in rows if "pushes off" in r)
    assert "| 0: 1.0, 1: 2.0, 2: 10.0 | 3.2 (3 seeds) | 38.5 | 35.0 |" in off
    assert humanoid_table.iqm([1.0, 2.0, 10.0]) == pytest.approx(1.5833333 / 0.5)
    assert any("pushes default, DR off | 0: 5.0 | 5.0 (1 seed)" in r for r in rows)
    assert any("| unknown | 0: 4.0 |" in r for r in rows)
    assert len(rows) == 3


def test_a_run_that_differs_from_its_preset_is_a_row_of_its_own(humanoid_table, tmp_path):
    """Seed 0 with --return-bound 5 on [-5, 5], one with a residual critic, one with a cosine
    schedule to 0 (the fraction at its default), do not replace seed 0 of the preset, and each
    row names what differs; settings that do not change learning (seed, length, physics
    implementation, evaluation) and settings at the preset's values name nothing; an older
    config.json without a setting counts as its default; no preset: 'preset unknown'."""
    same = dict(
        total_steps=53_248_000, impl="warp", eval_every=1, critic_hidden_sizes=[1024, 512, 256]
    )
    rb = dict(same, return_bound=5.0, v_min=-5.0, v_max=5.0)
    residual = dict(same, critic_network="residual", critic_hidden_sizes=[256, 256])
    cosine = dict(same, lr_schedule="cosine", lr_final_fraction=0.0)
    files = [_run(tmp_path, "plain", 0, {100: 1.0}, "off", **same),
             _run(tmp_path, "rb", 0, {100: 3.0}, "off", **rb),
             _run(tmp_path, "res", 0, {100: 4.0}, "off", **residual),
             _run(tmp_path, "cos", 0, {100: 5.0}, "off", **cosine),
             _run(tmp_path, "old", 1, {100: 6.0}, "off", critic_network=_ABSENT)]  # fmt: skip
    finals = [humanoid_table.final_of(path, 100) for path in files]
    settings = [row.split(" | ")[1:3] for row in humanoid_table.table(finals).splitlines()[2:]]
    assert sorted(settings) == [
        ["pushes off, DR off", "0: 1.0, 1: 6.0"],
        ["pushes off, DR off, critic_hidden_sizes 256 256, critic_network residual", "0: 4.0"],
        ["pushes off, DR off, lr_schedule cosine", "0: 5.0"],
        ["pushes off, DR off, v_min -5.0, v_max 5.0, return_bound 5.0", "0: 3.0"],
    ]
    assert humanoid_table.settings_of({"pushes": "off"}) == "pushes off, DR off, preset unknown"
