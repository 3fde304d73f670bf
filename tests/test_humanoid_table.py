"""benchmarks/humanoid_table.py: which runs count at the table's env steps, one per seed, and
their IQM against a hand-computed one."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

_SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "humanoid_table.py"


@pytest.fixture(scope="module")
def humanoid_table():
    spec = importlib.util.spec_from_file_location("humanoid_table", _SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
        config = {"pushes": pushes, "domain_randomization": False, **options}
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


def test_a_run_with_an_option_is_a_row_of_its_own(humanoid_table, tmp_path):
    """Seed 0 with --return-bound 5 on [-5, 5] does not replace seed 0 of the preset, and its
    row names the option; options left at their defaults (None, False, 0.0) name nothing."""
    off = dict(return_bound=None, critic_feature_norm=False, lr_final_fraction=0.0)
    rb = dict(off, return_bound=5.0, v_min=-5.0, v_max=5.0)
    both = dict(off, return_bound=2.5, critic_feature_norm=True, v_min=-2.0, v_max=2.0)
    files = [_run(tmp_path, "plain", 0, {100: 1.0}, "off", **off),
             _run(tmp_path, "rb", 0, {100: 3.0}, "off", **rb),
             _run(tmp_path, "both", 0, {100: 4.0}, "off", **both)]  # fmt: skip
    finals = [humanoid_table.final_of(path, 100) for path in files]
    settings = [row.split(" | ")[1:3] for row in humanoid_table.table(finals).splitlines()[2:]]
    assert sorted(settings) == [
        ["pushes off, DR off", "0: 1.0"],
        ["pushes off, DR off, return_bound 2.5 on [-2, 2], critic_feature_norm", "0: 4.0"],
        ["pushes off, DR off, return_bound 5 on [-5, 5]", "0: 3.0"],
    ]
